"""The ``capture`` task: one camera's defective pixels and flow pre-smoothing, before its flows.

:func:`~schlieren.pipeline.capture.find_defective_pixels` reads each reference frame (not
their mean: a pixel must stand out in every one) and a few capture frames spread over the
processed range; the map is stored (``defective_pixels``) for the camera's deflection
tasks, which give those pixels no weight. With ``flow.presmooth: auto`` the camera's
pre-smoothing is chosen from its reference's sharpness
(:func:`~schlieren.pipeline.flow.auto_presmooth`, the sensor noise measured on the
reference frames; Lucas-Kanade only) and stored (``presmooth``) for its flows; the
reference it measures is averaged from the frames the defect test reads (each frame is
decoded once). The
camera's static region (the pixels whose rays miss the volume) needs only the calibration:
each process computes it once (:func:`static_region`), and what the deflection tasks derive
from these for every frame once per camera too (:func:`camera_capture`).
"""

from __future__ import annotations

import itertools

import numpy as np

from schlieren.pipeline import capture
from schlieren.pipeline.flow.focus import AUTO, resolve_presmooth
from schlieren.pipeline.rigcheck import sensor_noise
from schlieren.storage.errors import SessionError
from schlieren.storage.frames import ReferenceMean, reference_frames
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["capture_task", "static_region", "defective_pixels", "camera_capture"]


def capture_task(ctx: RunContext, c: int) -> dict:
    """Camera ``c``'s defective pixels (stored ``defective_pixels``) and their counts, its
    flow pre-smoothing (stored ``presmooth``, in the receipt) and, for a reference of few
    frames, the reference topped up from the capture (stored ``reference``, ``reference_count``
    and ``reference_topup``)."""
    params = ctx.config.capture
    cam = ctx.cameras[c]
    auto = ctx.config.flow.presmooth == AUTO
    kept: list[np.ndarray] = []  # the reference frames at every other row and column: the sensor noise
    n_ref: list[int] = []  # the reference's frames, once read
    out: dict = {}
    if params.defective_pixels:
        refs = (_keep(img, kept) if auto else img for img in _reference_frames(ctx, c, n_ref))
        d = capture.find_defective_pixels(itertools.chain(refs, _capture_frames(ctx, c, params.defect_frames)),
                                          threshold=params.defect_threshold, stuck_ratio=params.stuck_ratio)
        out = capture.defect_counts(d)
    else:
        d = np.zeros((cam.height, cam.width), np.uint8)
        if auto or _may_top_up(ctx, c):
            kept = [np.asarray(img)[::2, ::2] for img in _reference_frames(ctx, c, n_ref)]
    ctx.store.write("defective_pixels", (c,), d[None])
    p = _presmooth(ctx, c, kept) if auto else float(ctx.config.flow.presmooth)
    ctx.store.write("presmooth", (c,), np.array([p], np.float64))
    out["presmooth"] = p
    if params.reference_topup > 0:
        out.update(_reference(ctx, c, n_ref[0] if n_ref else 0, d))
    return out


def _may_top_up(ctx: RunContext, c: int) -> bool:
    """Whether camera ``c``'s reference may be topped up (``capture.reference_topup``; not for
    interlaced cameras, whose fields have references of their own)."""
    return ctx.config.capture.reference_topup > 0 and not getattr(ctx.session.sources[c], "interlaced", None)


