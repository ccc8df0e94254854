"""Sessions rendered with lab effects: the written frames against what ``lab.json`` records."""

import cv2
import numpy as np
import pytest
from lab_helpers import phase_shift, radial_power

from schlieren.pipeline.synthetic.lab import LabParams
from schlieren.pipeline.synthetic.phantoms import Phantom
from schlieren.storage import synthetic_io as sio
from schlieren.storage.errors import StoreError
from schlieren.workers.synth import FIRST_FRAME, synthesize

SIZE = (240, 180)
N_RAW = FIRST_FRAME + 1 + 2


def _still(fine, *, t_start, duration, seed, medium, knot_dt):
    """No flow at all: every pixel of a frame moves as the camera does."""
    kt = np.arange(t_start - knot_dt, t_start + duration + 2 * knot_dt, knot_dt)
    return Phantom(fine, kt, lambda i: np.full(fine.shape, medium.refractivity_ambient), medium=medium,
                   name="still")


def _session(path, lab=None, **kw):
    args = dict(cameras=2, phantom=_still, frames=1, size=SIZE, seed=7, noise=0.0, bit_depth=16,
                recon_voxel=0.01, supersample=2, reference_frames=0, lab=lab)
    args.update(kw)
    return synthesize(path, **args)


def _img(path):
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 257.0


def _frame(d, cam, f):
    return _img(d / cam / "frames" / f"{f:05d}.png")


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return _session(tmp_path_factory.mktemp("lab") / "clean").session.parent


def test_motion_in_the_frames_is_the_recorded_motion(tmp_path, clean):
    d = _session(tmp_path / "s", LabParams(motion_offset=0.3, motion_walk=0.1)).session.parent
    rec = sio.read_lab_truth(d / "truth.zarr")
    assert rec["raw_frames"] == N_RAW and rec["params"]["motion_walk"] == 0.1
    for cam in ("cam00", "cam01"):
        truth = rec["cameras"][cam]
        assert truth["shift"].shape == (N_RAW, 2) and truth["homography"].shape == (N_RAW, 3, 3)
        assert np.hypot(*truth["shift"][0]) == pytest.approx(0.3)
        ref = _img(d / cam / "reference.png")
        np.testing.assert_array_equal(ref, _img(clean / cam / "reference.png"))   # recorded at the calibrated pose
        for f in range(FIRST_FRAME, N_RAW):  # the frames before carry the strobe flash
            np.testing.assert_allclose(phase_shift(ref, _frame(d, cam, f)), truth["shift"][f], atol=0.01)
        # the homography's translation at the principal point is the shift
        Hm = truth["homography"][3]
        K = np.array([[1.0, 0, (SIZE[0] - 1) / 2], [0, 1.0, (SIZE[1] - 1) / 2], [0, 0, 1]])
        q = Hm @ K[:, 2]
        np.testing.assert_allclose(q[:2] / q[2] - K[:2, 2], truth["shift"][3], atol=1e-9)


def _row_fit(ref, img, keep):
    """Least squares ``img = a_v ref + b`` over the pixels ``keep``: (a per row, b)."""
    H = ref.shape[0]
    r, i, k = ref * keep, img * keep, keep.astype(float)
    N = np.zeros((H + 1, H + 1))
    N[np.arange(H), np.arange(H)] = (r * r).sum(axis=1)
    N[:H, H] = N[H, :H] = r.sum(axis=1)
    N[H, H] = k.sum()
    x = np.linalg.solve(N, np.r_[(r * i).sum(axis=1), i.sum()])
    return x[:H], x[H]


