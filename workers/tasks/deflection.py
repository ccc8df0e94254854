"""The ``deflection`` task: one camera's optical flow at one raw frame (paper sec. 4).

The frame is compared with the camera's reference
(:func:`~schlieren.pipeline.capture.corrected_deflection`: the flow of
:func:`~schlieren.pipeline.flow.deflection_stage` with the camera's motion against the
reference, the frame's gain and offset and the defective pixels removed; the reference's
pyramid and the camera's fixed inputs of the corrections prepared once per process); the corrections (``background_motion``,
``photometric``, ``capture_fit``) and the frame-quality vector are stored beside the flow:
dark, saturated or frozen frames are flagged here and excluded by the resampling. A dropped frame, or a margin frame no output instant reads, stores a
NaN field and its flags without computing a flow.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from schlieren.pipeline import capture
from schlieren.pipeline import flow as flowmod
from schlieren.pipeline import frame_quality as fq
from schlieren.pipeline.stages import stage
from schlieren.storage.errors import SessionError
from schlieren.workers.tasks.capture import camera_capture
from schlieren.workers.tasks.resample import raw_range, resample_window
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["deflection_task", "raw_frame_needed", "frame_flags", "quality_vector", "flow_params"]

log = logging.getLogger(__package__)  # the package's logger: log records name it as before the split


def deflection_task(ctx: RunContext, c: int, j: int) -> dict:
    """Camera ``c``'s flow at raw frame ``j`` (stored ``flow_raw``) and its ``frame_quality``."""
    f = ctx.raw_first + j
    src = ctx.frames(c)
    if f in src.dropped:  # no frame at this time: excluded by resampling, like a dark frame
        _write_no_flow(ctx, c, j, fq.dropped_quality())
        log.warning("camera %s, frame %d: dropped by the camera; excluded from the reconstruction",
                    ctx.cameras[c].name, f)
        return {"max_px": 0.0, "excluded": fq.flag_names(fq.DROPPED)}
    if not ctx.first_frame <= f < ctx.first_frame + ctx.n_frames and not raw_frame_needed(ctx, c, f):
        # a margin frame no output instant reads (the plan made this task wait for the clock)
        _write_no_flow(ctx, c, j, fq.unused_quality())
        return {"unused": True}
    img = ctx.frame(c, f)
    parity = src.parity(f) if hasattr(src, "parity") else None  # interlaced fields
    params = flow_params(ctx, c)
    d, corr = capture.corrected_deflection(ctx.prepared_reference(c, parity), img, params, ctx.config.capture,
                                           camera=camera_capture(ctx, c, parity, params))
    ctx.store.write("flow_raw", (c, j), d.astype(np.float32))
    _write_capture(ctx, c, j, corr)
    # dark, saturated or frozen frames: flagged here, excluded by resampling
    q = quality_vector(ctx, c, f, img)
    ctx.store.write("frame_quality", (c, j), q)
    out = {"max_px": float(np.nanmax(np.abs(d))) if np.isfinite(d).any() else 0.0, "window": params.window,
           "motion_px": capture.motion_extent(corr.motion, ctx.cameras[c].image_size),
           "capture_flags": int(corr.flags)}
    if corr.flags & capture.GAIN_UNKNOWN:
        log.warning("camera %s, frame %d: its gain against the reference cannot be estimated (a dark or clipped "
                    "frame?): not normalised", ctx.cameras[c].name, f)
    bad = fq.flag_names(q[3])
    if bad:
        out["excluded"] = bad
        log.warning("camera %s, frame %d: %s; excluded from the reconstruction", ctx.cameras[c].name, f,
                    ", ".join(bad))
    return out


def _write_no_flow(ctx: RunContext, c: int, j: int, quality: np.ndarray) -> None:
    """Raw frame ``j`` of camera ``c`` has no flow (dropped, or not needed): a NaN field and
    its quality vector (and NaN capture corrections), so every chunk of the task exists."""
    ctx.store.write("flow_raw", (c, j), np.full(tuple(ctx.flow_grid.shape) + (2,), np.nan, np.float32))
    ctx.store.write("frame_quality", (c, j), quality)
    for name in ("background_motion", "photometric", "capture_fit"):
        shape = ctx.store.array(name).shape[2:]
        ctx.store.write(name, (c, j), np.full(shape, np.nan, ctx.store.array(name).dtype))


