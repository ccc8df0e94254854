"""A reference of few frames topped up with the capture's frames where nothing flows (issue 33):
against the noise-free background, its noise on the static pixels drops as the frame count's
square root and its mean does not move; the plume's pixels keep the recorded reference."""

from __future__ import annotations

import numpy as np
import pytest
from flow_helpers import NoiseBackground, plume_deflection, render

from schlieren.pipeline.capture import (CaptureParams, motion_displacement, sample_region, topup_reference,
                                        warp_to_reference)
from schlieren.pipeline.flow import FlowParams, prepare_reference

SHAPE = (192, 256)
SIZE = (SHAPE[1], SHAPE[0])
FLOW = FlowParams(window=9, factor=2, auto_factor=False)
NOISE = 2.0  # grey levels per frame
N_REF, K = 3, 13


@pytest.fixture(scope="module")
def background():
    return NoiseBackground(SHAPE, rng=np.random.default_rng(31), feature_px=1.0)


def _static():
    s = np.ones(SHAPE, bool)
    s[:, 70:186] = False
    return s


def _motions(rng, k):
    """A sub-pixel random walk of the camera from a 0.3 px offset, with a small rotation."""
    m = np.zeros((k, 8))
    m[:, :2] = np.array([0.3, -0.2]) + np.cumsum(rng.normal(0.0, 0.05, (k, 2)), axis=0)
    m[:, 3] = -1e-4
    m[:, 4] = 1e-4
    return m


def _capture(background, rng, motions, plume=None):
    """Frames of the camera moved by each motion, seeing ``plume`` through other pixels too, with
    lamp flicker (gain and offset per frame)."""
    frames = []
    for m in motions:
        def seen(u, v, m=m):
            mx, my = motion_displacement(m, u, v, SIZE)
            if plume is None:
                return mx, my
            du, dv = plume(u + mx, v + my)
            return du + mx, dv + my
        img = render(background, SHAPE, seen, noise=NOISE, rng=rng)
        frames.append((rng.uniform(0.97, 1.03) * img + rng.uniform(-2.0, 2.0)).astype(np.float32))
    return frames


def _topped(background, seed, plume=None):
    rng = np.random.default_rng(seed)
    refs = [render(background, SHAPE, noise=NOISE, rng=rng) for _ in range(N_REF)]
    ref = np.mean(np.asarray(refs, np.float64), axis=0).astype(np.float32)
    prep = prepare_reference(ref, presmooth=FLOW.presmooth, levels=FLOW.levels)
    static = _static()
    region = sample_region(prep, static=static)
    frames = _capture(background, rng, _motions(rng, K), plume)
    return ref, topup_reference(prep, ref, frames, n_reference=N_REF, static=static, region=region,
                                capture=CaptureParams())


def _shift(err: np.ndarray, truth: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """The displacement (u, v) that best explains ``err`` as ``truth`` moved (least squares)."""
    gy, gx = np.gradient(truth.astype(np.float64))
    A = np.stack([gx[pixels], gy[pixels]], axis=1)
    return np.linalg.lstsq(A, err[pixels].astype(np.float64), rcond=None)[0]


def test_the_static_region_is_topped_up_without_bias(background):
    truth = render(background, SHAPE)
    ref, t = _topped(background, 5)
    assert t.frames == K and t.rejected == 0
    inner = _static()
    inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
    assert 0.8 * N_REF < t.equivalent < 1.25 * N_REF  # the reference weighs its measured noise
    assert np.allclose(t.count[inner], t.equivalent + K)
    before = np.sqrt(np.mean((ref - truth)[inner] ** 2))
    after = np.sqrt(np.mean((t.reference - truth)[inner] ** 2))
    expected = np.sqrt(N_REF / (N_REF + K))  # the noise of N_REF + K frames against N_REF
    # the spline resampling of sub-pixel motions smooths the frames' noise a little
    assert 0.9 * expected < after / before < 1.1 * expected
    err = (t.reference - truth)
    assert abs(np.mean(err[inner])) < 0.05  # grey levels: the flicker normalised away
    # px: on the reference's own grid (its noise's displacement), which the rest of it keeps;
    # the frames moved back by their own registrations alone sit 0.0017 px off it
    assert np.all(np.abs(_shift(err, truth, inner) - _shift(ref - truth, truth, inner)) < 0.0006)


def test_the_plume_does_not_leak_into_the_reference(background):
    plume = plume_deflection(SHAPE, peak=0.5, width=15.0)
    ref, t = _topped(background, 6, plume)
    static = _static()
    np.testing.assert_array_equal(t.reference[~static], ref[~static])
    assert np.all(t.count[~static] == np.float32(t.equivalent))
    assert t.frames == K
    truth = render(background, SHAPE)
    inner = static.copy()
    inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
    assert np.all(np.abs(_shift(t.reference - truth, truth, inner) - _shift(ref - truth, truth, inner)) < 0.0006)


def test_without_a_static_region_the_reference_is_kept(background):
    rng = np.random.default_rng(7)
    ref = render(background, SHAPE, noise=NOISE, rng=rng)
    prep = prepare_reference(ref, presmooth=FLOW.presmooth, levels=FLOW.levels)
    static = np.zeros(SHAPE, bool)
    t = topup_reference(prep, ref, _capture(background, rng, _motions(rng, 3)), n_reference=1, static=static,
                        region=sample_region(prep, static=static), capture=CaptureParams())
    assert t.frames == 0
    np.testing.assert_array_equal(t.reference, ref)


def test_warp_to_reference_undoes_a_known_motion(background):
    m = np.array([0.4, -0.25, 2e-4, -3e-4, 3e-4, -1e-4, 0, 0])
    moved = render(background, SHAPE, lambda u, v: motion_displacement(m, u, v, SIZE))
    back = warp_to_reference(moved, m)
    truth = render(background, SHAPE)
    inner = (slice(8, -8), slice(8, -8))
    assert np.sqrt(np.mean((back - truth)[inner] ** 2)) < 0.05 * np.std(truth)
    assert np.sqrt(np.mean((moved - truth)[inner] ** 2)) > 0.3 * np.std(truth)


def test_a_noise_free_reference_is_kept_and_a_noisy_one_weighs_its_frames(background):
    rng = np.random.default_rng(8)
    static = _static()
    frames = _capture(background, rng, _motions(rng, 6))
    for ref, n, low, high in ((render(background, SHAPE), 1, 20.0, np.inf),
                              (np.mean([render(background, SHAPE, noise=NOISE, rng=rng) for _ in range(N_REF)],
                                       axis=0).astype(np.float32), N_REF, 0.8 * N_REF, 1.25 * N_REF)):
        prep = prepare_reference(ref, presmooth=FLOW.presmooth, levels=FLOW.levels)
        t = topup_reference(prep, ref, frames, n_reference=n, static=static,
                            region=sample_region(prep, static=static), capture=CaptureParams())
        assert low < t.equivalent < high
        if n == 1:  # worth more than topup_below frames: kept bit for bit
            assert t.frames == 0
            np.testing.assert_array_equal(t.reference, ref)
        else:
            assert t.frames == 6
