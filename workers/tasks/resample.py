"""The ``resample`` task: one camera's flow at one output instant, from its raw flows.

Rolling-shutter resampling (:func:`~schlieren.pipeline.sync.resample_flow`): each image
row of the raw flows is interpolated in time to the output instant, skipping the frames
the flash lit and those the deflection tasks flagged dark, saturated or frozen. The
ranges of raw frames an instant reads are computed here, and by
:func:`~schlieren.workers.tasks.deflection.raw_frame_needed` to leave out margin frames
that no instant reads.
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline import sync
from schlieren.pipeline.stages import stage
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["resample_task", "bad_frames", "resample_window", "raw_range", "frames_read"]


def bad_frames(ctx: RunContext, c: int, lo: int, hi: int) -> tuple[int, ...]:
    """Capture frames in ``[lo, hi]`` of camera ``c`` flagged dark, saturated or frozen."""
    out = []
    for f in range(max(lo, ctx.raw_first), min(hi, ctx.raw_first + ctx.n_raw - 1) + 1):
        q = ctx.read_upstream("frame_quality", (c, f - ctx.raw_first))
        if np.isfinite(q[3]) and int(q[3]):
            out.append(f)
    return tuple(out)


def resample_window(ctx: RunContext, k: int) -> tuple[int, int]:
    """Half-open range of the raw frames output frame ``k``'s resample task waits for (the
    plan's ``frame_halo`` window): it never reads beyond them."""
    centre = ctx.first_frame + k
    halo = stage("resample").frame_halo
    return max(ctx.raw_first, centre - halo), min(ctx.raw_first + ctx.n_raw, centre + halo + 1)


def raw_range(ctx: RunContext, c: int, k: int, window: tuple[int, int], excluded) -> tuple[int, int]:
    """Inclusive range ``(lo, hi)`` of camera ``c``'s raw frames that output frame ``k``'s
    resampling reads: ``sync.frames_needed`` past the ``excluded`` frames, within ``window``
    and the stored raw frames."""
    cam = ctx.cameras[c]
    f0, f1 = sync.frames_needed(float(ctx.times()[k]), offset=ctx.time_offset(c),
                                frame_rate=ctx.session.frame_rate, line_time=cam.line_time,
                                height=cam.height, excluded_frames=tuple(sorted(excluded)), frame_range=window)
    last = ctx.raw_first + ctx.n_raw - 1
    lo = max(ctx.raw_first, min(f0, last))
    return lo, max(lo, min(f1 - 1, last))


def frames_read(ctx: RunContext, c: int, k: int) -> tuple[int, int, tuple[int, ...], tuple[int, ...]]:
    """``(lo, hi, excluded, bad)``: the inclusive range of camera ``c``'s raw frames that output
    frame ``k``'s resampling reads, the frames it skips (flash and flagged) and the flagged ones."""
    window = resample_window(ctx, k)
    bad = bad_frames(ctx, c, window[0], window[1] - 1)
    excluded = tuple(sorted(set(ctx.flash_frames(c)) | set(bad)))
    lo, hi = raw_range(ctx, c, k, window, excluded)
    return lo, hi, excluded, bad


def resample_task(ctx: RunContext, c: int, k: int) -> dict:
    """Camera ``c``'s flow at output instant ``k`` (stored ``flow``) from the raw flows around it."""
    s = ctx.session
    cam = ctx.cameras[c]
    off = ctx.time_offset(c)
    t = float(ctx.times()[k])
    lo, hi, excluded, bad = frames_read(ctx, c, k)
    # the raw flows are final once their deflection tasks (this task's dependencies) are
    # done: neighbouring instants of a batched task share them, read and keyed once
    fields = [ctx.read_upstream("flow_raw", (c, f - ctx.raw_first)) for f in range(lo, hi + 1)]
    raw = np.stack(fields)
    digests = [ctx.memo(("flow_raw_digest", c, f), lambda a=a: sync.field_digest(a))
               for f, a in zip(range(lo, hi + 1), fields)]
    out = sync.resample_flow(raw, lo, t, offset=off, frame_rate=s.frame_rate,
                             line_time=cam.line_time, flow_grid=ctx.flow_grid,
                             excluded_frames=excluded, params=ctx.config.resample, digests=digests)
    ctx.store.write("flow", (c, k), np.asarray(out, dtype=np.float32))
    return {"raw_frames": [lo, hi], **({"excluded_frames": list(bad)} if bad else {})}
