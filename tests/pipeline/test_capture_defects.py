"""Hot, dead and stuck pixels found from a camera's frames, and nothing on clean noise (issue 33)."""

from __future__ import annotations

import numpy as np
import pytest
from flow_helpers import NoiseBackground, plume_deflection, render

from schlieren.pipeline.capture import DEAD, HOT, STUCK, defect_counts, find_defective_pixels
from schlieren.pipeline.capture.defects import range_chance, stuck_decidable

SHAPE = (144, 192)


@pytest.fixture(scope="module")
def scene():
    bg = NoiseBackground(SHAPE, rng=np.random.default_rng(21), feature_px=0.9)
    clean = render(bg, SHAPE)
    return clean


def _frames(clean, n, rng, *, noise=1.5):
    return [np.clip(np.round(clean + rng.normal(0, noise, SHAPE)), 0, 255).astype(np.float32) for _ in range(n)]


def test_no_false_positives_on_clean_noise(scene):
    rng = np.random.default_rng(0)
    for n in (1, 4, 16):
        assert not find_defective_pixels(_frames(scene, n, rng)).any()
    # pure sensor noise on a flat grey (no texture at all)
    flat = np.full(SHAPE, 100.0, np.float32)
    assert not find_defective_pixels(_frames(flat, 12, rng, noise=2.0)).any()


def test_hot_dead_and_stuck_pixels_found(scene):
    rng = np.random.default_rng(1)
    frames = _frames(scene, 16, rng)
    rows = np.array([10, 40, 70, 100, 130, 20, 50, 80, 110, 25])
    cols = np.array([15, 45, 75, 105, 135, 165, 20, 60, 100, 140])
    kinds = np.array([HOT, HOT, HOT, HOT, DEAD, DEAD, DEAD, STUCK, STUCK, STUCK])
    for img in frames:
        img[rows[kinds == HOT], cols[kinds == HOT]] = 255.0
        img[rows[kinds == DEAD], cols[kinds == DEAD]] = 0.0
        img[rows[kinds == STUCK], cols[kinds == STUCK]] = scene[rows[kinds == STUCK], cols[kinds == STUCK]].round()
    d = find_defective_pixels(frames)
    found = d[rows, cols]
    assert np.all(found != 0)
    assert np.all(found[kinds == STUCK] & STUCK)
    flagged = np.argwhere(d != 0)
    assert len(flagged) == len(rows)  # the neighbours of hot pixels are not flagged
    c = defect_counts(d)
    assert c["stuck"] == 3 and c["hot"] + c["dead"] >= 7


def test_stuck_needs_enough_frames(scene):
    rng = np.random.default_rng(2)
    frames = _frames(scene, 4, rng)
    for img in frames:
        img[60, 60] = 123.0
    assert not find_defective_pixels(frames)[60, 60] & STUCK
    with pytest.raises(ValueError):
        find_defective_pixels([])


# ---------------------------------------------------------------------------------------
# the stuck test's false alarms, controlled for the number of frames
# ---------------------------------------------------------------------------------------
FLOW_SHAPE = (192, 256)


@pytest.fixture(scope="module")
def flowing():
    """A camera's clean views: 16 of the reference (no flow), and 16 of a plume whose
    deflection (peak up to 0.8 px) changes from frame to frame."""
    bg = NoiseBackground(FLOW_SHAPE, rng=np.random.default_rng(31), feature_px=1.0)
    rng = np.random.default_rng(32)
    still = render(bg, FLOW_SHAPE)
    moving = [render(bg, FLOW_SHAPE, plume_deflection(FLOW_SHAPE, peak=p)) for p in rng.uniform(-0.8, 0.8, 16)]
    return still, moving


