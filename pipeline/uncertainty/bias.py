"""The regularisation's bias, estimated on the frame's own estimate (beyond the paper).

The frame's gradient ``x_hat`` solves the regularised normal equations of eq. 5
(:mod:`~schlieren.pipeline.tomography.normal_equations`)

    (N + mu^2 R + mu_c^2 C^T C) x_hat = S^T b,

so it sees the true field through the *resolution operator*
``K = (N + mu^2 R + mu_c^2 C^T C)^-1 N``: its bias is ``(K - I) x_true``, large where few
views cross (the prior fills in what they leave open) and small where many do. The truth
is unknown; its best stand-in is the estimate itself. Re-projecting ``x_hat`` through the
frame's rays (``b' = S x_hat``, the run's own operator and flow-window model) and solving
once more with the same regularisation, warm-started at ``x_hat``, moves it by

    d = K x_hat - x_hat = -(N + mu^2 R + mu_c^2 C^T C)^-1 (mu^2 R + mu_c^2 C^T C) x_hat,

which is what :func:`bias_solve` computes: the warm start's correction, solved from zero
with the regularisers' pull on ``x_hat`` as its right-hand side (the same solve, the data
cancel exactly). ``d = (K - I) K x_true`` plus noise: it has the bias's shape and rig
dependence but is smaller than it (each eigencomponent by its resolution ``k in [0, 1]``),
hence the fitted scale (:attr:`~schlieren.pipeline.uncertainty.UncertaintyParams.bias_scale`).
Integrated as the gradient is (eq. 8, the frame's
:class:`~schlieren.pipeline.uncertainty.LinearisedIntegration`), its local RMS is the
bias term of :func:`~schlieren.pipeline.uncertainty.frame_uncertainty`. Cost: one
tomography solve (the run's iteration budget) and one Poisson solve per frame.
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.regularisers import apply_regulariser, curl_normal
from schlieren.pipeline.tomography.solve import FrameSystem
from schlieren.pipeline.uncertainty.ensemble import perturbation_solve
from schlieren.pipeline.uncertainty.linear_integration import LinearisedIntegration

__all__ = ["regulariser_pull", "bias_solve", "regularisation_bias"]


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


def regularisation_bias(system: FrameSystem, gradient: np.ndarray, integration: LinearisedIntegration,
                        params: TomoParams, *, blur: MeasurementBlur | None = None,
                        volume: VolumeBlur | None = None) -> tuple[np.ndarray, int]:
    """The refractivity moved by one more regularised pass over the frame's estimate.

    Parameters
    ----------
    system : FrameSystem
        The frame's restricted system (as for :func:`~schlieren.pipeline.uncertainty.noise_ensemble`).
    gradient : ndarray, shape (nz, ny, nx, 3)
        The frame's estimate ``grad n`` (1/m).
    integration : LinearisedIntegration
        The frame's integration operator.
    params : TomoParams
        The run's solve.
    blur, volume :
        The run's flow-window model.

    Returns
    -------
    du : ndarray, shape (nz, ny, nx) float64
        The integrated ``K x_hat - x_hat`` (zero outside the hull).
    iterations : int
    """
    inset = system.inset
    if system.n == 0 or system.op.m == 0:
        return np.zeros(inset.shape), 0
    x_hat = np.asarray(gradient, dtype=np.float64)[inset]
    d, it = bias_solve(system, x_hat, params, blur=blur, volume=volume)
    dg = np.zeros(inset.shape + (3,))
    dg[inset] = d
    return integration(dg), it