def _reference(ctx: RunContext, c: int, n_ref: int, defects: np.ndarray) -> dict:
    """Camera ``c``'s reference (of ``n_ref`` frames), topped up from ``capture.reference_topup``
    capture frames when it has fewer than ``capture.topup_below`` frames and its measured noise
    is worth fewer too (:func:`~schlieren.pipeline.capture.topup_reference`): stored (``reference``,
    ``reference_count``, ``reference_topup``), and this process's reference of the camera from
    now on. Interlaced cameras store none (NaN)."""
    params = ctx.config.capture
    cam = ctx.cameras[c]
    if not _may_top_up(ctx, c):
        ref, count, t = np.full((cam.height, cam.width), np.nan, np.float32), np.zeros((cam.height, cam.width)), None
    elif n_ref >= params.topup_below or n_ref < 2:
        # one image: what it is worth (a single frame, or an average stored as one image) costs
        # registered and moved capture frames to measure, at paper scale more than the rest of the
        # capture task (benchmarks/results/reference_topup.md, "Cost"); it is kept as it is
        ref, count, t = ctx.reference(c), np.full((cam.height, cam.width), max(n_ref, 1)), None
    else:
        prep = ctx.prepared_reference(c)
        region = capture.sample_region(prep, static=static_region(ctx, c), valid=capture.valid_pixels(defects),
                                       min_static_fraction=params.min_static_fraction)
        t = capture.topup_reference(prep, ctx.reference(c), _capture_frames(ctx, c, params.reference_topup, session=True),
                                    n_reference=n_ref, static=static_region(ctx, c), region=region,
                                    defects=defects, max_frames=params.topup_below, capture=params)
        ref, count = t.reference, t.count
    frames = t.frames if t is not None else 0
    ctx.store.write("reference_topup", (c,), np.array([frames], np.int32))
    ctx.store.write("reference", (c,), ref[None])
    ctx.store.write("reference_count", (c,), count.astype(np.float32)[None])
    if frames:
        ctx.reference_topped_up(c, ref)
    out = {"reference_frames": n_ref, "topup_frames": frames}
    if t is not None:
        out.update(topup_rejected=t.rejected, reference_equivalent=t.equivalent)
    return out


def _keep(img: np.ndarray, kept: list) -> np.ndarray:
    kept.append(np.asarray(img)[::2, ::2])
    return img


def _presmooth(ctx: RunContext, c: int, kept: list) -> float:
    """:func:`~schlieren.pipeline.flow.auto_presmooth` of camera ``c``'s reference, its
    sensor noise from the reference frames ``kept`` (none removed with fewer than two)."""
    dtype = ctx.frames(c).raw_dtype
    full = float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None
    noise = sensor_noise(kept, full_scale=full) if len(kept) >= 2 else 0.0
    return resolve_presmooth(AUTO, ctx.reference(c), method=ctx.config.flow.method,
                             noise=noise if np.isfinite(noise) else 0.0, n_frames=max(len(kept), 1))


def _reference_frames(ctx: RunContext, c: int, n_ref: list):
    """Camera ``c``'s reference frames (one by one; none for interlaced cameras, whose
    fields are compared with per-field references). Once all are read, their average is the
    process's reference of the camera (:meth:`RunContext.reference`: not read again) and
    their number is appended to ``n_ref``."""
    s = ctx.session.sources[c]
    if getattr(s, "interlaced", None):
        return
    mean = ReferenceMean(s.reference, s.name)
    for img in reference_frames(s, camera_name=s.name):
        mean.add(img)
        yield img
    ctx.reference_averaged(c, mean.result)
    n_ref.append(mean.n)


def _capture_frames(ctx: RunContext, c: int, n: int, *, session: bool = False):
    """``n`` capture frames of camera ``c`` evenly spread over the processed range (over all of
    the camera's frames with ``session``; dropped or unreadable ones skipped)."""
    src = ctx.frames(c)
    first, last = (0, len(src) - 1) if session else (ctx.first_frame, ctx.first_frame + ctx.n_frames - 1)
    frames = np.unique(np.linspace(first, last, max(n, 0)).round().astype(int)) if n > 0 else []
    for f in frames:
        if int(f) in src.dropped:
            continue
        try:
            yield src.read(int(f))
        except SessionError:  # its own deflection task reports it
            continue


def static_region(ctx: RunContext, c: int) -> np.ndarray:
    """Camera ``c``'s pixels whose rays miss the volume (computed once per process)."""
    def make():
        g = ctx.session.grid
        return capture.static_region(ctx.cameras[c], g.vmin, g.vmax, margin=ctx.config.capture.static_margin)
    return ctx.once(("static_region", c), make)


def defective_pixels(ctx: RunContext, c: int) -> np.ndarray | None:
    """Camera ``c``'s stored defective pixels (None when it has none; read once per process)."""
    def read():
        d = np.asarray(ctx.store.read("defective_pixels", (c,)))
        return d if d.any() else None
    return ctx.once(("defective_pixels", c), read)


def camera_capture(ctx: RunContext, c: int, parity: int | None, flow) -> capture.CameraCapture:
    """Camera ``c``'s :func:`~schlieren.pipeline.capture.prepare_capture` for its prepared
    reference (of field ``parity``) and flow parameters ``flow`` (made once per process)."""
    return ctx.once(("camera_capture", c, parity), lambda: capture.prepare_capture(
        ctx.prepared_reference(c, parity), flow, ctx.config.capture, static=static_region(ctx, c),
        defects=defective_pixels(ctx, c)))
