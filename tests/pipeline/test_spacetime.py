"""Space-time reconstruction: the 3D motion estimate, the warp, the window, and a rigidly
moving field recovered better from a window of frames than from each frame alone."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi

from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.spacetime import (
    SpaceTimeParams,
    motion_compensated_mean,
    support_box,
    volume_motion,
    window_frames,
    window_weights,
    warp_volume,
)
from schlieren.pipeline.tomography import TomoParams, build_geometry, solve_gradient
from schlieren.pipeline.tomography.solve import basis_set

from test_tomography import ring_cameras  # noqa: E402 - the tomography tests' rig


def _texture(shape, seed=0, sigma=2.0):
    rng = np.random.default_rng(seed)
    return ndi.gaussian_filter(rng.normal(size=shape), sigma).astype(np.float32)


def test_volume_motion_recovers_a_known_shift():
    v = _texture((48, 40, 40))
    shift = np.array([2.3, 0.0, -0.7], np.float32)  # voxels, (z, y, x)
    moved = warp_volume(v, np.broadcast_to(-shift, v.shape + (3,)), order=3)  # moved(p + shift) = v(p)
    u = volume_motion(v, moved, levels=3, sigma=3.0, iterations=3)
    inner = u[10:-10, 10:-10, 10:-10].reshape(-1, 3)
    np.testing.assert_allclose(inner.mean(axis=0), shift, atol=0.05)
    assert inner.std(axis=0).max() < 0.1


def test_warp_volume_zero_motion_and_integer_shift():
    v = _texture((12, 10, 9), seed=1)[..., None].repeat(3, axis=-1)
    zero = np.zeros(v.shape[:3] + (3,), np.float32)
    np.testing.assert_allclose(warp_volume(v, zero, order=3), v, atol=1e-5)
    one = zero.copy()
    one[..., 2] = 1.0
    np.testing.assert_allclose(warp_volume(v, one, order=1)[:, :, :-1], v[:, :, 1:], atol=1e-6)


def test_window_is_symmetric_and_stays_in_the_run():
    assert list(window_frames(0, 7, 2)) == [0]
    assert list(window_frames(1, 7, 2)) == [0, 1, 2]
    assert list(window_frames(3, 7, 2)) == [1, 2, 3, 4, 5]
    assert list(window_frames(6, 7, 2)) == [6]
    assert list(window_frames(3, 7, 0)) == [3]
    np.testing.assert_allclose(window_weights([-1, 0, 1], 0.5), [0.25, 0.5, 0.25])
    np.testing.assert_allclose(window_weights([-1, 0, 1], 1.0), [1 / 3] * 3)


def test_support_box():
    s = np.zeros((10, 10, 10), bool)
    s[3:5, 4, 6:8] = True
    assert support_box(s, margin=1) == (slice(2, 6), slice(3, 6), slice(5, 9))
    assert support_box(np.zeros((4, 4, 4), bool)) == (slice(0, 0),) * 3


# --- a rigidly moving field seen by fixed cameras ------------------------------------------

#: Per frame: the field moves this much (metres, x y z): 1.2 voxels up and 0.4 across.
STEP = np.array([0.001, 0.0, 0.003])


def _field(grid, t):
    """Three Gaussian blobs of refractivity, translated by ``t * STEP``: its gradient (1/m,
    x y z components) on the grid."""
    X = grid.centres()
    grad = np.zeros(X.shape, np.float64)
    for c, s, a in (((0.0, 0.0, 0.03), 0.006, -8e-5), ((0.008, -0.004, 0.042), 0.004, -5e-5),
                    ((-0.007, 0.005, 0.05), 0.005, -6e-5)):
        d = X - (np.asarray(c) + t * STEP)
        e = a * np.exp(-(d ** 2).sum(-1) / (2 * s ** 2))
        grad += (-d / s ** 2) * e[..., None]
    return grad


@pytest.fixture(scope="module")
def moving_frames():
    """Five frames of the moving field: the truth's gradients and the per-frame solves from
    rays with independent noise (30 % of the rays' RMS)."""
    grid = Grid((-0.04, -0.04, 0.0), (0.04, 0.04, 0.08), 0.0025)  # 32^3
    cams = ring_cameras(8, grid, image_size=(144, 108))
    geom = build_geometry(cams, grid, FlowGrid((144, 108), 2), params=TomoParams())
    rng = np.random.default_rng(3)
    params = TomoParams(reg_weight=0.004, max_iter=25)
    truth, solved, hulls = [], [], []
    for t in range(-2, 3):
        g = _field(grid, t)
        clean = np.stack([geom.S @ g[..., i].ravel() for i in range(3)], axis=1).reshape(*geom.flow_shape, 3)
        sig = 0.3 * np.sqrt(np.mean(clean[np.abs(clean).sum(-1) > 1e-3 * np.abs(clean).max()] ** 2))
        hull = np.linalg.norm(g, axis=-1) > 0.02 * np.linalg.norm(g, axis=-1).max()
        hull = ndi.binary_dilation(hull, iterations=2)
        sol, _ = solve_gradient(geom, clean + rng.normal(scale=sig, size=clean.shape), hull, params=params)
        truth.append(g)
        solved.append(sol)
        hulls.append(hull)
    return truth, solved, hulls, params


def _rms(a, b, mask):
    return float(np.sqrt(np.mean((a[mask] - b[mask]) ** 2)))


def test_spacetime_recovers_a_rigidly_moving_field_better_than_per_frame(moving_frames):
    """The middle frame from its window of five beats its own solve against the truth; with
    the window switched off (0) the result is the per-frame solve and does not."""
    truth, solved, hulls, tomo = moving_frames
    k, n = 2, len(solved)
    support = basis_set(hulls[k], tomo.hull_dilation)
    errs = {}
    for window in (0, 1, 2):
        params = SpaceTimeParams(window=window, motion_scale=1, motion_window=2.0)
        frames = list(window_frames(k, n, params.window))
        g, info = motion_compensated_mean([solved[j] for j in frames], [j - k for j in frames], support,
                                          params=params)
        errs[window] = _rms(g, truth[k], support)
        if window:  # the motion found is the field's: 1.26 voxels per frame
            assert abs(info.mean_motion[0] - window * 1.26) < 0.35 * window, info
    per_frame = _rms(solved[k], truth[k], support)
    assert errs[0] == pytest.approx(per_frame, rel=1e-6)  # off: exactly the per-frame solve
    assert errs[1] < 0.75 * per_frame, (errs, per_frame)
    assert errs[2] < errs[1], errs
