"""The regularisation's bias: what the frame's solve and integration lose of a field (beyond the paper).

The frame's gradient ``x_hat`` solves the regularised normal equations of eq. 5
(:mod:`~schlieren.pipeline.tomography.normal_equations`)

    (N + mu^2 R + mu_c^2 C^T C) x_hat = S^T b,

so it sees the true field through the *resolution operator*
``K = (N + mu^2 R + mu_c^2 C^T C)^-1 N``: its bias is ``(K - I) x_true``, large where few
views cross (the prior fills in what they leave open) and small where many do. For any
field ``x``, re-projecting it through the frame's rays (``S x``, the run's own operator and
flow-window model) and solving with the same regularisation, warm-started at ``x``, moves
it by

    d = K x - x = -(N + mu^2 R + mu_c^2 C^T C)^-1 (mu^2 R + mu_c^2 C^T C) x

(:func:`bias_solve`: the warm start's correction, solved from zero with the regularisers'
pull on ``x`` as its right-hand side; the data cancel exactly). The truth is unknown, and
the estimate is a poor stand-in for it: ``x_hat`` already lies where ``K`` passes fields,
so ``(K - I) x_hat`` misses what the views never saw. :func:`resolution_loss` therefore
probes ``K`` with random fields of the plume's scale instead: smooth random refractivity
fields ``q`` (a Gaussian of ``width`` voxels over white noise), their gradients through
``K - I`` and both through the frame's integration (eq. 8,
:class:`~schlieren.pipeline.uncertainty.LinearisedIntegration`); the local RMS ratio
``loss = rms(A^-1 f((K - I) grad q)) / rms(A^-1 f(grad q))`` is the share of such a field the
reconstruction loses at each voxel, small where many views cross. The bias term of
:func:`~schlieren.pipeline.uncertainty.frame_uncertainty` is that share of the estimate's
local amplitude ``|r - r_ambient|`` times a fitted scale
(:attr:`~schlieren.pipeline.uncertainty.UncertaintyParams.bias_scale`). Cost: one
tomography solve (the run's iteration budget) and two Poisson solves per probe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.regularisers import apply_regulariser, curl_normal
from schlieren.pipeline.tomography.solve import FrameSystem
from schlieren.pipeline.uncertainty.ensemble import perturbation_solve
from schlieren.pipeline.uncertainty.linear_integration import LinearisedIntegration
from schlieren.pipeline.uncertainty.local import masked_mean

__all__ = ["regulariser_pull", "bias_solve", "ResolutionLoss", "resolution_loss", "smooth_probe"]


def regulariser_pull(system: FrameSystem, x: np.ndarray, params: TomoParams) -> np.ndarray:
    """``(mu^2 R + mu_c^2 C^T C) x`` (n, 3): the priors' terms of the frame's normal operator
    on ``x``, with the weights the solve uses (``mu^2 = reg_weight mean(diag(S^T S))``)."""
    n = system.n
    out = np.zeros((n, 3))
    if n == 0:
        return out
    mean_diag = float(np.mean(system.colsumsq))
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(n, 3)
    if params.reg_weight > 0:
        out += params.reg_weight * mean_diag * apply_regulariser(system.LtL, x)
    if params.curl_weight > 0:
        if system.CtC is None:
            system.CtC = curl_normal(system.inset)
        system.CtC.apply3(x, params.curl_weight * mean_diag, out)
    return out


def bias_solve(system: FrameSystem, x_hat: np.ndarray, params: TomoParams, *,
               blur: MeasurementBlur | None = None, volume: VolumeBlur | None = None) -> tuple[np.ndarray, int]:
    """``K x_hat - x_hat`` (n, 3): the re-solve of the estimate's own projection, warm-started
    at it, minus it (module notes); the run's normal equations, stopping rule and budget.
    Returns ``(d, iterations)``."""
    x_hat = np.asarray(x_hat, dtype=np.float64).reshape(system.n, 3)
    zero = np.zeros((system.op.m, 3))
    return perturbation_solve(system, zero, params, blur=blur, volume=volume,
                              extra=-regulariser_pull(system, x_hat, params))


@dataclass(frozen=True)
class ResolutionLoss:
    """Result of :func:`resolution_loss`.

    Attributes
    ----------
    loss : ndarray, shape (nz, ny, nx) float64
        Local share of a smooth random field the solve and integration lose (0 outside the hull).
    probes : int
    iterations : tuple of int
        Conjugate-gradient iterations of each probe's solve.
    """

    loss: np.ndarray
    probes: int
    iterations: tuple


def smooth_probe(hull: np.ndarray, width: float, h: float, rng: np.random.Generator) -> np.ndarray:
    """The gradient (nz, ny, nx, 3; x, y, z components, 1/m) of a random refractivity field:
    white noise smoothed by a Gaussian of ``width`` voxels, unit RMS over ``hull``."""
    q = ndi.gaussian_filter(rng.standard_normal(hull.shape), width, mode="constant")
    q /= max(float(np.sqrt(np.mean(q[hull] ** 2))), 1e-300)
    gz, gy, gx = np.gradient(q, h)
    return np.stack([gx, gy, gz], axis=-1)


def resolution_loss(system: FrameSystem, integration: LinearisedIntegration, params: TomoParams, *,
                    h: float, width: float, probes: int, smoothing: float, rng: np.random.Generator,
                    blur: MeasurementBlur | None = None, volume: VolumeBlur | None = None) -> ResolutionLoss:
    """Local share of a smooth field that the frame's solve and integration lose (module notes).

    Parameters
    ----------
    system : FrameSystem
        The frame's restricted system (as for :func:`~schlieren.pipeline.uncertainty.noise_ensemble`).
    integration : LinearisedIntegration
        The frame's integration operator.
    params : TomoParams
        The run's solve.
    h : float
        Voxel size (m).
    width : float
        The probes' smoothing (voxels): the scale of structure whose loss is measured.
    probes : int
    smoothing : float
        Gaussian width (voxels) of the local mean squares whose ratio is the loss.
    rng : numpy.random.Generator
    blur, volume :
        The run's flow-window model.

    Returns
    -------
    ResolutionLoss
    """
    hull = integration.hull
    inset = system.inset
    num, den = np.zeros(hull.shape), np.zeros(hull.shape)
    its = []
    if system.n == 0 or system.op.m == 0 or not hull.any():
        return ResolutionLoss(num, 0, ())
    for _ in range(int(probes)):
        g = smooth_probe(hull, width, h, rng)
        d, it = bias_solve(system, g[inset], params, blur=blur, volume=volume)
        dg = np.zeros(hull.shape + (3,))
        dg[inset] = d
        num += integration(dg) ** 2
        den += integration(g) ** 2
        its.append(it)
    num, den = masked_mean(num, hull, smoothing), masked_mean(den, hull, smoothing)
    loss = np.where(hull, np.sqrt(num / np.where(den > 0, den, np.inf)), 0.0)
    return ResolutionLoss(loss, len(its), tuple(its))
