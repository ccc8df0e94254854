"""The frame's ray noise propagated through its tomography and integration: an ensemble of solves.

The per-frame solve (paper sec. 5, eq. 5, regularised as
:mod:`~schlieren.pipeline.tomography.solve` describes) is linear in its right-hand side up
to the truncation of its conjugate gradients, so the estimate's response to noise ``e``
on the rays is the solve of ``e`` alone: a perturbation, solved from zero with the run's
own system (the frame's hull, rays, weights, flow-window model and iteration budget), not
the whole field again. Each sample draws ``e`` as the flows' measured noise
(:mod:`~schlieren.pipeline.uncertainty.noise`), maps it to right-hand sides as the run
maps its flows (eq. 3, :func:`~schlieren.pipeline.tomography.rhs_from_flows`, through the
ray binning), solves, and integrates the gradient perturbation with the frame's own
integration operator (:class:`~schlieren.pipeline.uncertainty.LinearisedIntegration`).
The mean square of the samples is the noise variance of every voxel's refractivity.

With ``prior`` the samples are perturb-then-optimise samples of the posterior the solve's
normal equations define (Bardsley et al. 2014, "Randomize-then-optimize"): read as a
linear-Gaussian model, ``||S G x - b||^2 + mu^2 x^T R x + mu_c^2 ||C x||^2`` is the negative
log posterior of white ray noise ``sigma`` with the Gaussian priors
``N(0, sigma^2 (mu^2 R)^-1)`` and ``N(0, sigma^2 (mu_c^2 C^T C)^-1)``, and a sample of the
posterior's spread is the solve of the data noise plus the priors' own perturbations
``sigma mu M eta`` (``R = M^2``, ``M = L^T L`` symmetric; :class:`~schlieren.pipeline.
tomography.regularisers.SquaredLaplacian`; ``sigma mu L^T eta`` for the first-difference
prior) and ``sigma mu_c C^T eta_c``. Its variance adds the prior's share, the
regularisation's expected bias, to the noise's; converged, it is the exact posterior
variance (the tests check it against a dense inverse).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.linalg.cg import ConjugateGradient
from schlieren.pipeline.tomography.binning import bin_cells
from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur
from schlieren.pipeline.tomography.geometry import TomoGeometry
from schlieren.pipeline.tomography.normal_equations import DataTerm, data_term, normal_vectors
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.rays import rhs_from_flows
from schlieren.pipeline.tomography.regularisers import SquaredLaplacian, difference_operator
from schlieren.pipeline.tomography.solve import FrameSystem
from schlieren.pipeline.uncertainty.linear_integration import LinearisedIntegration
from schlieren.pipeline.uncertainty.noise import correlated_flow_noise

__all__ = ["NoiseEnsemble", "noise_ensemble", "perturbation_solve", "prior_perturbation"]


@dataclass(frozen=True)
class NoiseEnsemble:
    """Result of :func:`noise_ensemble`.

    Attributes
    ----------
    variance : ndarray, shape (nz, ny, nx) float64
        Mean square of the samples' refractivity perturbations (zero outside the hull).
    samples : int
    iterations : tuple of int
        Conjugate-gradient iterations of each sample's solve.
    seconds : float
    """

    variance: np.ndarray
    samples: int
    iterations: tuple
    seconds: float


def perturbation_solve(system: FrameSystem, e: np.ndarray, params: TomoParams, *,
                       blur: MeasurementBlur | None = None, volume: VolumeBlur | None = None,
                       extra: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """The frame's solve (its normal equations, Jacobi scaling, stopping rule and iteration
    budget, :mod:`~schlieren.pipeline.tomography.normal_equations`) of ray data ``e``
    (m, 3) from zero, with ``extra`` (n, 3) added to the normal equations' right-hand side
    (the priors' perturbations of :func:`prior_perturbation`). Returns ``(x (n, 3), iterations)``."""
    data = data_term(system, e, None, blur=blur, volume=volume)
    if extra is not None:
        data = DataTerm(data.normal, data.colsumsq, data.Stb + extra, data.StSx0)
    vec = normal_vectors(system, e, params, data, None, None)
    res = ConjugateGradient(vec, max_iter=params.max_iter).run()
    return vec.P * res.x, int(res.iterations)


def prior_perturbation(system: FrameSystem, params: TomoParams, sigma: np.ndarray,
                       rng: np.random.Generator) -> np.ndarray:
    """A draw of the priors' perturbation ``sigma mu M eta + sigma mu_c C^T eta_c`` (n, 3)
    of the frame's normal equations (module notes); ``sigma`` (3,) is the white ray noise
    of each component (the curl term, which couples them, takes their RMS)."""
    n = system.n
    colsumsq = system.colsumsq
    mean_diag = float(np.mean(colsumsq)) if n else 0.0
    sigma = np.asarray(sigma, dtype=np.float64).reshape(3)
    out = np.zeros((n, 3))
    if params.reg_weight > 0 and n:
        mu = np.sqrt(params.reg_weight * mean_diag)
        R = system.LtL
        if isinstance(R, SquaredLaplacian):  # R = M^2, M symmetric
            out += mu * sigma * (R.M @ rng.standard_normal((n, 3)))
        else:  # R = L^T L
            L = difference_operator(system.inset)
            out += mu * sigma * (L.T @ rng.standard_normal((L.shape[0], 3)))
    if params.curl_weight > 0 and n and system.CtC is not None:
        muc = np.sqrt(params.curl_weight * mean_diag)
        C = system.CtC.curl_matrix()
        out += muc * float(np.sqrt(np.mean(sigma ** 2))) * (C.T @ rng.standard_normal(C.shape[0])).reshape(n, 3)
    return out


def noise_ensemble(geom: TomoGeometry, system: FrameSystem, integration: LinearisedIntegration, *,
                   level: np.ndarray, window_cells, binning: int, params: TomoParams, samples: int,
                   rng: np.random.Generator, blur: MeasurementBlur | None = None,
                   volume_blur: float = 0.0, flow_shape=None, prior: bool = False) -> NoiseEnsemble:
    """Propagate ``samples`` draws of the flows' noise through the frame's solve and integration.

    Parameters
    ----------
    geom : TomoGeometry
        The run's geometry (rays on the ray grid).
    system : FrameSystem
        The frame's restricted system (:func:`~schlieren.pipeline.tomography.solve.prepare_frame`
        with the run's hull, valid rays, prior and curl term).
    integration : LinearisedIntegration
        The frame's integration operator.
    level : ndarray, shape (C, 2)
        RMS noise of each camera's flow components (pixels, on the flow grid).
    window_cells : sequence of float
        Width of each camera's flow averaging (flow cells): the noise's correlation.
    binning : int
        Flow cells per ray (the run's ray binning): the samples are block-averaged as the flows are.
    params : TomoParams
        The run's solve (its weight, iterations, flow-window model).
    samples : int
    rng : numpy.random.Generator
    blur, volume_blur :
        The run's flow-window model, as for :func:`~schlieren.pipeline.tomography.solve_gradient`.
    flow_shape : (C, H, W), optional
        The flow grid (default: the ray grid times ``binning``).
    prior : bool
        Perturb the priors too (posterior samples, see the module notes), at each sample's
        RMS ray noise per component.

    Returns
    -------
    NoiseEnsemble
    """
    t0 = time.perf_counter()
    C, h, w = (int(v) for v in geom.flow_shape)
    shape = tuple(flow_shape) if flow_shape is not None else (C, h * binning, w * binning)
    op = system.op
    hull_shape = system.inset.shape
    acc = np.zeros(hull_shape)
    its = []
    G = VolumeBlur(system.inset, volume_blur) if volume_blur > 0 and system.inset.any() else None
    if op.n == 0 or op.m == 0 or samples < 1:
        return NoiseEnsemble(acc, 0, (), time.perf_counter() - t0)
    for _ in range(int(samples)):
        noise = correlated_flow_noise(rng, shape, window_cells, level)
        rays = bin_cells(noise, binning) if binning > 1 else noise
        e = rhs_from_flows(geom, rays, n_ambient=params.n_ambient, rays=op.rows)
        extra = prior_perturbation(system, params, np.sqrt(np.mean(e * e, axis=0)), rng) if prior else None
        x, it = perturbation_solve(system, e, params, blur=blur, volume=G, extra=extra)
        dg = np.zeros(hull_shape + (3,))
        dg[system.inset] = x
        du = integration(dg)
        acc += du * du
        its.append(it)
    return NoiseEnsemble(acc / samples, int(samples), tuple(its), time.perf_counter() - t0)
