"""Registration of a frame's background to the reference: a known motion, gain, offset and
row banding are recovered (issue 33), on images rendered from a continuous background
(tests/pipeline/flow_helpers.py: no resampling of the images themselves)."""

from __future__ import annotations

import numpy as np
import pytest
from flow_helpers import NoiseBackground, plume_deflection, render

from schlieren.pipeline.capture import (motion_displacement, normalise_frame, register_background, row_knots,
                                        row_profile)

SHAPE = (192, 256)  # rows, columns
SIZE = (SHAPE[1], SHAPE[0])


@pytest.fixture(scope="module")
def background():
    return NoiseBackground(SHAPE, rng=np.random.default_rng(11), feature_px=1.0)


@pytest.fixture(scope="module")
def reference(background):
    return render(background, SHAPE, noise=0.4, rng=np.random.default_rng(1))


def _moved(m):
    def field(u, v):
        return motion_displacement(m, u, v, SIZE)
    return field


def _rms_error(m_est, m_true) -> float:
    W, H = SIZE
    y, x = np.mgrid[0:H:4, 0:W:4]
    dx, dy = motion_displacement(np.asarray(m_est) - np.asarray(m_true), x, y, SIZE)
    return float(np.sqrt(np.mean(dx * dx + dy * dy)))


@pytest.mark.parametrize("shift", [0.1, 0.3, 1.2])
def test_known_affine_motion_recovered(background, reference, shift):
    # a shift, a rotation of 3e-4 rad, a 1e-4 zoom: 0.1-1.2 px at the centre, ~0.05 px more at the corners
    m = np.array([shift, -0.6 * shift, 1e-4, -3e-4, 3e-4, 1e-4, 0.0, 0.0])
    frame = render(background, SHAPE, _moved(m), noise=1.5, rng=np.random.default_rng(2))
    fit = register_background(reference, frame, model="affine")
    assert fit.converged
    assert _rms_error(fit.motion, m) < 0.005  # px, RMS over the image
    assert fit.motion_sigma < 0.002
    assert fit.noise < 2.5


def test_stop_early_returns_the_coarse_levels_fit(background, reference):
    m = np.array([0.3, -0.2, 0, 0, 0, 0, 0.0, 0.0])
    frame = render(background, SHAPE, _moved(m), noise=1.5, rng=np.random.default_rng(5))
    seen = []
    coarse = register_background(reference, frame, stop_early=lambda fit: seen.append(fit) or True)
    assert seen == [coarse] and coarse.level == 1  # asked once, before the finest level
    assert _rms_error(coarse.motion, m) < 0.02
    full = register_background(reference, frame, stop_early=lambda fit: False)
    assert full.level == 0 and full.samples > coarse.samples
    assert _rms_error(full.motion, m) < 0.005
    assert full.motion_sigma < coarse.motion_sigma


def test_homography_model_recovers_a_tilt(background, reference):
    m = np.array([0.2, 0.1, 0.0, 0.0, 0.0, 0.0, 2e-6, -1.5e-6])  # 0.05 px more at the edges
    frame = render(background, SHAPE, _moved(m), noise=1.0, rng=np.random.default_rng(3))
    fit = register_background(reference, frame, model="homography", photometric=False)
    assert _rms_error(fit.motion, m) < 0.005
    affine = register_background(reference, frame, model="affine", photometric=False)
    assert _rms_error(affine.motion, m) > _rms_error(fit.motion, m)


def test_static_region_keeps_the_plume_out(background, reference):
    m = np.array([0.25, 0.15, 0, 0, 0, 0, 0, 0.0])
    plume = plume_deflection(SHAPE, peak=0.8, width=20.0)

    def both(u, v):
        du, dv = plume(u, v)
        mx, my = motion_displacement(m, u, v, SIZE)
        return du + mx, dv + my

    frame = render(background, SHAPE, both, noise=1.0, rng=np.random.default_rng(4))
    static = np.ones(SHAPE, bool)
    static[:, 80:176] = False  # the plume's columns (centred, about 40 px either side)
    fit = register_background(reference, frame, static=static)
    assert not fit.fallback
    assert _rms_error(fit.motion, m) < 0.005
    # without a static region, the robust fit over every pixel still lands near it
    every = register_background(reference, frame)
    assert _rms_error(every.motion, m) < 0.03


def test_gain_offset_and_banding_recovered_and_removed(background, reference):
    rows = np.arange(SHAPE[0])[:, None]
    gain = 1.02 * (1 + 0.01 * np.sin(2 * np.pi * rows / 300.0 + 1.0))
    offset = 1.0 + 0.5 * np.cos(2 * np.pi * rows / 300.0)
    clean = render(background, SHAPE, noise=1.0, rng=np.random.default_rng(5))
    lit = (gain * clean + offset).astype(np.float32)
    fit = register_background(reference, lit, banding_rows=32)
    g, o = fit.photometric.profiles(SHAPE[0])
    assert np.max(np.abs(g - gain[:, 0])) < 0.003
    assert np.max(np.abs(o - offset[:, 0])) < 0.4  # grey levels (gain and offset trade at the mean, 128)
    level = (g - gain[:, 0]) * 128.0 + (o - offset[:, 0])  # the mean grey level's error
    assert np.max(np.abs(level)) < 0.2
    restored = normalise_frame(lit, fit.photometric)
    assert np.sqrt(np.mean((restored - clean) ** 2)) < 0.15  # grey levels, against 2.6 before
    assert np.sqrt(np.mean((lit - clean) ** 2)) > 2.0
    assert fit.photometric.departs(gain_tolerance=0.002, offset_tolerance=0.1, mean=128.0,
                                   gain_sigma=fit.gain_sigma, level_sigma=fit.level_sigma, significance=10)


def test_an_unchanged_frame_is_not_significant(background, reference):
    frame = render(background, SHAPE, noise=1.5, rng=np.random.default_rng(6))
    fit = register_background(reference, frame)
    ph = fit.photometric
    assert not ph.departs(gain_tolerance=0.0, offset_tolerance=0.0, mean=128.0, gain_sigma=fit.gain_sigma,
                          level_sigma=fit.level_sigma, significance=10)
    assert np.max(np.abs(fit.motion[:2])) < 10 * fit.motion_sigma


def test_row_profiles_interpolate_between_knots():
    knots = row_knots(481, 48)
    assert knots[0] == 0 and knots[-1] == 480 and np.all(np.diff(knots) <= 48)
    vals = np.arange(len(knots), dtype=float)
    np.testing.assert_allclose(row_profile(vals, knots, knots), vals)
    mid = 0.5 * (knots[1:] + knots[:-1])
    np.testing.assert_allclose(row_profile(vals, knots, mid), vals[:-1] + 0.5)
    assert row_knots(1, 48).shape == (1,)
