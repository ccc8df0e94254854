"""The deflection stage with the capture corrections (issue 33): a moved, flickering,
defective capture gives the deflections of the clean one; a clean capture gives exactly
the flow it gave before."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from flow_helpers import NoiseBackground, pixel_truth, plume_deflection, render

from schlieren.pipeline.capture import (FALLBACK, GAIN_UNKNOWN, MOTION_APPLIED, PHOTOMETRIC_APPLIED, SCREENED,
                                        CaptureParams, corrected_deflection, motion_displacement, motion_field,
                                        normalise_frame, register_background, row_knots, stored_fit,
                                        to_reference_grid)
from schlieren.pipeline.flow import FlowParams, deflection_stage, prepare_reference

SHAPE = (192, 256)
SIZE = (SHAPE[1], SHAPE[0])
FLOW = FlowParams(window=9, factor=2, auto_factor=False)


@pytest.fixture(scope="module")
def background():
    return NoiseBackground(SHAPE, rng=np.random.default_rng(31), feature_px=1.0)


@pytest.fixture(scope="module")
def prep(background):
    ref = render(background, SHAPE, noise=0.4, rng=np.random.default_rng(1))
    return prepare_reference(ref, presmooth=FLOW.presmooth, levels=FLOW.levels)


def _static():
    s = np.ones(SHAPE, bool)
    s[:, 70:186] = False
    return s


def _cells(d):
    return np.sqrt(np.nanmean(np.sum(d * d, axis=-1)))


@pytest.mark.parametrize("shift", [0.3, 1.2])  # the flow starts from the motion / the reference is moved
def test_static_scene_with_a_known_motion_gives_no_deflection(background, prep, shift):
    m = np.array([shift, -0.6 * shift, 1e-4, -3e-4, 3e-4, 0.0, 0, 0])
    frame = render(background, SHAPE, lambda u, v: motion_displacement(m, u, v, SIZE), noise=1.5,
                   rng=np.random.default_rng(2))
    d, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.flags & MOTION_APPLIED
    W, H = SIZE
    y, x = np.mgrid[0:H:4, 0:W:4]
    dx, dy = motion_displacement(corr.motion - m, x, y, SIZE)
    assert np.sqrt(np.mean(dx * dx + dy * dy)) < 0.005  # the motion, px RMS over the image
    assert np.abs(np.nanmean(d, axis=(0, 1))).max() < 0.003  # no uniform deflection left
    assert _cells(d) < 0.03  # the flow's own noise (uncompensated: 0.36 px)
    assert _cells(deflection_stage(prep, frame, FLOW)) > 0.3


def test_registration_error_leaves_no_bias_on_the_static_cells(background, prep, monkeypatch):
    # the registration's motion 0.003 px off, and what the flow still shows on the static
    # cells below motion_tolerance: the flow's own fit there removes it all the same, so
    # the static cells keep no uniform deflection (integrated by the masks' potential,
    # 0.003 px is a ramp of 0.2 px x cells across this image)
    import dataclasses

    from schlieren.pipeline.capture import correction

    m = np.array([0.3, -0.2, 0, 0, 0, 0, 0, 0.0])
    frame = render(background, SHAPE, lambda u, v: motion_displacement(m, u, v, SIZE), noise=1.5,
                   rng=np.random.default_rng(8))
    register = correction.register_background

    def off_by(*args, **kwargs):
        fit = register(*args, **kwargs)
        return dataclasses.replace(fit, motion=fit.motion + np.array([0.003, 0, 0, 0, 0, 0, 0, 0]))

    monkeypatch.setattr(correction, "register_background", off_by)
    capture = CaptureParams(motion_tolerance=0.01)
    d, corr = corrected_deflection(prep, frame, FLOW, capture, static=_static())
    assert corr.flags & MOTION_APPLIED
    assert 0.003 < corr.residual < capture.motion_tolerance
    static = _static()[::2, ::2]
    assert np.abs(np.nanmedian(d[static], axis=0)).max() < 0.0005  # px; 0.003 before


def test_clean_capture_keeps_its_flow_bit_for_bit(background, prep):
    frame = render(background, SHAPE, plume_deflection(SHAPE, peak=0.4, width=15.0), noise=1.5,
                   rng=np.random.default_rng(3))
    d, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.flags == SCREENED  # the coarse levels' fit showed nothing to apply: no full-resolution fit
    assert corr.fit.level > 0
    np.testing.assert_array_equal(d, deflection_stage(prep, frame, FLOW))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_small_motion_above_the_tolerance_gets_the_full_registration(background, prep, seed):
    # 0.012 px at the centre: 2.4 motion_tolerance and several of the coarse levels' standard
    # deviations, so the screen passes the frame on to the full-resolution fit
    m = np.array([0.011, -0.005, 0, 0, 0, 0, 0, 0.0])
    frame = render(background, SHAPE, lambda u, v: motion_displacement(m, u, v, SIZE), noise=1.5,
                   rng=np.random.default_rng(40 + seed))
    d, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.flags & MOTION_APPLIED and not corr.flags & SCREENED
    assert corr.fit.level == 0
    W, H = SIZE
    y, x = np.mgrid[0:H:4, 0:W:4]
    dx, dy = motion_displacement(corr.motion - m, x, y, SIZE)
    assert np.sqrt(np.mean(dx * dx + dy * dy)) < 0.005  # px RMS over the image


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_small_gain_change_gets_the_full_registration(background, prep, seed):
    # a 1 % flicker: 5 gain_tolerance, several of the coarse levels' standard deviations
    frame = 1.01 * render(background, SHAPE, noise=1.5, rng=np.random.default_rng(50 + seed))
    d, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.flags & PHOTOMETRIC_APPLIED and not corr.flags & SCREENED
    assert np.abs(corr.fit.photometric.gain - 1.01).max() < 0.003


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_clean_frame_is_screened_out(background, prep, seed):
    frame = render(background, SHAPE, noise=1.5, rng=np.random.default_rng(60 + seed))
    d, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.flags == SCREENED and corr.fit.level > 0
    assert corr.fit.samples < np.count_nonzero(_static())  # only the coarse levels' samples were fitted
    np.testing.assert_array_equal(d, deflection_stage(prep, frame, FLOW))


def test_moved_flickering_capture_gives_the_clean_deflections(background, prep):
    plume = plume_deflection(SHAPE, peak=0.4, width=15.0)
    m = np.array([0.25, 0.15, 0.0, -2e-4, 2e-4, 0.0, 0, 0])

    def camera_turned(u, v):  # the plume is seen through other pixels too: frame(p) = clean(T(p))
        mx, my = motion_displacement(m, u, v, SIZE)
        du, dv = plume(u + mx, v + my)
        return du + mx, dv + my

    rows = np.arange(SHAPE[0])[:, None]
    rng = np.random.default_rng(4)
    clean = render(background, SHAPE, plume, noise=1.5, rng=rng)
    moved = render(background, SHAPE, camera_turned, noise=1.5, rng=rng)
    lab = (1.02 * (1 + 0.01 * np.sin(rows / 40.0)) * moved + 1.0).astype(np.float32)
    truth = pixel_truth(plume, SHAPE)
    t = truth.reshape(SHAPE[0] // 2, 2, SHAPE[1] // 2, 2, 2).mean(axis=(1, 3))
    d_clean = deflection_stage(prep, clean, FLOW)
    d, corr = corrected_deflection(prep, lab, FLOW, static=_static())
    assert corr.flags & MOTION_APPLIED and corr.flags & PHOTOMETRIC_APPLIED
    e_clean, e_lab = _cells(d_clean - t), _cells(d - t)
    assert e_lab < 1.25 * e_clean + 0.002  # px; uncorrected it is 10x the clean error
    d_off, _ = corrected_deflection(prep, lab, FLOW, CaptureParams(motion_model="none", photometric=False),
                                    static=_static())
    assert _cells(d_off - t) > 5 * e_clean


def _lab_frame(background, m, seed):
    """A frame of the plume whose camera moved by ``m``, with flicker and row banding."""
    plume = plume_deflection(SHAPE, peak=0.4, width=15.0)

    def camera_turned(u, v):
        mx, my = motion_displacement(m, u, v, SIZE)
        du, dv = plume(u + mx, v + my)
        return du + mx, dv + my

    rows = np.arange(SHAPE[0])[:, None]
    moved = render(background, SHAPE, camera_turned, noise=1.5, rng=np.random.default_rng(seed))
    return (1.02 * (1 + 0.01 * np.sin(rows / 40.0)) * moved + 1.0).astype(np.float32), pixel_truth(plume, SHAPE)


@pytest.mark.parametrize("m", [[0.25, 0.15, 0.0, -2e-4, 2e-4, 0.0, 0, 0], [0.0] * 8])
def test_a_known_registration_gives_the_flow_of_measuring_it(background, prep, m):
    # the frame's own registration passed in: the same flow and correction bit for bit
    capture = CaptureParams()
    frame, _ = _lab_frame(background, np.array(m), 5)
    d, corr = corrected_deflection(prep, frame, FLOW, capture, static=_static())
    d_known, corr_known = corrected_deflection(prep, frame, FLOW, capture, static=_static(), fit=corr.fit)
    np.testing.assert_array_equal(d_known, d)
    np.testing.assert_array_equal(corr_known.motion, corr.motion)
    assert corr_known.flags == corr.flags and corr_known.residual == corr.residual
    # a registration measured apart, to convergence at full resolution, is used as given
    fit = register_background(prep, frame, static=_static(), presmooth=FLOW.presmooth, levels=FLOW.levels)
    _, corr_fit = corrected_deflection(prep, frame, FLOW, capture, static=_static(), fit=fit)
    assert corr_fit.fit is fit


def test_the_stored_registration_keeps_the_corrections_and_the_flow(background, prep):
    # what a run stores of a moved, flickering frame's correction (motion, float32 profiles
    # and statistics) measures the frame's flow again without registering it: the same
    # corrections applied, the flow within the registration's own noise of the first
    capture = CaptureParams()
    m = np.array([0.25, 0.15, 0.0, -2e-4, 2e-4, 0.0, 0, 0])
    frame, truth = _lab_frame(background, m, 6)
    d, corr = corrected_deflection(prep, frame, FLOW, capture, static=_static())
    assert corr.flags & MOTION_APPLIED and corr.flags & PHOTOMETRIC_APPLIED
    ph = corr.fit.photometric
    fit = stored_fit(corr.motion, np.stack([ph.gain, ph.offset]).astype(np.float32), corr.stats(),
                     row_knots(SHAPE[0], capture.banding_rows))
    d2, corr2 = corrected_deflection(prep, frame, FLOW, capture, static=_static(), fit=fit)
    assert corr2.flags == corr.flags
    assert np.abs(corr2.motion - corr.motion).max() < 1e-3  # the flow's refit finds (almost) nothing left
    assert _cells(d2 - d) < 0.002  # px
    t = truth.reshape(SHAPE[0] // 2, 2, SHAPE[1] // 2, 2, 2).mean(axis=(1, 3))
    assert _cells(d2 - t) < 1.02 * _cells(d - t)
    # a frame whose corrections were not applied keeps them unapplied
    clean = render(background, SHAPE, noise=1.5, rng=np.random.default_rng(7))
    d0, corr0 = corrected_deflection(prep, clean, FLOW, capture, static=_static())
    ph0 = corr0.fit.photometric
    fit0 = stored_fit(corr0.motion, np.stack([ph0.gain, ph0.offset]), corr0.stats(), ph0.knots)
    d0_known, corr0_known = corrected_deflection(prep, clean, FLOW, capture, static=_static(), fit=fit0)
    assert not corr0.flags & (MOTION_APPLIED | PHOTOMETRIC_APPLIED) and corr0_known.flags == corr0.flags
    np.testing.assert_array_equal(d0_known, d0)


def test_small_static_region_falls_back_to_the_low_deflection_cells(background, prep):
    plume = plume_deflection(SHAPE, peak=0.4, width=15.0)
    m = np.array([0.2, -0.1, 0, 0, 0, 0, 0, 0.0])
    frame = render(background, SHAPE, lambda u, v: tuple(a + b for a, b in zip(plume(u, v),
                                                                                   motion_displacement(m, u, v, SIZE))),
                   noise=1.5, rng=np.random.default_rng(5))
    static = np.zeros(SHAPE, bool)
    static[:, :4] = True  # 1.6 % of the image
    d, corr = corrected_deflection(prep, frame, FLOW, CaptureParams(motion_source="background"), static=static)
    assert corr.flags & FALLBACK
    assert np.abs(corr.motion[:2] - m[:2]).max() < 0.01


def test_defective_pixels_get_no_weight_and_no_nan(background):
    # a uniform 0.3 px deflection: hot pixels that stay put pin the flow around them to 0
    frame = render(background, SHAPE, lambda u, v: (np.full_like(u, 0.3), np.zeros_like(v)), noise=1.5,
                   rng=np.random.default_rng(6))
    ref = render(background, SHAPE, noise=0.4, rng=np.random.default_rng(7))
    defects = np.zeros(SHAPE, np.uint8)
    rows, cols = np.array([30, 90, 150, 40]), np.array([40, 200, 120, 230])
    defects[rows, cols] = 1
    off = CaptureParams(motion_model="none", photometric=False)
    d_clean, _ = corrected_deflection(prepare_reference(ref, presmooth=FLOW.presmooth, levels=FLOW.levels), frame, FLOW, off)
    frame[rows, cols] = 255.0
    ref[rows, cols] = 255.0
    prep_hot = prepare_reference(ref, presmooth=FLOW.presmooth, levels=FLOW.levels)
    d, _ = corrected_deflection(prep_hot, frame, FLOW, off, defects=defects)
    assert np.isfinite(d).all()
    d_blind, _ = corrected_deflection(prep_hot, frame, FLOW, off)
    around = np.zeros(d.shape[:2], bool)
    for r, c in zip(rows // 2, cols // 2):
        around[r - 2:r + 3, c - 2:c + 3] = True
    err = np.abs(d - d_clean)[around].mean()
    err_blind = np.abs(d_blind - d_clean)[around].mean()
    assert err_blind > 0.01  # px: pulled towards 0 around the hot pixels
    assert err < 0.5 * err_blind


@pytest.mark.parametrize("invalid_check", [True, False])
@pytest.mark.parametrize("clipped", [False, True])  # a saturated patch: the frame has invalid pixels of its own
def test_prepared_invalid_pixels_give_the_same_flow(background, prep, invalid_check, clipped):
    from schlieren.pipeline.flow import frame_pyramid, prepare_invalid

    frame = render(background, SHAPE, plume_deflection(SHAPE, peak=0.4, width=15.0), noise=1.5,
                   rng=np.random.default_rng(9))
    if clipped:
        frame[60:90, 20:60] = frame.max()
    bad = np.zeros(SHAPE, bool)
    bad[[30, 31, 90, 150], [40, 40, 200, 120]] = True
    bad[100:104, 10:14] = True  # a cluster: empties a cell, filled from its neighbours
    params = FlowParams(window=9, factor=2, auto_factor=False, invalid_check=invalid_check)
    expect = deflection_stage(prep, frame, params, invalid=bad)
    got = deflection_stage(prep, frame, params, invalid=prepare_invalid(prep, bad, params),
                           pyramid=frame_pyramid(prep, frame))
    np.testing.assert_array_equal(got, expect)
    assert prepare_invalid(prep, np.zeros(SHAPE, bool), params) is None


def test_flow_moved_back_onto_the_reference_grid():
    f = 2
    m = np.array([0.6, -0.4, 0, 0, 0, 0, 0, 0.0])  # 0.3 x -0.2 flow cells
    h, w = SHAPE[0] // f, SHAPE[1] // f
    y, x = np.mgrid[0:h, 0:w].astype(float)
    field = lambda yy, xx: np.dstack([np.sin(xx / 7.0), np.cos(yy / 9.0)]).astype(np.float32)
    seen = field(y - 0.2, x + 0.3)  # frame cell q shows the reference's q + m / f
    back = to_reference_grid(seen, m, SIZE, f)
    np.testing.assert_allclose(back[3:-3, 3:-3], field(y, x)[3:-3, 3:-3], atol=2e-3)
    assert motion_field(m, SIZE, f)[0, 0, 0] == pytest.approx(0.6)


@pytest.mark.parametrize("level", [0.0, 255.0])
def test_a_frame_without_a_gain_is_flagged_not_normalised(prep, level):
    """A frame whose gain cannot be estimated (all dark: a lens cap; all clipped white)
    is flagged GAIN_UNKNOWN and left as it is: no division by its zero gain."""
    frame = np.full(SHAPE, level, np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning from a division by zero
        d, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.flags & GAIN_UNKNOWN and not corr.flags & PHOTOMETRIC_APPLIED
    assert not corr.fit.photometric.estimable()
    assert d.shape == (SHAPE[0] // 2, SHAPE[1] // 2, 2)
    with pytest.raises(ValueError, match="cannot be normalised"):
        normalise_frame(frame, corr.fit.photometric)


def test_a_flickering_frame_keeps_its_gain_estimable(background, prep):
    rng = np.random.default_rng(8)
    frame = (0.97 * render(background, SHAPE, noise=1.5, rng=rng) + 2.0).astype(np.float32)
    _, corr = corrected_deflection(prep, frame, FLOW, static=_static())
    assert corr.fit.photometric.estimable() and not corr.flags & GAIN_UNKNOWN
    assert corr.flags & PHOTOMETRIC_APPLIED
