"""The ``potential``, ``threshold`` and ``mask`` tasks: where each camera sees the flow.

A mask is the part of a camera's image whose deflections belong to the flow, not to the
noise (:mod:`schlieren.pipeline.masks`): each camera-frame's flow is integrated into a
potential (paper sec. 4; with ``masks.baseline: static`` its zero is the quadratic surface
it shows on the cells whose rays miss the volume) and summarised; one ``threshold`` task pools the summaries of
the whole sequence into one threshold; each mask then thresholds the evidence of its
frame and its temporal neighbours.
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline import capture
from schlieren.pipeline import masks as masksmod
from schlieren.workers.tasks.capture import static_region
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["potential_task", "threshold_task", "mask_task"]


def potential_task(ctx: RunContext, c: int, k: int) -> dict:
    """Potential of one camera-frame (the flow Poisson-integrated, paper sec. 4) and its summary.

    The summary (:func:`~schlieren.pipeline.masks.potential_summary`) is the map step of
    the sequence-wide threshold, computed here while the potential is in memory so the
    single ``threshold`` task that every mask waits for only pools small vectors.
    """
    f = ctx.read_upstream("flow", (c, k))
    params = ctx.config.masks
    p = np.asarray(masksmod.flow_potential(f, static=_static_cells(ctx, c, f.shape[:2])), dtype=np.float32)
    ctx.store.write("potential", (c, k), p)
    ctx.store.write("potential_summary", (c, k), masksmod.potential_summary(
        p, smooth_sigma=params.smooth_sigma, n_quantiles=params.n_quantiles))
    return {}


def _static_cells(ctx: RunContext, c: int, shape) -> np.ndarray | None:
    """Camera ``c``'s flow cells whose rays miss the volume (``masks.baseline: static``), or None."""
    return _camera_static_cells(ctx, c, shape) if ctx.config.masks.baseline == "static" else None


def _noise_cells(ctx: RunContext, c: int, shape) -> np.ndarray | None:
    """Camera ``c``'s flow cells whose reference was not topped up (the cells some of whose
    rays meet the volume), when its capture task topped the reference up; else None (the
    deflection criterion's noise from the whole frame, as before)."""
    if ctx.config.capture.reference_topup <= 0:
        return None

    def make():
        static = _camera_static_cells(ctx, c, shape)
        return None if static is None or int(ctx.store.read("reference_topup", (c,))) <= 0 else ~static
    return ctx.once(("noise_cells", c), make)


def _camera_static_cells(ctx: RunContext, c: int, shape) -> np.ndarray | None:
    """The capture stage's static region of camera ``c`` on the flow grid (cells all of whose
    pixels' rays miss the volume; computed once per process), or None if not of ``shape``."""
    def make():
        cells = capture.static_cells(static_region(ctx, c), ctx.flow_grid.factor)
        return cells if cells.shape == tuple(shape) else None
    return ctx.once(("static_cells", c), make)


def threshold_task(ctx: RunContext) -> dict:
    """The sequence-wide mask threshold (stored ``mask_threshold``) from every potential's summary."""
    params = ctx.config.masks
    # stores of versions that wrote no summaries are not resumed (no chunk checksums), so
    # every summary under a set potential marker exists (a lost one raises ChunkError)
    summaries = [ctx.store.read("potential_summary", (c, k))
                 for c in range(len(ctx.cameras)) for k in range(ctx.n_frames)]
    thr = masksmod.threshold_from_summaries(summaries, percentile=params.percentile)
    ctx.store.write("mask_threshold", (), np.array([thr], dtype=np.float64))
    return {"threshold": float(thr)}


def mask_task(ctx: RunContext, c: int, k: int) -> dict:
    """Camera ``c``'s mask at frame ``k`` (stored ``mask``) from the evidence of frames ``k +- temporal_radius``."""
    params = ctx.config.masks
    h = params.temporal_radius
    ks = [min(max(i, 0), ctx.n_frames - 1) for i in range(k - h, k + h + 1)]
    thr = ctx.mask_threshold()

    def evidence(i):  # masksmod.make_mask, with each frame's evidence made once per process
        flow = ctx.read_upstream("flow", (c, i))
        return masksmod.frame_evidence(ctx.read_upstream("potential", (c, i)), thr,
                                       flow=flow, noise_cells=_noise_cells(ctx, c, flow.shape[:2]),
                                       smooth_sigma=params.smooth_sigma,
                                       deflection_threshold=params.deflection_threshold,
                                       flow_sigma=params.flow_sigma, noise_factor=params.noise_factor,
                                       grow_factor=params.grow_factor)

    keys = {i: ("mask_evidence", c, i, thr) for i in ks}
    todo = [(c, i) for i, key in keys.items() if not ctx.memoized(key)]
    if todo:  # read the frames still needed together (concurrent requests on object stores)
        ctx.read_upstream_many("potential", todo)
        ctx.read_upstream_many("flow", todo)
    ev = [ctx.memo(key, lambda i=i: evidence(i)) for i, key in keys.items()]
    m = masksmod.mask_from_evidence(ev, dilation_radius=params.dilation_radius)
    ctx.store.write("mask", (c, k), np.asarray(m, dtype=bool))
    return {"fraction": float(np.mean(m))}
