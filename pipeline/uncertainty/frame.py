"""One frame's standard errors of refractivity, temperature and density (beyond the paper).

``sigma_r^2 = sigma_noise^2 + sigma_bias^2 + sigma_boundary^2 + sigma_structure^2`` inside the
visual hull:

* ``sigma_noise``: the flows' measured noise propagated through the frame's tomography
  and integration (:func:`~schlieren.pipeline.uncertainty.noise_ensemble`), its variance
  averaged locally (``UncertaintyParams.smoothing``);
* ``sigma_bias``: ``bias_scale`` times the share of a smooth field the frame's solve and
  integration lose there (:func:`~schlieren.pipeline.uncertainty.resolution_loss`, random
  probes through the regularised inverse) times the estimate's local amplitude
  ``|r - r_ambient|``: the regularisation's bias, which grows where the views are few;
* ``sigma_boundary``: ``boundary_scale`` times the local RMS of the integration's
  sensitivity to its boundary condition (:func:`~schlieren.pipeline.uncertainty.boundary_sensitivity`):
  the slowly varying error the gradient accumulates, and a hull that cuts the plume;
* ``sigma_structure``: ``structure_scale`` times the local RMS of the estimate's curvature
  ``h^2 lap(r)`` (:func:`~schlieren.pipeline.uncertainty.curvature_rms`): the fine structure lost.

The scales were fitted on the realistic family's tune cases (docs/uncertainty.md).

Outside the hull the refractivity is set to ambient by the integration's boundary
condition (paper sec. 5); its standard error there is 0: the hull is a constraint, and flow
that every mask missed is not covered. The derived quantities take the first-order
propagation of the Gladstone-Dale and ideal-gas relations (:mod:`schlieren.pipeline.derived`):
``sigma_rho = sigma_r / G`` and ``sigma_T = T_amb r_amb sigma_r / r^2`` (NaN where ``r <= 0``,
as the temperature).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.pipeline.poisson.integration import PoissonParams
from schlieren.pipeline.tomography.binning import bin_cells
from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur
from schlieren.pipeline.tomography.geometry import TomoGeometry
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.solve import prepare_frame, valid_rays
from schlieren.pipeline.uncertainty.bias import resolution_loss
from schlieren.pipeline.uncertainty.boundary import boundary_sensitivity
from schlieren.pipeline.uncertainty.ensemble import noise_ensemble
from schlieren.pipeline.uncertainty.linear_integration import LinearisedIntegration
from schlieren.pipeline.uncertainty.local import masked_mean
from schlieren.pipeline.uncertainty.structure import curvature_rms
from schlieren.pipeline.uncertainty.noise import flow_noise_level
from schlieren.pipeline.uncertainty.params import UncertaintyParams

__all__ = ["FrameUncertainty", "frame_uncertainty", "frame_rng", "temperature_sigma", "density_sigma"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameUncertainty:
    """Result of :func:`frame_uncertainty` (volumes of shape (nz, ny, nx), float64).

    Attributes
    ----------
    refractivity_sigma : ndarray
        Standard error of ``n - 1`` (dimensionless); 0 outside the hull.
    noise_sigma, boundary_sigma, structure_sigma, bias_sigma : ndarray
        Its terms (``refractivity_sigma^2`` is the sum of their squares).
    flow_noise : ndarray, shape (C, 2)
        The flows' measured noise (pixels) the samples were drawn with.
    samples : int
    iterations : tuple of int
        Conjugate-gradient iterations of each sample's tomography solve.
    seconds : float
    bias_iterations : tuple of int
        Conjugate-gradient iterations of the bias term's probe solves.
    """

    refractivity_sigma: np.ndarray
    noise_sigma: np.ndarray
    boundary_sigma: np.ndarray
    structure_sigma: np.ndarray
    flow_noise: np.ndarray
    samples: int = 0
    iterations: tuple = field(default=())
    seconds: float = 0.0
    bias_sigma: np.ndarray | None = None
    bias_iterations: tuple = field(default=())


def frame_uncertainty(geom: TomoGeometry, flows: np.ndarray, quiet: np.ndarray, hull: np.ndarray,
                      gradient: np.ndarray, refractivity: np.ndarray, grid: Grid, *, window_cells,
                      rng: np.random.Generator, binning: int = 1, tomography: TomoParams = TomoParams(),
                      poisson: PoissonParams = PoissonParams(), blur: MeasurementBlur | None = None,
                      volume_blur: float = 0.0,
                      params: UncertaintyParams = UncertaintyParams()) -> FrameUncertainty:
    """Standard error of one frame's refractivity (see the module notes).

    Parameters
    ----------
    geom : TomoGeometry
        The run's geometry.
    flows : ndarray, shape (C, H, W, 2)
        The frame's deflections on the flow grid (pixels; NaN = invalid cell).
    quiet : ndarray, shape (C, H, W) bool
        Flow cells outside every mask (their flow is noise).
    hull : ndarray, shape (nz, ny, nx) bool
    gradient, refractivity : ndarray
        The frame's estimate: ``grad n`` (nz, ny, nx, 3), 1/m, and ``n - 1`` (nz, ny, nx).
    grid : Grid
    window_cells : sequence of float
        Width of each camera's flow averaging (flow cells,
        :func:`~schlieren.pipeline.flow.measurement_sigma` over the flow grid's factor): the
        correlation of the flows' noise.
    rng : numpy.random.Generator
    binning : int
        The run's ray binning (flow cells per ray).
    tomography, poisson : TomoParams, PoissonParams
        The run's (the weight it chose).
    blur, volume_blur :
        The run's flow-window model (:func:`~schlieren.pipeline.tomography.solve_gradient`).
    params : UncertaintyParams

    Returns
    -------
    FrameUncertainty
    """
    t0 = time.perf_counter()
    hull = np.asarray(hull, dtype=bool)
    flows = np.asarray(flows)
    level = flow_noise_level(flows, quiet)
    zero = np.zeros(hull.shape)
    integration = LinearisedIntegration(hull, grid, poisson=poisson, gradient=gradient)
    noise_var, samples, its = zero, 0, ()
    noise_wanted = params.samples > 0 and np.all(np.isfinite(level))
    if params.samples > 0 and not noise_wanted:
        log.warning("uncertainty: no noise measurable outside the masks; the noise term is left out")
    system = None
    if (noise_wanted or (params.bias_scale > 0 and params.bias_probes > 0)) and hull.any():
        ray_flows = bin_cells(flows, binning) if binning > 1 else flows
        system = prepare_frame(geom, hull, dilation=tomography.hull_dilation, rows=valid_rays(ray_flows),
                               prior=tomography.prior, curl=tomography.curl_weight > 0)
    if noise_wanted and system is not None:
        ens = noise_ensemble(geom, system, integration, level=level, window_cells=window_cells, binning=binning,
                             params=tomography, samples=params.samples, rng=rng, blur=blur,
                             volume_blur=volume_blur, flow_shape=flows.shape[:3], prior=params.prior_samples)
        noise_var, samples, its = masked_mean(ens.variance, hull, params.smoothing), ens.samples, ens.iterations
    bias, bias_its = zero, ()
    if params.bias_scale > 0 and system is not None:
        bias, bias_its = _bias_term(system, integration, refractivity, hull, grid, tomography, params, rng,
                                    blur=blur, volume_blur=volume_blur)
    bound = zero
    if params.boundary_scale > 0 and hull.any():
        d = boundary_sensitivity(gradient, integration, grid, poisson=poisson)
        bound = params.boundary_scale * np.sqrt(masked_mean(d * d, hull, params.boundary_smoothing))
    struct = zero
    if params.structure_scale > 0:
        struct = params.structure_scale * curvature_rms(refractivity, hull, smoothing=params.structure_smoothing)
    noise = np.sqrt(np.maximum(noise_var, 0.0))
    total = np.where(hull, np.sqrt(noise * noise + bias * bias + bound * bound + struct * struct), 0.0)
    return FrameUncertainty(refractivity_sigma=total, noise_sigma=noise, boundary_sigma=bound,
                            structure_sigma=struct, flow_noise=level, samples=samples, iterations=its,
                            seconds=time.perf_counter() - t0, bias_sigma=bias, bias_iterations=bias_its)


def _bias_term(system, integration: LinearisedIntegration, refractivity: np.ndarray, hull: np.ndarray, grid: Grid,
               tomography: TomoParams, params: UncertaintyParams, rng: np.random.Generator, *,
               blur: MeasurementBlur | None, volume_blur: float) -> tuple[np.ndarray, tuple]:
    """``bias_scale * loss * local RMS(r - r_ambient)`` and the probes' iterations (module notes)."""
    G = VolumeBlur(system.inset, volume_blur) if volume_blur > 0 and system.inset.any() else None
    res = resolution_loss(system, integration, tomography, h=float(grid.voxel_size), width=params.bias_width,
                          probes=params.bias_probes, smoothing=params.bias_smoothing, rng=rng, blur=blur, volume=G)
    dev = np.asarray(refractivity, dtype=np.float64) - (tomography.n_ambient - 1.0)
    amplitude = np.sqrt(masked_mean(dev * dev, hull, params.bias_smoothing))
    return params.bias_scale * res.loss * amplitude, res.iterations


def frame_rng(params: UncertaintyParams, frame: int) -> np.random.Generator:
    """The noise samples' generator of capture frame ``frame``: seeded by ``(params.seed, frame)``,
    so a frame's sigma does not depend on which task or worker computes it."""
    return np.random.default_rng([params.seed, int(frame)])


def density_sigma(refractivity_sigma: np.ndarray, medium: Medium = Medium()) -> np.ndarray:
    """Standard error of the Gladstone-Dale density (kg/m^3): ``sigma_r / G``."""
    return np.asarray(refractivity_sigma, dtype=np.float64) / medium.gladstone_dale


def temperature_sigma(refractivity: np.ndarray, refractivity_sigma: np.ndarray,
                      medium: Medium = Medium()) -> np.ndarray:
    """Standard error of the temperature (K), first order in ``sigma_r``:
    ``|dT/dr| sigma_r = T_amb r_amb sigma_r / r^2``; NaN where ``r <= 0`` (as
    :func:`~schlieren.pipeline.derived.temperature`)."""
    r = np.asarray(refractivity, dtype=np.float64)
    s = np.asarray(refractivity_sigma, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = medium.T_ambient * medium.refractivity_ambient * s / (r * r)
    return np.where(r > 0, out, np.nan)
