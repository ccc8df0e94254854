"""Strobe sync and rolling-shutter resampling against the timing model's ground truth."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schlieren.pipeline import sync as S
from schlieren.pipeline.sync import motion
from schlieren.pipeline.geometry import FlowGrid

FR = 60.0
LT = 1.54e-5
H = 1080


def strobe_row_means(offset, *, exposure, n_frames=30, height=H, line_time=LT, rng,
                     gain=40.0, noise=0.05, first_frame=0):
    """Row means of a static background with a flash at t = 0 (docs/design.md model)."""
    base = rng.normal(120.0, 15.0, height)
    f = first_frame + np.arange(n_frames)[:, None]
    start = offset + f / FR + np.arange(height)[None, :] * line_time
    lit = (start <= 0.0) & (start + exposure > 0.0)
    rm = base[None, :] + rng.normal(0.0, noise, (n_frames, height)) + gain * lit
    return np.minimum(rm, 255.0), lit


def test_random_offsets_recovered_within_two_line_times():
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(300):
        exposure = rng.uniform(5e-4, 1.0 / FR)
        offset = rng.uniform(-25.0 / FR, -2.0 / FR)
        rm, lit = strobe_row_means(offset, exposure=exposure, rng=rng)
        det = S.detect_flash(rm)
        est = S.offset_from_flash(det, first_frame=0, frame_rate=FR, line_time=LT)
        errors.append(abs(est - offset) / LT)
        # every frame with lit rows is reported as carrying the flash
        assert set(np.flatnonzero(lit.any(axis=1))) <= S.flash_frames(det, first_frame=0)
    errors = np.array(errors)
    assert errors.max() < 2.0, errors.max()
    assert np.median(errors) < 0.5


def test_band_split_over_two_frames_uses_lower_edge_in_second():
    rng = np.random.default_rng(1)
    # flash while rows ~900.. of frame 10 are starting: band runs into frame 11's top
    exposure = 8e-3
    offset = -10 / FR - 900 * LT - 0.3 * LT
    rm, lit = strobe_row_means(offset, exposure=exposure, rng=rng)
    det = S.detect_flash(rm)
    assert det.lit_frames == (10, 11) or det.frame == 10
    est = S.offset_from_flash(det, first_frame=0, frame_rate=FR, line_time=LT)
    assert abs(est - offset) < LT
    assert S.flash_frames(det, first_frame=0) >= set(np.flatnonzero(lit.any(axis=1)))


def test_band_top_cut_at_row_zero():
    rng = np.random.default_rng(2)
    exposure = 12e-3
    # lower edge at row 300 of frame 7; the band started in frame 6's bottom rows
    offset = -7 / FR - 300 * LT - 0.5 * LT
    rm, _ = strobe_row_means(offset, exposure=exposure, rng=rng)
    det = S.detect_flash(rm)
    assert det.frame == 7 and det.first_row == 0 and det.last_row == 300
    assert det.lit_frames == (6, 7)
    assert S.flash_frames(det, first_frame=100) == {106, 107}
    est = S.offset_from_flash(det, first_frame=0, frame_rate=FR, line_time=LT)
    assert abs(est - offset) <= 0.5 * LT + 1e-12


def test_band_ending_in_vertical_blanking():
    rng = np.random.default_rng(3)
    lt = 1.2e-5  # readout 13 ms of a 16.7 ms frame: a 300-line blanking gap
    exposure = 5e-3
    # flash 1 ms after the last row of frame 12 started, i.e. in the blanking gap
    offset = -12 / FR - (H - 1) * lt - 1e-3
    rm, _ = strobe_row_means(offset, exposure=exposure, rng=rng, line_time=lt)
    det = S.detect_flash(rm)
    assert det.cut_bottom and det.frame == 12
    # without the exposure: the middle of the blanking gap (error <= half the gap)
    est = S.offset_from_flash(det, first_frame=0, frame_rate=FR, line_time=lt)
    gap = 1 / FR - H * lt
    assert abs(est - offset) <= 0.5 * gap + lt
    # with the exposure: the upper edge gives it to within a line
    est = S.offset_from_flash(det, first_frame=0, frame_rate=FR, line_time=lt, exposure=exposure)
    assert abs(est - offset) <= lt


def test_search_window_offset_is_added():
    rng = np.random.default_rng(4)
    offset = -47 / FR - 123.5 * LT
    rm, _ = strobe_row_means(offset, exposure=4e-3, rng=rng, first_frame=40, n_frames=20)
    det = S.detect_flash(rm)
    est = S.offset_from_flash(det, first_frame=40, frame_rate=FR, line_time=LT)
    assert abs(est - offset) <= 0.5 * LT + 1e-12
    assert S.flash_frames(det, first_frame=40) == {46, 47}  # band began in 46


def test_no_flash_raises_clear_error():
    rng = np.random.default_rng(5)
    rm, _ = strobe_row_means(+1.0, exposure=1e-3, rng=rng)  # flash before the capture
    with pytest.raises(ValueError, match="no strobe flash"):
        S.detect_flash(rm)
    with pytest.raises(ValueError, match="rolling shutter"):
        S.offset_from_flash(S.detect_flash(strobe_row_means(-0.1, exposure=1e-3, rng=rng)[0]),
                            first_frame=0, frame_rate=FR, line_time=0.0)


def test_output_times_formula():
    offs = [0.001, -0.002, 0.0005]
    t = S.output_times(10, 4, offsets=offs, frame_rate=FR, height=H, line_time=LT)
    expect = (10 + np.arange(4)) / FR + np.mean(offs) + 0.5 * H * LT
    np.testing.assert_allclose(t, expect, rtol=0, atol=1e-15)
    assert t.dtype == np.float64


@settings(max_examples=200, deadline=None)
@given(target=st.floats(0.05, 0.9), offset=st.floats(-0.03, 0.03),
       line_time=st.floats(0.0, 1.5e-5), height=st.integers(2, 1200),
       excl=st.sets(st.integers(0, 60), max_size=3))
def test_frames_needed_brackets_every_row(target, offset, line_time, height, excl):
    f0, f1 = S.frames_needed(target, offset=offset, frame_rate=FR, line_time=line_time,
                             height=height, excluded_frames=excl)
    usable = [f for f in range(f0, f1) if f not in excl]
    for r in (0, height // 3, height - 1):  # brute force: each row's exposure times
        times = offset + np.array(usable) / FR + r * line_time
        assert times.min() <= target + 1e-12 and times.max() >= target - 1e-12


# --------------------------------------------------------------------------------------
# Resampling
# --------------------------------------------------------------------------------------
GRID = FlowGrid((240, 180), 3)          # 60 x 80 flow cells
LT_SMALL = 0.9 / (FR * 180)             # readout spans 90 % of the frame


def blob_field(t, *, speed=2.5, amp=0.8):
    """Smooth plume-like deflection pattern moving up by ``speed`` cells per frame."""
    h, w = GRID.shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    cy = 45.0 - speed * FR * t
    cx = 40.0 + 3.0 * np.sin(2 * np.pi * 2.0 * t)
    g = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 6.0**2))
    return np.stack([amp * (x - cx) / 6.0 * g, amp * (y - cy) / 6.0 * g], -1).astype(np.float32)


def rolling_raw(first, k, offset, **kw):
    """Raw flow fields of frames first..first+k-1: each grid row sampled at its own time."""
    rows = GRID.row_of_cell()
    out = np.empty((k,) + GRID.shape + (2,), np.float32)
    for j in range(k):
        t_rows = offset + (first + j) / FR + rows * LT_SMALL
        for i, t in enumerate(t_rows):
            out[j, i] = blob_field(t, **kw)[i]
    return out


def test_static_field_is_unchanged_by_resampling():
    field = blob_field(0.0)
    raw = np.repeat(field[None], 4, axis=0)
    for method in ("motion", "linear", "nearest"):
        out = S.resample_flow(raw, 5, 6.4 / FR, offset=0.001, frame_rate=FR, line_time=LT_SMALL,
                              flow_grid=GRID, params=S.ResampleParams(method=method))
        np.testing.assert_allclose(out, field, atol=1e-5)


def test_field_linear_in_time_is_interpolated_exactly():
    rows = GRID.row_of_cell()
    A = blob_field(0.0)
    B = np.random.default_rng(0).normal(size=A.shape).astype(np.float32)
    offset = 0.002
    raw = np.stack([A + B * (offset + f / FR + rows[:, None, None] * LT_SMALL)
                    for f in range(3, 7)])
    T = 5.1 / FR
    out = S.resample_flow(raw, 3, T, offset=offset, frame_rate=FR, line_time=LT_SMALL,
                          flow_grid=GRID, params=S.ResampleParams(method="linear"))
    np.testing.assert_allclose(out, A + B * T, atol=1e-5)


@pytest.fixture(scope="module")
def moving_case():
    offset = -0.0041
    f0, f1 = S.frames_needed(0.1, offset=offset, frame_rate=FR, line_time=LT_SMALL,
                             height=180)
    raw = rolling_raw(f0, f1 - f0, offset)
    return offset, f0, raw


def test_motion_resampling_matches_global_shutter_truth(moving_case):
    offset, f0, raw = moving_case
    T = 0.1
    truth = blob_field(T)
    kw = dict(offset=offset, frame_rate=FR, line_time=LT_SMALL, flow_grid=GRID)
    motion = S.resample_flow(raw, f0, T, **kw)
    linear = S.resample_flow(raw, f0, T, params=S.ResampleParams(method="linear"), **kw)
    # "unresampled": the raw frame whose mid-readout is closest to T
    mid = offset + (f0 + np.arange(len(raw))) / FR + 90 * LT_SMALL
    unres = raw[int(np.argmin(np.abs(mid - T)))]

    def rms(a):
        return float(np.sqrt(np.mean(np.sum((a - truth) ** 2, -1))))

    print("rms motion %.4f linear %.4f unresampled %.4f" % (rms(motion), rms(linear), rms(unres)))
    assert rms(motion) < 0.3 * rms(unres), (rms(motion), rms(unres))
    assert rms(motion) < 0.6 * rms(linear), (rms(motion), rms(linear))


def test_excluded_flash_frame_is_never_read(moving_case):
    offset, f0, raw = moving_case
    T = 0.1
    phi = (T - offset - 90 * LT_SMALL) * FR  # frame exposing the middle rows at T
    bad = int(np.floor(phi))
    raw2 = raw.copy()
    raw2[bad - f0] = np.nan
    kw = dict(offset=offset, frame_rate=FR, line_time=LT_SMALL, flow_grid=GRID)
    lo, hi = S.frames_needed(T, height=180, excluded_frames={bad}, **{k: kw[k] for k in
                             ("offset", "frame_rate", "line_time")})
    raw3 = rolling_raw(lo, hi - lo, offset)
    raw3[bad - lo] = np.nan
    out = S.resample_flow(raw3, lo, T, excluded_frames={bad}, **kw)
    assert np.isfinite(out).all()
    truth = blob_field(T)
    assert np.sqrt(np.mean((out - truth) ** 2)) < 0.1


def test_instants_outside_the_frames_are_clamped():
    raw = np.stack([blob_field(0.0), blob_field(0.5)])
    out = S.resample_flow(raw, 0, -1.0, offset=0.0, frame_rate=FR, line_time=LT_SMALL,
                          flow_grid=GRID)
    np.testing.assert_allclose(out, raw[0], atol=1e-6)
    out = S.resample_flow(raw, 0, 5.0, offset=0.0, frame_rate=FR, line_time=LT_SMALL,
                          flow_grid=GRID)
    np.testing.assert_allclose(out, raw[1], atol=1e-6)


def test_field_motion_recovers_a_translation():
    a = blob_field(0.0)
    b = blob_field(1.0 / FR)  # moved up by 2.5 cells (cx also shifts by ~0.6)
    m = S.field_motion(a, b)
    g = np.linalg.norm(a, axis=-1) > 0.1
    assert np.median(m[g, 1]) == pytest.approx(-2.5, abs=0.15)


def test_field_motion_from_the_coarser_level_is_no_worse_on_noisy_fields():
    """``finest_level=1`` (the default of ``ResampleParams.finest_level``) estimates the motion on
    the half-resolution level and prolongs it: the motion between flow fields is smooth, so
    against the known translation (2.5 cells up) it is at least as accurate as the full-grid
    estimate, with and without flow noise."""
    rng = np.random.default_rng(4)
    g = np.linalg.norm(blob_field(0.0), axis=-1) > 0.1
    for sigma in (0.0, 0.02):
        err = {}
        for finest in (0, 1):
            e = []
            for _ in range(3):
                a = blob_field(0.0) + rng.normal(0, sigma, GRID.shape + (2,)).astype(np.float32)
                b = blob_field(1.0 / FR) + rng.normal(0, sigma, GRID.shape + (2,)).astype(np.float32)
                m = S.field_motion(a, b, window=15, levels=3, iterations=2, finest_level=finest)
                assert m.shape == GRID.shape + (2,)
                e.append(np.sqrt(np.mean((m[g, 1] + 2.5) ** 2)))
            err[finest] = float(np.mean(e))
        assert err[1] < 0.1, err
        assert err[1] <= err[0], err


def test_row_means_of_flashed_frames_feed_detection():
    rng = np.random.default_rng(9)
    h, w, lt = 200, 64, 8e-5  # readout 16 ms of a 16.7 ms frame
    background = rng.normal(120, 30, (h, w))
    offset = -3 / FR - 77 * lt - 0.2 * lt
    frames = []
    for f in range(8):
        start = offset + f / FR + np.arange(h) * lt
        lit = (start <= 0) & (start + 4e-3 > 0)
        frames.append(np.clip(background + 60.0 * lit[:, None] + rng.normal(0, 1.5, (h, w)), 0, 255))
    det = S.detect_flash(np.stack([S.row_means(fr) for fr in frames]))
    assert det.frame == 3 and det.last_row == 77
    est = S.offset_from_flash(det, first_frame=0, frame_rate=FR, line_time=lt)
    assert abs(est - offset) <= 0.5 * lt


def test_row_warps_and_the_motion_cache_change_nothing(moving_case):
    """The resampler warps only the rows a frame pair serves and reuses the motion of a
    pair it met before: both must give exactly the full-field, uncached result."""
    from schlieren.pipeline import flow as F

    offset, f0, raw = moving_case
    rng = np.random.default_rng(4)
    coef = F.spline_coefficients(np.ascontiguousarray(raw[0, ..., 0]))
    disp = rng.normal(scale=2.0, size=raw.shape[1:3] + (2,)).astype(np.float32)
    rows = np.array([0, 3, 4, 17, raw.shape[1] - 1])
    np.testing.assert_array_equal(F.warp_coefficient_rows(coef, rows, disp[rows]),
                                  F.warp_coefficients(coef, disp)[rows])
    with pytest.raises(ValueError, match="rows"):
        F.warp_coefficient_rows(coef, np.array([raw.shape[1]]), disp[:1])
    motion._MOTION_CACHE.clear()
    m1 = S.cached_field_motion(raw[0], raw[1], window=15)
    assert len(motion._MOTION_CACHE) == 1
    m2 = S.cached_field_motion(raw[0], raw[1], window=15)
    np.testing.assert_array_equal(m1, S.field_motion(raw[0], raw[1], window=15))
    np.testing.assert_array_equal(m2, m1)
    assert len(motion._MOTION_CACHE) == 1  # the second call was a hit
    m2[:] = 0  # callers own what they get
    np.testing.assert_array_equal(S.cached_field_motion(raw[0], raw[1], window=15), m1)
    other = S.cached_field_motion(raw[0], raw[1], window=9)  # other parameters: another entry
    assert len(motion._MOTION_CACHE) == 2 and not np.array_equal(other, m1)
    # a whole resampling gives the same field cold and with every motion from the cache
    kw = dict(offset=offset, frame_rate=FR, line_time=LT_SMALL, flow_grid=GRID)
    motion._MOTION_CACHE.clear()
    cold = S.resample_flow(raw, f0, 0.1, **kw)
    warm = S.resample_flow(raw, f0, 0.1, **kw)
    np.testing.assert_array_equal(cold, warm)
    # the digests a caller kept are the cache's keys: the same result, with or without them
    # (None entries are computed), and no new entry
    n = len(motion._MOTION_CACHE)
    kept = [S.field_digest(r) for r in raw]
    np.testing.assert_array_equal(S.resample_flow(raw, f0, 0.1, digests=kept, **kw), cold)
    np.testing.assert_array_equal(S.resample_flow(raw, f0, 0.1, digests=[None] * len(raw), **kw), cold)
    assert len(motion._MOTION_CACHE) == n
    motion._MOTION_CACHE.clear()
    np.testing.assert_array_equal(S.resample_flow(raw, f0, 0.1, digests=kept, **kw), cold)


def test_motion_cache_keeps_the_eight_most_recently_used_pairs():
    """The motion cache is an LRU of 8 frame pairs: a hit refreshes its pair, and the ninth
    pair evicts the one used longest ago (the other seven stay hits)."""
    rng = np.random.default_rng(7)
    fields = rng.normal(size=(10, 24, 32, 2)).astype(np.float32)
    motion._MOTION_CACHE.clear()
    for j in range(8):
        S.cached_field_motion(fields[j], fields[j + 1], window=5, levels=1, iterations=1)
    assert len(motion._MOTION_CACHE) == 8
    S.cached_field_motion(fields[0], fields[1], window=5, levels=1, iterations=1)  # a hit: now the newest
    S.cached_field_motion(fields[8], fields[9], window=5, levels=1, iterations=1)
    assert len(motion._MOTION_CACHE) == 8
    kw = dict(window=5, levels=1, iterations=1)
    keys = [motion._motion_key(fields[j], fields[j + 1], **kw) for j in range(9)]
    assert keys[1] not in motion._MOTION_CACHE
    assert all(k in motion._MOTION_CACHE for i, k in enumerate(keys) if i != 1)
    motion._MOTION_CACHE.clear()


def test_invalid_flow_cells_stay_local(moving_case):
    """A few cells the flow left NaN (a textureless window at the image's edge) stay NaN
    where they are; the rest of the field is resampled as if they held zero deflection,
    instead of the pair's motion and spline warps turning the whole field NaN."""
    offset, f0, raw = moving_case
    T = 0.1
    kw = dict(offset=offset, frame_rate=FR, line_time=LT_SMALL, flow_grid=GRID)
    holed = raw.copy()
    holed[:, 0:2, 20:25] = np.nan          # the same cells in every frame, on the top edge
    filled = np.where(np.isfinite(holed), holed, 0.0)
    out = S.resample_flow(holed, f0, T, **kw)
    ref = S.resample_flow(filled, f0, T, **kw)
    bad = ~np.isfinite(out).all(axis=-1)
    assert bad[0:2, 20:25].all()
    assert bad.sum() == 10
    np.testing.assert_array_equal(out[~bad], ref[~bad])
    truth = blob_field(T)
    far = np.ones(bad.shape, bool)
    far[:8] = False                         # away from the holes, the resampling is as good as without them
    clean = S.resample_flow(raw, f0, T, **kw)
    err, err_clean = (np.sqrt(np.mean((f[far] - truth[far]) ** 2)) for f in (out, clean))
    assert err < 1.05 * err_clean + 1e-4, (err, err_clean)
