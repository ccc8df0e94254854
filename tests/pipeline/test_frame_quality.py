"""Dark, saturated and frozen frames (pipeline/frame_quality.py) against frames built to be each."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.frame_quality import (
    DARK, FROZEN, QUALITY_NAMES, SATURATED, dropped_quality, flag_names, frame_quality,
)


@pytest.fixture
def frames():
    rng = np.random.default_rng(4)
    background = rng.uniform(40, 200, (60, 80))
    noisy = lambda: np.clip(np.round(background + rng.normal(0, 1.5, background.shape)), 0, 255)  # noqa: E731
    return background, noisy


def test_ordinary_frames_with_sensor_noise_are_not_flagged(frames):
    background, noisy = frames
    a, b = noisy(), noisy()
    q = frame_quality(b, a, reference_mean=background.mean(), full_scale=255)
    assert q[3] == 0 and flag_names(q[3]) == []
    assert q[0] == pytest.approx(b.mean(), rel=1e-6) and 1.0 < q[2] < 2.5  # noise: mean |change| ~ 1.7
    # the first frame has no previous one: no change measured, not frozen
    first = frame_quality(a, None, reference_mean=background.mean(), full_scale=255)
    assert np.isnan(first[2]) and first[3] == 0


def test_dark_saturated_and_frozen_frames_are_flagged(frames):
    background, noisy = frames
    ref = background.mean()
    prev = noisy()
    dark = frame_quality(0.1 * noisy(), prev, reference_mean=ref, full_scale=255)
    assert int(dark[3]) == DARK and flag_names(dark[3]) == ["dark"]
    blown = np.where(np.arange(background.size).reshape(background.shape) % 3 == 0, 120.0, 255.0)
    sat = frame_quality(blown, prev, reference_mean=ref, full_scale=255)
    assert int(sat[3]) == SATURATED and sat[1] == pytest.approx(2 / 3, abs=1e-3)
    frozen = frame_quality(prev.copy(), prev, reference_mean=ref, full_scale=255)
    assert int(frozen[3]) == FROZEN and frozen[2] == 0 and "frozen" in flag_names(frozen[3])[0]
    # black and repeated at once: both flags
    black = np.zeros_like(prev)
    both = frame_quality(black, black, reference_mean=ref, full_scale=255)
    assert int(both[3]) == DARK | FROZEN


def test_sixteen_bit_and_floating_point_frames(frames):
    background, noisy = frames
    a16, b16 = 257.0 * noisy(), 257.0 * noisy()
    assert frame_quality(b16, a16, reference_mean=257 * background.mean(), full_scale=65535)[3] == 0
    full = np.full_like(a16, 65535.0)
    assert int(frame_quality(full, a16, reference_mean=257 * background.mean(), full_scale=65535)[3]) == SATURATED
    # float frames: no full scale, no saturation test; frozen relative to the frame's range
    f = noisy() / 255.0
    q = frame_quality(np.ones_like(f), f, reference_mean=f.mean(), full_scale=None)
    assert q[1] == 0 and int(q[3]) == 0


def test_lossy_video_frames_of_a_slow_flow_are_not_frozen(frames):
    """H.264 at camcorder bitrates strips the sensor noise: consecutive frames of a weak plume
    differ by a few hundredths of a grey level (0.02-0.12 measured on the realistic family),
    which is change, not a repeat; a bit-identical repeat still is."""
    background, noisy = frames
    prev = noisy()
    rng = np.random.default_rng(9)
    moved = prev.copy()
    idx = rng.choice(prev.size, size=prev.size // 50, replace=False)  # 2 % of pixels change by one level
    moved.flat[idx] += 1.0
    q = frame_quality(moved, prev, reference_mean=background.mean(), full_scale=255)
    assert q[2] == pytest.approx(0.02, abs=1e-3) and int(q[3]) == 0
    # one pixel in 1000 changed: indistinguishable from a repeat
    nearly = prev.copy()
    nearly.flat[idx[: prev.size // 1000]] += 1.0
    assert int(frame_quality(nearly, prev, reference_mean=background.mean(), full_scale=255)[3]) == FROZEN


def test_statistics_equal_the_float64_definition_for_every_frame_type():
    """The OpenCV sums give the statistics of the float64 definition (mean grey level,
    saturated share, mean absolute change, population std, min, max) for 8/16-bit, float
    frames with NaN, other integer types and mixed types (those take the numpy path); a
    frame with a NaN pixel has NaN statistics."""
    rng = np.random.default_rng(2)
    a = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    b = rng.integers(0, 256, (60, 80)).astype(np.uint8)
    b[:10] = 255
    f = rng.random((60, 80)).astype(np.float32) * 255
    g = f.copy()
    g[3, 4] = np.nan
    w = rng.integers(0, 65536, (60, 80)).astype(np.uint16)
    for frame, prev, full in ((b, a, 255), (w, w[::-1].copy(), 65535), (f, g, None), (g, f, None),
                              (b.astype(np.int32), a.astype(np.int32), 255), (b, a.astype(np.float32), 255),
                              (f, None, None)):
        q = frame_quality(frame, prev, reference_mean=100.0, full_scale=full)
        x = np.asarray(frame, dtype=np.float64)
        want_change = np.nan if prev is None else np.mean(np.abs(x - np.asarray(prev, dtype=np.float64)))
        want_sat = 0.0 if full is None else np.mean(x >= full)
        np.testing.assert_allclose(q[:3], [x.mean(), want_sat, want_change], rtol=1e-6, equal_nan=True)
        np.testing.assert_allclose(q[4:], [x.std(), x.min(), x.max()], rtol=1e-6, equal_nan=True)
    assert np.isnan(frame_quality(g, f, reference_mean=100.0, full_scale=None)[[0, 4, 5, 6]]).all()
    # 8-bit frames as their samples (uint8, what the run passes for one-channel 8-bit files)
    # or as float32 grey levels: the same vector bit for bit, also at paper scale, where the
    # sums of squares pass 2^24 (exact integers in OpenCV's double sums either way)
    big = rng.integers(0, 256, (1080, 1440)).astype(np.uint8)
    big[:40] = 255
    for frame, prev in ((b, a), (b, None), (big, np.roll(big, 1, axis=1)), (np.full_like(big, 7), big)):
        as_float = None if prev is None else prev.astype(np.float32)
        np.testing.assert_array_equal(
            frame_quality(frame, prev, reference_mean=100.0, full_scale=255).view(np.uint32),
            frame_quality(frame.astype(np.float32), as_float, reference_mean=100.0, full_scale=255).view(np.uint32))
    # grey levels decoded from integer samples skip the NaN check (finite=True, as the run
    # passes for integer sources): the same vector, bit for bit
    for frame, prev, full in ((b.astype(np.float32), a.astype(np.float32), 255), (f, None, None),
                              (w.astype(np.float32), None, 65535)):
        np.testing.assert_array_equal(
            frame_quality(frame, prev, reference_mean=100.0, full_scale=full, finite=True).view(np.uint32),
            frame_quality(frame, prev, reference_mean=100.0, full_scale=full).view(np.uint32))
    # below full scale everywhere: no saturated pixel (the count is skipped, not guessed)
    assert frame_quality(np.minimum(b, 254), a, reference_mean=100.0, full_scale=255)[1] == 0.0
    assert QUALITY_NAMES[4:] == ("std", "min", "max") and len(dropped_quality()) == len(QUALITY_NAMES)
