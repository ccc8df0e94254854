"""The Appendix's edge-preserving diffusion tensor ``D`` of eq. 8, and the sign constraint.

Diffusion tensor (Appendix): structure tensor ``J = K_sigma * (g g^T)`` (each component
smoothed by a Gaussian of ``sigma`` voxels), eigen-decomposition with
``lambda0 >= lambda1 >= lambda2``, eigenvalues replaced by ``alpha`` (along the dominant
gradient direction) and ``alpha + (1 - alpha) exp(-max|g| / (k (lambda0 - lambda_j)^2))``.

Units of the exponent: the Appendix's ``k = 0.5e-5`` is not dimensionless (the exponent
scales as ``|g|^-3``) and the paper does not give its units. We evaluate it on the
gradient expressed *per voxel* in units in which the field spans ``value_scale``:
``g_hat = g * h * value_scale / range_est``, where ``range_est`` is the largest excursion
of the gradient's running integral along the grid axes (a cheap estimate of the
refractivity range). With ``max|g_hat| = M`` the exponent at a sharp edge is about
``1 / (k M^3)``. With the default ``value_scale = 255`` (an 8-bit volume, like the
paper's fuel-injection data set) the exponent is large almost everywhere on our plumes,
so ``D ~ alpha I`` (equivalent to plain Poisson) except at the sharpest edges. With
16-bit units (65535) the anisotropy is active at the plume's edges. ``alpha = 1`` gives
plain Poisson.

Default ``alpha = 1`` (plain Poisson), chosen by measurement, not by the paper's 0.8: with
the 8-bit units the tensor is almost everywhere ``alpha I``, plain Poisson under another
name, and where it is active (16-bit units) it lost against plain Poisson on the
project's plume and on the realistic family (docs/tuning.md, "Poisson"). The tensor
stays available (``alpha < 1`` with ``value_scale`` 65535).

:func:`sign_constraint` projects the integrated refractivity onto fields of one sign
(``PoissonParams.sign``, beyond the paper).
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.poisson._tensor_kernels import _tensor_from_structure
from schlieren.pipeline.poisson.params import SIGNS, PoissonParams

__all__ = ["sign_constraint", "diffusion_tensor", "SIGNS"]

log = logging.getLogger(__name__)


def sign_constraint(r: np.ndarray, hull: np.ndarray, r_ambient: float, *, sign: str = PoissonParams.sign,
                    max_opposite: float = PoissonParams.sign_max_opposite) -> tuple[np.ndarray, str, float]:
    """Set the hull voxels whose offset ``r - r_ambient`` has the wrong sign to ambient.

    The projection onto fields of one sign (:class:`PoissonParams` ``sign``): a heated
    flow's refractivity never exceeds the ambient one, so positive lobes of its estimate
    are the limited views' ringing. The sign-constrained least-squares integration
    (pinning those voxels at ambient and integrating again, or projected iterations
    towards the constrained optimum) is worse: the data then pull the whole plume towards
    ambient, so the constraint is applied as a projection after the unconstrained solve
    (measurements: benchmarks/results/realistic_no_sign.md, docs/tuning.md "Poisson").

    Parameters
    ----------
    r : ndarray
        Refractivity ``n - 1``.
    hull : ndarray of bool, same shape
        Voxels the constraint applies to (outside, ``r`` is ambient already).
    r_ambient : float
    sign : {"auto", "negative", "positive", "none"}
    max_opposite : float
        ``"auto"``: apply the dominant sign only if the other one holds at most this
        share of ``sum |r - r_ambient|`` over the hull.

    Returns
    -------
    r : ndarray
        A copy with the wrong-sign voxels at ``r_ambient`` (``r`` itself if nothing changed).
    applied : str
        ``"negative"``, ``"positive"`` or ``"none"``.
    clipped : float
        Share of the hull's voxels set to ambient.
    """
    if sign not in SIGNS:
        raise ValueError(f"sign must be one of {SIGNS}, not {sign!r}")
    hull = np.asarray(hull, dtype=bool)
    if sign == "none" or not hull.any():
        return r, "none", 0.0
    u = r[hull] - r_ambient
    if sign == "auto":
        neg = float(-u[u < 0].sum())
        pos = float(u[u > 0].sum())
        if not np.isfinite(neg + pos) or neg + pos == 0.0:  # nothing to go by (or an infinite value)
            return r, "none", 0.0
        sign = "negative" if neg >= pos else "positive"
        opposite = min(neg, pos) / (neg + pos)
        if opposite > max_opposite:
            log.info("integrate: both signs of r - r_ambient (%.0f %% of |r - r_ambient| has the minority sign, "
                     "above sign_max_opposite %.0f %%): no sign applied", 100 * opposite, 100 * max_opposite)
            return r, "none", 0.0
    wrong = u > 0 if sign == "negative" else u < 0
    if not wrong.any():
        return r, sign, 0.0
    out = np.array(r, copy=True)
    out.flat[np.flatnonzero(hull)[wrong]] = r_ambient  # the other voxels keep their exact values
    return out, sign, float(wrong.mean())


def _range_estimate(g: np.ndarray, h: float) -> float:
    """Largest excursion of the running integral of each gradient component along its axis."""
    est = 0.0
    for comp, axis in ((0, 2), (1, 1), (2, 0)):
        c = np.cumsum(g[..., comp], axis=axis) * h
        est = max(est, float(c.max() - c.min()) if c.size else 0.0)
    return est


def diffusion_tensor(g: np.ndarray, h: float, *, alpha: float, sigma: float, k: float,
                     value_scale: float = PoissonParams.value_scale, where: np.ndarray | None = None) -> np.ndarray:
    """Edge-preserving diffusion tensor of the Appendix.

    Parameters
    ----------
    g : ndarray, shape (nz, ny, nx, 3)
        Gradient field (1/m), component 0 = x.
    h : float
        Voxel size, metres.
    alpha, sigma, k, value_scale : float
        See :class:`PoissonParams`.
    where : ndarray, shape (nz, ny, nx) bool, optional
        Voxels at which ``D`` is needed (others are not computed).

    Returns
    -------
    D : ndarray, shape (n_where, 3, 3)
        Symmetric tensors with eigenvalues in ``[alpha, 1]`` (C order of ``where``).
    """
    if where is None:
        where = np.ones(g.shape[:3], bool)
    n = int(where.sum())
    if alpha >= 1.0:
        return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    rng = _range_estimate(g, h)
    scale = h * value_scale / rng if rng > 0 else 0.0
    gh = np.asarray(g, dtype=np.float64) * scale
    M = float(np.sqrt((gh ** 2).sum(axis=-1)).max()) if gh.size else 0.0
    J6 = np.empty((6, n))
    for c, (a, b) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
        J6[c] = ndi.gaussian_filter(gh[..., a] * gh[..., b], sigma, mode="constant")[where]
    D = np.empty((n, 3, 3))
    _tensor_from_structure(J6, M, float(k), float(alpha), D)
    return D
