"""The ``sync`` and ``clock`` tasks: each camera's time offset, then the output instants.

``sync`` finds the strobe flash in a camera's frames (the row means of the search range,
:func:`~schlieren.pipeline.sync.detect_flash`) and turns the lit rows into the camera's
time offset (or takes the manifest's offset when the session has no strobe); ``clock``
places the output instants from every camera's offset (the rolling-shutter timeline,
:func:`~schlieren.pipeline.sync.output_times`).
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline import sync
from schlieren.workers.tasks.run_context import RunContext, TaskFailed

__all__ = ["sync_task", "clock_task"]


def sync_task(ctx: RunContext, c: int) -> dict:
    """Camera ``c``'s time offset and flash frames (stored ``time_offset``, ``flash_frames``)."""
    cam = ctx.cameras[c]
    s = ctx.session
    if s.strobe_search is not None:
        a, b = s.strobe_search
        b = min(b, len(ctx.frames(c)))
        rows = _row_means(ctx, c, a, b)
        try:
            flash = ctx.config.flash
            det = sync.detect_flash(rows, min_snr=flash.min_snr, min_contrast=flash.min_contrast)
        except ValueError as exc:
            raise TaskFailed(f"sync: camera {cam.name}: frames {a}..{b - 1}: {exc}") from None
        off = sync.offset_from_flash(det, first_frame=a, frame_rate=s.frame_rate,
                                     line_time=cam.line_time)
        flash = sorted(sync.flash_frames(det, first_frame=a))
        span = (flash[0], flash[-1]) if flash else (-1, -1)
        info = {"offset": off, "flash_frames": list(span)}
    else:
        off = float(cam.time_offset)
        span = (-1, -1)
        info = {"offset": off}
    ctx.store.write("time_offset", (c,), np.array([off], dtype=np.float64))
    ctx.store.write("flash_frames", (c,), np.array([span], dtype=np.int64))
    return info


def _row_means(ctx: RunContext, c: int, a: int, b: int) -> np.ndarray:
    """Mean grey level of each image row of camera ``c``'s frames ``a`` to ``b - 1``,
    (frame, row): what the flash detection reads."""
    cam = ctx.cameras[c]
    src = ctx.frames(c)
    src.prefetch(range(a, b))
    gone = set(src.dropped)
    rows = np.stack([src.read(f).mean(axis=1) if f not in gone else np.full(cam.height, np.nan)
                     for f in range(a, b)])
    if gone & set(range(a, b)):  # a dropped frame holds no flash: its rows at their median
        rows = np.where(np.isnan(rows), np.nanmedian(rows, axis=0, keepdims=True), rows)
    return rows


def clock_task(ctx: RunContext) -> dict:
    """The output frames' instants from every camera's offset (stored ``time``)."""
    offsets = np.array([float(ctx.store.read("time_offset", (c,))) for c in range(len(ctx.cameras))])
    line_time = float(np.mean([cam.line_time for cam in ctx.cameras]))
    times = sync.output_times(ctx.first_frame, ctx.n_frames, offsets=offsets,
                              frame_rate=ctx.session.frame_rate,
                              height=ctx.cameras[0].height, line_time=line_time)
    ctx.store.write("time", (), np.asarray(times, dtype=np.float64))
    return {"t0": float(times[0])}