def test_lamp_vignetting_and_defects_in_the_frames(tmp_path, clean):
    lab = LabParams(flicker_gain=0.03, flicker_offset=2.0, banding=0.02, banding_frequency=120.0, vignetting=0.2,
                    hot_pixels=6, dead_pixels=5, stuck_pixels=4)
    d = _session(tmp_path / "s", lab, line_time=3e-5).session.parent
    rec = sio.read_lab_truth(d)
    for cam in ("cam00", "cam01"):
        t = rec["cameras"][cam]
        ref = _img(d / cam / "reference.png")
        bad = np.zeros(ref.shape, bool)
        for k in ("hot", "dead", "stuck"):
            bad[t[k][:, 0], t[k][:, 1]] = True
        # the single reference is the ideal average: vignetting (against the clean render) and defects only
        ideal = _img(clean / cam / "reference.png")
        ok = ~bad & (ideal > 1.0) & (ideal < 255.0)                       # not clipped
        v, u = np.mgrid[:SIZE[1], :SIZE[0]]
        r2 = (u - (SIZE[0] - 1) / 2) ** 2 + (v - (SIZE[1] - 1) / 2) ** 2
        np.testing.assert_allclose((ref / np.maximum(ideal, 1.0))[ok], (1 - 0.2 * r2 / r2.max())[ok], atol=2e-3)
        for f in range(FIRST_FRAME, N_RAW):
            img = _frame(d, cam, f)
            assert np.all(img[t["hot"][:, 0], t["hot"][:, 1]] == 255.0)
            assert np.all(img[t["dead"][:, 0], t["dead"][:, 1]] == 0.0)
            np.testing.assert_allclose(img[t["stuck"][:, 0], t["stuck"][:, 1]], t["stuck_value"], atol=0.5 / 257)
            a, b = _row_fit(ref, img, ok & (img > 0.0) & (img < 255.0))
            rows = np.arange(SIZE[1]) * 3e-5
            want = t["gain"][f] * (1 + 0.02 * np.sin(2 * np.pi * 120.0 * rows + t["phase"][f]))
            np.testing.assert_allclose(a, want, atol=2e-4)
            assert b == pytest.approx(t["offset"][f], abs=0.03)


def test_defocus_in_the_reference_is_a_gaussian_of_its_sigma(tmp_path, clean):
    d = _session(tmp_path / "s", LabParams(defocus=0.7)).session.parent
    edges = np.array([0.05, 0.1, 0.15, 0.2, 0.25])
    k = 0.5 * (edges[:-1] + edges[1:])
    for cam in ("cam00", "cam01"):
        ratio = radial_power(_img(d / cam / "reference.png"), edges) / \
            radial_power(_img(clean / cam / "reference.png"), edges)
        np.testing.assert_allclose(ratio, np.exp(-(2 * np.pi * 0.7 * k) ** 2), rtol=0.08)


def test_reference_frames_carry_their_own_flicker(tmp_path):
    lab = LabParams(flicker_gain=0.05, flicker_offset=3.0)
    d = _session(tmp_path / "s", lab, reference_frames=3).session.parent
    ideal = _session(tmp_path / "ideal", None, reference_frames=3).session.parent
    t = sio.read_lab_truth(d)["cameras"]["cam01"]
    for r in range(3):
        x, y = (_img(p / "cam01" / "reference" / f"{r:03d}.png") for p in (ideal, d))
        a, b = _row_fit(x, y, (x > 0) & (x < 255) & (y > 0) & (y < 255))
        np.testing.assert_allclose(a, t["ref_gain"][r], atol=2e-4)
        assert b == pytest.approx(t["ref_offset"][r], abs=0.03)


def test_lab_effects_off_change_nothing_and_keep_the_sensor_noise(tmp_path):
    """All effects at 0 render the clean capture bit for bit; hot pixels alone change only
    their pixels (the lab effects draw from their own generator, not the sensor's)."""
    kw = dict(noise=1.5, bit_depth=8)
    base = _session(tmp_path / "clean", None, **kw).session.parent
    off = _session(tmp_path / "off", LabParams(), **kw).session.parent
    hot = _session(tmp_path / "hot", LabParams(hot_pixels=7), **kw).session.parent
    assert not (off / "lab.json").exists()
    with pytest.raises(StoreError, match="no lab effects"):
        sio.read_lab_truth(off)
    t = sio.read_lab_truth(hot)["cameras"]["cam00"]
    for f in range(N_RAW):
        a, b, c = (cv2.imread(str(x / "cam00" / "frames" / f"{f:05d}.png"), cv2.IMREAD_UNCHANGED)
                   for x in (base, off, hot))
        np.testing.assert_array_equal(a, b)
        diff = np.argwhere(a != c)
        assert {tuple(p) for p in diff} <= {tuple(p) for p in t["hot"]}
        assert np.all(c[t["hot"][:, 0], t["hot"][:, 1]] == 255)
