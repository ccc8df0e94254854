"""The ``tomography`` task: one frame's refractive-index gradient (paper eq. 5).

The frame's flows of every camera on the ray grid, its visual hull and the run's cached
geometry go to :func:`~schlieren.pipeline.tomography.solve_gradient` (or, beyond the
paper, :func:`~schlieren.pipeline.tomography.solve_refractivity` for ``reconstruction:
direct``), warm-started from the previous frame within a warm-start block and with the
weight and flow averaging the ``regularisation`` task chose. With ``refine.passes`` > 0 the
frame's flows are then measured again around the solution's prediction and solved again
(:mod:`.refine`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from schlieren.pipeline import tomography
from schlieren.pipeline.tomography.restriction import SHARED_RESTRICTIONS
from schlieren.workers.tasks.geometry import cached_geometry, geometry_key
from schlieren.workers.tasks.refine import refined_flows
from schlieren.workers.tasks.regularisation import window_model
from schlieren.workers.tasks.run_context import RunContext, solver_receipt
from schlieren.workers.tasks.spacetime import per_frame_array

__all__ = ["tomography_task", "tomo_params", "flow_blur"]


def flow_blur(ctx: RunContext, scale: float = 1.0) -> dict:
    """The flow averaging the regularisation stage chose (stored ``flow_window``) times
    ``scale``, as the solver's keyword
    (:func:`~schlieren.workers.tasks.regularisation.window_model`); empty for ``scale`` 0
    (the refined flows' solves take ``refine.window_scale`` of it)."""
    if scale <= 0:
        return {}
    return ctx.once(("flow_blur", float(scale)), lambda: window_model(
        ctx, scale * np.asarray(ctx.store.read("flow_window", ()), dtype=np.float64)))


def tomo_params(ctx: RunContext):
    """The run's tomography parameters with the weight the regularisation stage chose."""
    params = ctx.config.tomography
    w = ctx.once("reg_weight", lambda: float(ctx.store.read("reg_weight", ())[0]))
    return dataclasses.replace(params, reg_weight=w) if np.isfinite(w) else params


def tomography_task(ctx: RunContext, k: int) -> dict:
    """Frame ``k``'s gradient (stored ``gradient``, or ``gradient_frame`` under a space-time stage;
    with ``reconstruction: direct`` also ``refractivity``)."""
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    flows = ctx.tomography_flows(k)
    hull = ctx.store.read("hull", (k,))
    x0 = None
    if k % max(ctx.config.warm_start_block, 1) != 0:
        x0 = ctx.store.read(per_frame_array(ctx), (k - 1,))
    if ctx.config.reconstruction == "direct":
        # beyond the paper: solve for n - 1 directly; the gradient stored is its derivative
        r0 = ctx.store.read("refractivity", (k - 1,)).astype(np.float64) if x0 is not None else None
        r, info = tomography.solve_refractivity(
            geom, flows, hull, ctx.session.grid, r_ambient=ctx.session.medium.refractivity_ambient,
            params=ctx.config.direct, x0=r0)
        h = ctx.session.grid.voxel_size
        gz, gy, gx = np.gradient(np.asarray(r, dtype=np.float64), h)
        ctx.store.write("refractivity", (k,), np.asarray(r, dtype=np.float32))
        ctx.store.write("gradient", (k,), np.stack([gx, gy, gz], axis=-1).astype(np.float32))
        return solver_receipt(info)
    params = tomo_params(ctx)
    support = _block_support(ctx, k, params.hull_dilation)
    grad, info = tomography.solve_gradient(geom, flows, hull, params=params, x0=x0, support=support,
                                           **flow_blur(ctx))
    passes, window_scale, crop = ctx.config.refine.passes, ctx.config.refine.window_scale, ctx.config.refine.crop
    for _ in range(passes):
        # beyond the paper: the flows re-measured around this solution's prediction carry the
        # window's bias of the residual only, so they are solved with a share of the flow-window
        # model (refine.window_scale; 0: without it)
        refined = tomography.bin_cells(refined_flows(ctx, k, geom, grad, crop=crop), ctx.ray_binning)
        grad, info = tomography.solve_gradient(geom, refined, hull, params=params, support=support,
                                               **flow_blur(ctx, window_scale))
    ctx.store.write(per_frame_array(ctx), (k,), np.asarray(grad, dtype=np.float32))
    return solver_receipt(info)


def _block_support(ctx: RunContext, k: int, dilation: int) -> np.ndarray:
    """The union of the basis sets of frame ``k``'s warm-start block (the plan makes every
    tomography task wait for its block's hulls): each frame's system is selected inside
    this shared restriction, which a worker builds once per block (``solve_gradient``'s
    ``support``; the same system as the frame's own restriction)."""
    B = max(ctx.config.warm_start_block, 1)
    lo = k - k % B
    frames = range(lo, min(lo + B, len(ctx.times())))
    key = (lo, dilation)
    # as many blocks as the solver keeps restrictions for (a worker alternates two blocks)
    held = ctx._small.setdefault("block_support", {})
    if key not in held:
        while len(held) >= SHARED_RESTRICTIONS:
            held.pop(next(iter(held)))
        held[key] = tomography.block_support([ctx.store.read("hull", (i,)) for i in frames], dilation)
    return held[key]
