"""The ``uncertainty`` task: one frame's standard errors of refractivity, density and temperature.

Optional (``uncertainty.enabled``). The frame's flows, masks, hull and estimate (its
``gradient`` and ``refractivity``), the run's geometry and the weight and flow-window model
the ``regularisation`` task chose go to
:func:`~schlieren.pipeline.uncertainty.frame_uncertainty`: the flows' noise measured
outside the masks, drawn with the flow window's correlation, through the frame's own
tomography solve and integration, plus the bias, boundary and structure terms. A stage of its own rather
than part of the solve: it costs several solves, and as its own task it runs beside the
next frames' solves while the per-frame tomography stays as it is.
"""

from __future__ import annotations

import logging

import numpy as np

from schlieren.pipeline import flow as flowmod
from schlieren.pipeline import uncertainty
from schlieren.workers.tasks.deflection import flow_params
from schlieren.workers.tasks.geometry import cached_geometry, geometry_key
from schlieren.workers.tasks.run_context import RunContext
from schlieren.workers.tasks.tomography import flow_blur, tomo_params

__all__ = ["uncertainty_task", "noise_window"]

log = logging.getLogger(__package__)


def noise_window(ctx: RunContext) -> np.ndarray:
    """Per-camera width of the flows' averaging (flow cells,
    :func:`~schlieren.pipeline.flow.measurement_sigma`, without the tomography's
    ``flow_window_scale``): the correlation of the flows' noise."""
    return ctx.once("noise_window", lambda: np.array([
        flowmod.measurement_sigma(flow_params(ctx, c)) / ctx.flow_grid.factor for c in range(len(ctx.cameras))]))


def uncertainty_task(ctx: RunContext, k: int) -> dict:
    """Frame ``k``'s ``refractivity_sigma``, ``density_sigma`` and ``temperature_sigma``."""
    grid = ctx.session.grid
    medium = ctx.session.medium
    if ctx.config.reconstruction == "direct":
        log.warning("uncertainty: computed for the two-step reconstruction only; frame %d left at NaN",
                    ctx.first_frame + k)
        nan = np.full(tuple(grid.shape), np.nan, np.float32)
        for name in ("refractivity_sigma", "density_sigma", "temperature_sigma"):
            ctx.store.write(name, (k,), nan)
        return {"samples": 0}
    C = len(ctx.cameras)
    flows = np.stack(ctx.read_upstream_many("flow", [(c, k) for c in range(C)]))
    masks = np.stack(ctx.store.read_many("mask", [(c, k) for c in range(C)]))
    hull = np.asarray(ctx.store.read("hull", (k,)), dtype=bool)
    r = np.asarray(ctx.store.read("refractivity", (k,)), dtype=np.float64)
    params = ctx.config.uncertainty
    res = uncertainty.frame_uncertainty(
        cached_geometry(ctx.store_path, geometry_key(ctx)), flows, ~masks, hull,
        ctx.store.read("gradient", (k,)), r, grid, window_cells=noise_window(ctx),
        rng=uncertainty.frame_rng(params, ctx.first_frame + k), binning=ctx.ray_binning,
        tomography=tomo_params(ctx), poisson=ctx.config.poisson, params=params, **flow_blur(ctx))
    sigma = res.refractivity_sigma
    ctx.store.write("refractivity_sigma", (k,), sigma.astype(np.float32))
    ctx.store.write("density_sigma", (k,), uncertainty.density_sigma(sigma, medium).astype(np.float32))
    ctx.store.write("temperature_sigma", (k,), uncertainty.temperature_sigma(r, sigma, medium).astype(np.float32))
    inside = hull if hull.any() else np.ones(hull.shape, bool)
    return {"samples": res.samples, "iterations": list(res.iterations),
            "noise_rms": float(np.sqrt(np.mean(res.noise_sigma[inside] ** 2))),
            "boundary_rms": float(np.sqrt(np.mean(res.boundary_sigma[inside] ** 2))),
            "structure_rms": float(np.sqrt(np.mean(res.structure_sigma[inside] ** 2))),
            "bias_rms": float(np.sqrt(np.mean(res.bias_sigma[inside] ** 2))) if res.bias_sigma is not None else 0.0,
            "flow_noise_px": float(np.nanmedian(res.flow_noise)) if np.isfinite(res.flow_noise).any() else None}