def _camera_frames(flowing, n, rng, *, noise=1.5):
    """``n`` frames as the run reads them: up to 4 reference frames, then capture frames;
    8-bit values with ``noise`` grey levels of sensor noise."""
    still, moving = flowing
    n_ref = min(4, n // 2)
    clean = [still] * n_ref + moving[: n - n_ref]
    return [np.clip(np.round(c + rng.normal(0, noise, FLOW_SHAPE)), 0, 255).astype(np.float32) for c in clean]


@pytest.mark.parametrize("n", [6, 9, 16])
def test_a_clean_camera_has_no_defective_pixels_whatever_the_number_of_frames(flowing, n):
    """With 6 or 9 frames of a quantised sensor some normal pixels repeat one value in every
    frame (at 1.5 grey levels about 1 in 2000 and 1 in 10^5); none is taken for stuck."""
    for seed in range(3):
        frames = _camera_frames(flowing, n, np.random.default_rng(100 * n + seed))
        assert not find_defective_pixels(frames).any(), (n, seed)


@pytest.mark.parametrize("n", [9, 16])
def test_stuck_pixels_in_the_flow_and_hot_and_dead_ones_found_with_few_frames(flowing, n):
    """Stuck pixels (one value in every frame) where their neighbours vary with the noise and
    the plume's deflections are found from 9 frames on; hot and dead pixels too; nothing else."""
    still, moving = flowing
    clean = np.stack([still] * min(4, n // 2) + moving[: n - min(4, n // 2)])
    sd = clean.std(axis=0)
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    from scipy.ndimage import minimum_filter

    varies = minimum_filter(sd, footprint=ring) > 4.0  # every neighbour moves with the flow
    varies[:2], varies[-2:], varies[:, :2], varies[:, -2:] = False, False, False, False
    rng = np.random.default_rng(40 + n)
    hot_at, dead_at = np.array([[20, 30], [100, 200], [150, 60]]), np.array([[60, 220], [170, 120]])
    stuck_at = []  # apart from each other and from the hot and dead pixels (whose neighbours vary)
    for p in np.argwhere(varies)[rng.permutation(np.count_nonzero(varies))]:
        if all(np.abs(p - q).max() > 2 for q in [*stuck_at, *hot_at, *dead_at]):
            stuck_at.append(p)
        if len(stuck_at) == 6:
            break
    stuck_at = np.array(stuck_at)
    frames = _camera_frames(flowing, n, rng)
    for img in frames:
        img[tuple(stuck_at.T)] = still[tuple(stuck_at.T)].round()
        img[tuple(hot_at.T)] = 255.0
        img[tuple(dead_at.T)] = 0.0
    d = find_defective_pixels(frames)
    assert np.all(d[tuple(stuck_at.T)] & STUCK)
    assert np.all(d[tuple(hot_at.T)] == HOT) and np.all(d[tuple(dead_at.T)] == DEAD)
    assert np.count_nonzero(d) == len(stuck_at) + len(hot_at) + len(dead_at)


def test_stuck_needs_frames_enough_for_the_noise(scene):
    """Without a flow (neighbours varying by the noise alone) a stuck pixel is told from a
    normal one only with frames enough for the image's size: 16 at 1.5 grey levels for a
    small image, not 9 (:func:`stuck_decidable` says which beforehand)."""
    for n, found in ((9, False), (16, True)):
        frames = _frames(scene, n, np.random.default_rng(50 + n))
        for img in frames:
            img[60, 60] = 123.0
        assert bool(find_defective_pixels(frames)[60, 60] & STUCK) is found
        assert stuck_decidable(n, np.sqrt(1.5 ** 2 + 1 / 12), SHAPE[0] * SHAPE[1]) is found


def test_range_chance_against_sampled_pixels():
    """The chance that n quantised normal values span at most R levels, against 4 x 10^5 drawn
    pixels (the worst of the pixel's means on a level and half way), and unquantised."""
    rng = np.random.default_rng(60)
    for n, s in ((3, 0.7), (6, 1.5), (9, 1.5)):
        for mu in (0.0, 0.5):
            x = np.round(rng.normal(mu, s, size=(400_000, n)))
            r = x.max(axis=1) - x.min(axis=1)
            for R in (0, 1, 2):
                p = float((r <= R).mean())
                assert float(range_chance(R, s, n)) >= p - 4 * np.sqrt(p * (1 - p) / len(r)) - 1e-6, (n, s, mu, R)
            assert float(range_chance(0, s, n)) == pytest.approx(max(float((r <= 0).mean()), 0), rel=0.6, abs=1e-4) \
                if mu == 0.0 else True
    x = rng.normal(0, 1.3, size=(400_000, 5))
    p = float((x.max(axis=1) - x.min(axis=1) <= 1.0).mean())
    assert float(range_chance(1.0, 1.3, 5, quantum=0)) == pytest.approx(p, rel=0.03)


@pytest.mark.parametrize("shape", [(1080, 1440), (7, 9), (8, 6), (1, 1), (3, 1)])
def test_the_residual_median_is_numpys_bit_for_bit(shape):
    from schlieren.pipeline.capture._defects_kernels import abs_median_every_second

    rng = np.random.default_rng(sum(shape))
    for r in (rng.normal(size=shape).astype(np.float32),
              np.round(rng.normal(size=shape) * 3).astype(np.float32),  # many ties, zeros of both signs
              -np.abs(rng.normal(size=shape)).astype(np.float32) * 1e-30):
        want = np.median(np.abs(r[::2, ::2]))
        got = abs_median_every_second(r)
        assert np.float32(got) == want and isinstance(got, float)
