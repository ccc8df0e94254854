"""The rolling-shutter timing model (docs/design.md): row ``r`` of frame ``f`` starts its
exposure at ``offset + f / frame_rate + r * line_time`` on the session clock; the
instants the volumes are reconstructed at, and the raw frames one instant needs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["row_times", "output_times", "frames_needed"]


def row_times(frame: int, rows, *, offset: float, frame_rate: float, line_time: float
              ) -> np.ndarray:
    """Session time at which ``rows`` (image rows, may be fractional) of ``frame`` start."""
    return offset + frame / frame_rate + np.asarray(rows, dtype=np.float64) * line_time


def output_times(first_frame: int, n_frames: int, *, offsets, frame_rate: float, height,
                 line_time) -> np.ndarray:
    """Session-clock instants of the reconstructed frames (docs/design.md).

    ``time[k] = (first_frame + k) / frame_rate + mean_c(offset_c + 0.5 * height_c *
    line_time_c)``: the mid-frame instant of the average camera. ``height`` and
    ``line_time`` may be scalars or one value per camera.

    Returns
    -------
    ndarray, shape (n_frames,), float64, seconds
    """
    offs = np.atleast_1d(np.asarray(offsets, dtype=np.float64))
    h = np.broadcast_to(np.asarray(height, dtype=np.float64), offs.shape)
    lt = np.broadcast_to(np.asarray(line_time, dtype=np.float64), offs.shape)
    mid = float(np.mean(offs + 0.5 * h * lt))
    return (first_frame + np.arange(n_frames, dtype=np.float64)) / frame_rate + mid


def _fractional_frame(target_time, rows, *, offset, frame_rate, line_time):
    """Fractional frame index at which each image row is exposed at ``target_time``."""
    return (target_time - offset - np.asarray(rows, np.float64) * line_time) * frame_rate


def frames_needed(target_time: float, *, offset: float, frame_rate: float, line_time: float,
                  height: int, excluded_frames=(), frame_range: tuple[int, int] | None = None
                  ) -> tuple[int, int]:
    """Half-open range ``[f0, f1)`` of raw frames whose rows bracket ``target_time``.

    Every image row ``r`` is exposed at ``target_time`` between frames
    ``floor(phi_r)`` and ``floor(phi_r) + 1`` with
    ``phi_r = (target_time - offset - r * line_time) * frame_rate``; the range covers all
    rows, extended past excluded (flash) frames at either end, and clipped to
    ``frame_range`` (the frames that exist) if given.

    Returns
    -------
    (f0, f1) : tuple of int
    """
    phi = _fractional_frame(target_time, [0.0, height - 1.0], offset=offset,
                            frame_rate=frame_rate, line_time=line_time)
    # rounding only ever widens the range: a row exposed 1e-11 s before frame f still
    # needs frame f - 1 (hypothesis found phi = 29.9999999995 dropping it)
    lo = int(np.floor(phi.min()))
    hi = int(np.floor(phi.max() + 1e-9)) + 1
    excluded = set(int(e) for e in excluded_frames)
    if frame_range is not None:
        a, b = int(frame_range[0]), int(frame_range[1])
        lo = min(max(lo, a), b - 1)
        hi = min(max(hi, a), b - 1)
    else:
        a, b = -(2**62), 2**62
    while lo in excluded and lo > a:
        lo -= 1
    while hi in excluded and hi < b - 1:
        hi += 1
    return lo, hi + 1