def _write_capture(ctx: RunContext, c: int, j: int, corr) -> None:
    """The capture corrections of camera ``c``'s raw frame ``j``: the background's motion,
    the frame's gain and offset profiles, and the fit's statistics."""
    ph = corr.fit.photometric
    ctx.store.write("background_motion", (c, j), np.asarray(corr.motion, np.float64))
    ctx.store.write("photometric", (c, j), np.stack([ph.gain, ph.offset]).astype(np.float32))
    ctx.store.write("capture_fit", (c, j), corr.stats())


def raw_frame_needed(ctx: RunContext, c: int, f: int) -> bool:
    """Whether any output instant's resampling (:func:`~schlieren.workers.tasks.resample.resample_task`)
    will read raw frame ``f`` of camera ``c``.

    The same ranges as the resampling's: ``sync.frames_needed`` over each output frame's
    window, its excluded frames the flash and the flagged frames. Only the ends of a range
    move past excluded frames, so the flags needed are those of the range's end on ``f``'s
    side, added one at a time (each from the frame itself, as its own deflection task
    flags it: read here, not waited for). Unreadable: needed (its own task reports it).
    """
    halo = stage("resample").frame_halo
    near = f - ctx.first_frame  # the output frames whose window holds f are within the halo
    for k in range(max(0, near - halo), min(ctx.n_frames, near + halo + 1)):
        window = resample_window(ctx, k)
        if not window[0] <= f < window[1]:
            continue
        excluded = set(ctx.flash_frames(c))
        while True:
            lo, hi = raw_range(ctx, c, k, window, excluded)
            if lo <= f <= hi:
                return True
            end = lo if f < lo else hi
            if end in excluded:
                break
            try:
                bad = frame_flags(ctx, c, end) & fq.PROBLEMS
            except SessionError:
                return True
            if not bad:
                break
            excluded.add(end)
    return False


def frame_flags(ctx: RunContext, c: int, f: int) -> int:
    """The flags :func:`deflection_task` stores for capture frame ``f`` of camera ``c``, from
    the frame (and the one before it) alone."""
    if f in ctx.frames(c).dropped:
        return fq.DROPPED
    return int(quality_vector(ctx, c, f, ctx.frame(c, f))[3])


def quality_vector(ctx: RunContext, c: int, f: int, img: np.ndarray) -> np.ndarray:
    """:func:`~schlieren.pipeline.frame_quality.frame_quality` of frame ``f`` (image ``img``)
    of camera ``c`` against its reference and the frame before it."""
    src = ctx.frames(c)
    dtype = src.raw_dtype
    full = float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None
    parity = src.parity(f) if hasattr(src, "parity") else None
    ref_mean = ctx.once(("reference_mean", c, parity),
                        lambda: float(np.mean(ctx.reference(c, parity), dtype=np.float64)))
    try:
        previous = ctx.frame(c, f - 1) if f > 0 else None
    except SessionError:  # the previous frame is unreadable (its own task reports it): not frozen
        previous = None
    if dtype == np.uint8 and src.one_channel:
        # the 8-bit samples themselves (exact): their sums are the same integers, and OpenCV
        # sums them faster than float32, conversions included (docs/tuning.md, "Speed")
        img = img.astype(np.uint8)
        previous = None if previous is None else previous.astype(np.uint8)
    # grey levels of integer samples are finite (no NaN check over the frame)
    return fq.frame_quality(img, previous, reference_mean=ref_mean, full_scale=full, finite=full is not None)


def flow_params(ctx: RunContext, c: int):
    """Camera ``c``'s flow parameters: its pre-smoothing (:meth:`RunContext.presmooth`; with
    ``auto``, the capture stage's choice) and the LK window from the voxel footprint
    (``window_per_voxel``, :func:`~schlieren.pipeline.flow.camera_window`; the run logs and
    stores it)."""
    params = ctx.config.flow

    def make():
        p = dataclasses.replace(params, presmooth=ctx.presmooth(c))
        if params.window_per_voxel <= 0:
            return p
        return dataclasses.replace(p, window=flowmod.camera_window(
            ctx.cameras[c], ctx.session.grid, window=params.window, window_per_voxel=params.window_per_voxel))
    return ctx.once(("flow_params", c), make)
