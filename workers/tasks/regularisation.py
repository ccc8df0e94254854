"""The ``regularisation`` task: the run's tomography weight and modelled flow averaging.

Morozov's discrepancy principle on the middle frame
(:func:`~schlieren.pipeline.tomography.reg_choice.choose_reg_weight`), and the per-camera width
of the flow averaging the tomography models (``TomoParams.model_flow_window``), both
chosen once per run and stored for every tomography task.
"""

from __future__ import annotations

import logging

import numpy as np

from schlieren.pipeline import flow as flowmod
from schlieren.pipeline import hull as hullmod
from schlieren.pipeline import tomography
from schlieren.pipeline.stages import middle_frame
from schlieren.pipeline.tomography.reg_choice import RUN_SMALLEST_WEIGHT
from schlieren.workers.tasks.deflection import flow_params
from schlieren.workers.tasks.geometry import cached_geometry, geometry_key
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["regularisation_task", "choose_flow_window", "window_model"]

log = logging.getLogger(__package__)  # the package's logger: log records name it as before the split


def regularisation_task(ctx: RunContext) -> dict:
    """The tomography weight for the run: Morozov's discrepancy principle on the middle frame.

    The noise of the right-hand side is measured on the rays outside every camera's mask
    (no flow: pure measurement noise); the weight whose data residual matches it is
    chosen on the middle frame's hull and used for every frame (one weight per run keeps
    the frames comparable and costs one frame's search: a cold solve at the search's start
    and about 1-5 warm-started ones bracketing the crossing, :func:`~schlieren.pipeline.
    tomography.reg_choice.choose_reg_weight`).
    """
    params = ctx.config.tomography
    out = {"reg_choice": params.reg_choice}
    weight, noise = float(params.reg_weight), np.full(3, np.nan)
    window = choose_flow_window(ctx)
    ctx.store.write("flow_window", (), window.astype(np.float64))
    out["flow_window"] = [float(v) for v in window]
    if params.reg_choice == "discrepancy" and ctx.n_frames > 0:
        weight, noise = _discrepancy_weight(ctx, window, weight, out)
    ctx.store.write("reg_weight", (), np.array([weight], dtype=np.float64))
    ctx.store.write("rhs_noise", (), np.asarray(noise, dtype=np.float64))
    out.update({"reg_weight": weight, "rhs_noise": [float(v) for v in noise]})
    return out


def _discrepancy_weight(ctx: RunContext, window: np.ndarray, weight: float, out: dict) -> tuple[float, np.ndarray]:
    """``(weight, noise)`` from the discrepancy principle on the middle frame (``weight``, the
    configured one, when no noise is measurable outside the masks); the search's figures go
    into the receipt ``out``."""
    params = ctx.config.tomography
    C = len(ctx.cameras)
    # The weight is chosen with the image-space model whatever flow_window_space says: it
    # fits the cell data to their noise, which the discrepancy principle needs; the volume
    # model's misfit stays above it on 16 cameras (the search would end at its smallest
    # weight), and volume solves do better with the weight chosen this way (docs/tuning.md,
    # "Flow-window model").
    blur = window_model(ctx, window, space="image")
    k = middle_frame(ctx.n_frames)  # the plan's "middle" dependency: these masks are done
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    masks = np.stack([ctx.store.read("mask", (c, k)) for c in range(C)])
    flows = ctx.tomography_flows(k)
    rhs = tomography.rhs_from_flows(geom, flows, n_ambient=params.n_ambient)
    quiet = tomography.bin_quiet(~masks, ctx.ray_binning)
    noise = tomography.rhs_noise(rhs, quiet)
    if np.all(np.isfinite(noise)):
        snr = tomography.rhs_snr(rhs, ~quiet, noise)
        out["ray_snr"] = [float(v) for v in snr]
        log.info("regularisation: rays in the masks carry %s x their noise (RMS; x, y, z)",
                 np.array2string(snr, precision=3))
    hull = hullmod.visual_hull(masks, ctx.cameras, ctx.session.grid, ctx.flow_grid, params=ctx.config.hull)
    if np.all(np.isfinite(noise)) and noise.any() and hull.any():
        choice = tomography.choose_reg_weight(geom, flows, hull, noise, params=params,
                                              smallest=RUN_SMALLEST_WEIGHT, **blur)
        weight = choice.reg_weight
        out["path"] = [[float(a), float(b)] for a, b in choice.path]
        log.info("regularisation: weight %.4g from the discrepancy principle (noise %s, frame %d)",
                 weight, np.array2string(noise, precision=3), k)
    else:
        log.warning("regularisation: no noise measurable outside the masks; using reg_weight %.4g", weight)
    return weight, noise


def choose_flow_window(ctx: RunContext) -> np.ndarray:
    """Per-camera width (flow cells) of the flow averaging the tomography models
    (``TomoParams.model_flow_window``; :func:`schlieren.pipeline.flow.measurement_sigma` times
    ``TomoParams.flow_window_scale``), 0 = none."""
    C = len(ctx.cameras)
    if not ctx.config.tomography.model_flow_window:
        return np.zeros(C)
    scale = float(ctx.config.tomography.flow_window_scale)
    return np.array([scale * flowmod.measurement_sigma(flow_params(ctx, c)) / ctx.flow_grid.factor
                     for c in range(C)])


def window_model(ctx: RunContext, window: np.ndarray, space: str | None = None) -> dict:
    """The solver's keyword for the flow averaging of per-camera widths ``window`` (flow
    cells): ``blur`` (:class:`~schlieren.pipeline.tomography.MeasurementBlur`, image space)
    or ``volume_blur`` (sigma in voxels, :func:`~schlieren.pipeline.tomography.volume_sigma`)
    as ``space`` (default ``TomoParams.flow_window_space``) says; empty if every width is 0."""
    window = np.asarray(window, dtype=np.float64)
    if not np.any(window > 0):
        return {}
    window = tomography.binned_sigma(window, ctx.ray_binning)  # in ray-grid cells
    rays = ctx.ray_grid
    if (space or ctx.config.tomography.flow_window_space) == "image":
        return {"blur": tomography.MeasurementBlur((len(ctx.cameras),) + tuple(rays.shape), window)}
    return {"volume_blur": tomography.volume_sigma(window, ctx.cameras, ctx.session.grid, rays.factor)}
