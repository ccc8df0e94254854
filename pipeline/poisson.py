"""Anisotropic Poisson integration of the reconstructed gradient (paper sec. 5, eq. 8, Appendix).

Solves ``div(D grad n) = div(D g)`` for the refractivity inside the visual hull with the
Dirichlet condition ``r = r_ambient`` outside (paper: ``n = n_air`` outside the hull).
Beyond the paper: where the hull touches a face of the reconstruction box (a plume
rising from a source on the floor or leaving through the top) the flow is not ambient
beyond the face, so by default the differences crossing the box faces are dropped
there (natural boundary, ``box_boundary="neumann"``); on the project's developed plume
this lifts the integration of the true gradient from 35.8 to 53.7 dB.

Discretisation ("first-order forward and backward differences, similar to central
differences", sec. 5): with ``u = r - r_ambient`` (zero outside the hull and outside the
grid) minimise

    E(u) = 1/4 sum_i sum_{s=+,-} (grad_s u_i - g_i)^T D_i (grad_s u_i - g_i),

where ``grad_+`` / ``grad_-`` are the forward / backward difference gradients at voxel
``i``. The normal equations ``A u = f`` with ``A = 1/2 sum_s grad_s^T D grad_s`` are
symmetric positive definite; for ``D = 1`` ``A`` is the 7-point Laplacian and ``f`` the
central-difference divergence of ``g``.

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
16-bit units (65535) the anisotropy is active at the plume's edges, and on the
project's plume (benchmarks/tomography.py, 16 cameras, 48 x 48 x 96) alpha = 0.8 then
*loses* about 1 dB against plain Poisson on tomographic gradients (paper: gains about
1 dB), and 1.5 dB on exact gradients; that is why the inert 8-bit units are the default.
``alpha = 1``
gives plain Poisson.

Default ``alpha = 1`` (plain Poisson), chosen by measurement, not by the paper's 0.8: with
the 8-bit units the tensor is ``alpha I`` in 99.5 % of hull voxels, which is plain Poisson
under another name; where it is active (16-bit units, 4096 or 65535) it lost 0.05-0.1 dB
with alpha 0.8 and 0.45 dB with alpha 0.5 on the realistic benchmark family (CFD plume,
16 cameras, 640x480, 1.4 mm voxels: 40.24 dB plain), and about 1 dB on the project's
smooth plume. The tensor stays available (``alpha < 1`` with ``value_scale`` 65535).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.params import param

__all__ = ["PoissonParams", "PoissonInfo", "integrate", "sign_constraint", "diffusion_tensor", "assemble",
           "SOLVERS", "LaplaceMultigrid", "laplacian_matrix", "pcg"]

log = logging.getLogger(__name__)

SOLVERS = ("mg", "amg", "jacobi_cg")
SIGNS = ("auto", "negative", "positive", "none")


@dataclass(frozen=True)
class PoissonParams:
    """Parameters of :func:`integrate`.

    Attributes
    ----------
    alpha : float
        Data fidelity of the diffusion tensor (Appendix); 1 = plain Poisson (the
        default: the paper's 0.8 measured no gain on the realistic family, see the
        module notes).
    sigma : float
        Gaussian smoothing of the structure tensor, voxels.
    k : float
        Edge constant of the Appendix, in the units described in the module docstring.
    value_scale : float
        The field range those units assume (255: 8-bit volume; see the module notes).
    box_boundary : str
        Where the hull touches a face of the reconstruction box (a plume rising from a
        source at the floor, or leaving through the top) the paper's ``n = n_air``
        outside the hull is wrong. ``"neumann"`` (default) drops the differences that
        cross the box faces there (natural boundary); ``"dirichlet"`` keeps
        ``r = r_ambient`` beyond the box as in the paper. Inside the box the hull
        boundary is always Dirichlet.
    solver : str
        ``"mg"`` (default: CG preconditioned by one geometric-multigrid V-cycle of the
        hull Laplacian, rebuilt per frame at negligible cost), ``"amg"`` (CG
        preconditioned by pyamg smoothed aggregation; its setup dominates) or
        ``"jacobi_cg"`` (the paper's Jacobi-preconditioned CG).
    tol : float
        Relative residual ``||f - A u|| / ||f||`` at which to stop.
    max_iter : int
        Iteration cap.
    sign : str
        The sign of the flow's refractivity offset ``r - r_ambient``: ``"negative"`` for
        gas hotter or lighter than the surrounding air (flames, candles, burners, hot
        jets, helium), ``"positive"`` for colder or denser gas (a CO2 jet, a cold
        plume). Voxels whose estimate has the other sign are set to ambient
        (:func:`sign_constraint`): with few views the reconstruction rings around the
        plume with both signs, and those lobes are artefacts. ``"auto"`` (default) takes
        the sign of the frame's dominant offset and applies it only when the other sign
        holds at most ``sign_max_opposite`` of the summed ``|r - r_ambient|``
        (a flow that really has both signs is left as it is); ``"none"`` keeps every
        value (the paper). Applies to the two-step reconstruction (``reconstruction:
        direct`` writes its solve's refractivity as it is).
    sign_max_opposite : float
        ``"auto"`` applies the sign only below this share of the opposite sign (the
        realistic family's ringing: 1.5-3 %).
    """

    alpha: float = param(1.0, unit="1", gt=0, le=1)
    sigma: float = param(0.5, unit="voxels", ge=0, le=20)
    k: float = param(0.5e-5, unit="1", gt=0, le=1e3)
    value_scale: float = param(255.0, unit="1", gt=0, le=1e9)
    box_boundary: str = param("neumann", choices=("neumann", "dirichlet"))
    solver: str = param("mg", choices=SOLVERS)
    tol: float = param(1e-6, unit="1", gt=0, lt=1)
    max_iter: int = param(5000, unit="1", ge=1, le=100000)
    sign: str = param("auto", choices=SIGNS)
    sign_max_opposite: float = param(0.1, unit="1", ge=0, le=0.5)


@dataclass(frozen=True)
class PoissonInfo:
    """Receipt of one integration (``sign``: the sign applied, ``"none"`` if none;
    ``clipped``: the share of hull voxels it set to ambient)."""

    iterations: int
    residual: float
    solver: str
    n_unknowns: int
    setup_seconds: float
    solve_seconds: float
    sign: str = "none"
    clipped: float = 0.0


def sign_constraint(r: np.ndarray, hull: np.ndarray, r_ambient: float, *, sign: str = "auto",
                    max_opposite: float = 0.1) -> tuple[np.ndarray, str, float]:
    """Set the hull voxels whose offset ``r - r_ambient`` has the wrong sign to ambient.

    The projection onto fields of one sign (:class:`PoissonParams` ``sign``): a heated
    flow's refractivity never exceeds the ambient one, so positive lobes of its estimate
    are the limited views' ringing. Measured on the realistic family's tune cases
    (plume1; whole box / in plume dB, each case with its own pipeline estimate): 16
    cameras 43.08 / 28.66 -> 43.43 / 28.72, 8 cameras 41.47 / 26.95 -> 41.77 / 27.00,
    8 cameras H.264 36.18 / 21.33 -> 36.31 / 21.38; the wrong-sign voxels were 1-2 % of
    the box and held 1.5-3 % of the summed ``|r - r_ambient|``. The sign-constrained
    least-squares integration (pinning those voxels at ambient and integrating again, or
    projected iterations towards the constrained optimum) lost instead (43.08 -> 42.93 and
    42.3-43.4): the data then pull the whole plume towards ambient, so the constraint is
    applied as a projection after the unconstrained solve.

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
                     value_scale: float = 255.0, where: np.ndarray | None = None) -> np.ndarray:
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


@nb.njit(cache=True)
def _eigh3(a, v):
    """Eigen-decomposition of the symmetric 3x3 ``a`` by cyclic Jacobi rotations.

    On return the diagonal of ``a`` holds the eigenvalues and the columns of ``v`` the
    eigenvectors (orthonormal to rounding); ``a`` is overwritten.
    """
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(50):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-32 * diag or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = a[p, q]
            if apq == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for kk in range(3):  # a <- a G (columns p, q)
                akp = a[kk, p]
                akq = a[kk, q]
                a[kk, p] = c * akp - s * akq
                a[kk, q] = s * akp + c * akq
            for kk in range(3):  # a <- G^T a (rows p, q)
                apk = a[p, kk]
                aqk = a[q, kk]
                a[p, kk] = c * apk - s * aqk
                a[q, kk] = s * apk + c * aqk
            a[p, q] = 0.0
            a[q, p] = 0.0
            for kk in range(3):
                vkp = v[kk, p]
                vkq = v[kk, q]
                v[kk, p] = c * vkp - s * vkq
                v[kk, q] = s * vkp + c * vkq


@nb.njit(parallel=True, cache=True)
def _tensor_from_structure(J6, M, k, alpha, D):
    """The Appendix's tensor from the smoothed structure tensor (components xx, yy, zz,
    xy, xz, yz per voxel): eigenvalues ``lambda0 >= lambda1 >= lambda2`` with vectors
    ``v0, v1, v2``; ``D = alpha v0 v0^T + sum_{j=1,2} (alpha + (1 - alpha)
    exp(-M / (k (lambda0 - lambda_j)^2))) v_j v_j^T``.

    ``J`` is positive semi-definite (a Gaussian-weighted sum of ``g g^T``), so every
    eigenvalue gap is at most ``trace(J)``; where even that bound makes both exponentials
    underflow to exactly 0 (``exp(-x) == 0`` for ``x > 745.2``) all eigenvalues are
    alpha and ``D = alpha I`` exactly, with no decomposition (almost everywhere with the
    default units).
    """
    n = J6.shape[1]
    for i in nb.prange(n):
        tr = J6[0, i] + J6[1, i] + J6[2, i]
        for r in range(3):
            for c in range(3):
                D[i, r, c] = 0.0
        inert = tr <= 0.0
        if not inert:
            bound = k * (1.01 * tr) ** 2
            inert = bound == 0.0 or M / bound > 800.0
        if inert:
            D[i, 0, 0] = alpha
            D[i, 1, 1] = alpha
            D[i, 2, 2] = alpha
            continue
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        a[0, 0] = J6[0, i]
        a[1, 1] = J6[1, i]
        a[2, 2] = J6[2, i]
        a[0, 1] = a[1, 0] = J6[3, i]
        a[0, 2] = a[2, 0] = J6[4, i]
        a[1, 2] = a[2, 1] = J6[5, i]
        _eigh3(a, v)
        lam = np.array([a[0, 0], a[1, 1], a[2, 2]])
        order = np.argsort(-lam)  # lambda0 first
        l0 = lam[order[0]]
        for rank in range(3):
            j = order[rank]
            if rank == 0:
                mu = alpha
            else:
                d = (l0 - lam[j]) ** 2
                mu = alpha + (1.0 - alpha) * np.exp(-M / (k * d)) if d > 0.0 else alpha
            for r in range(3):
                for c in range(3):
                    D[i, r, c] += mu * v[r, j] * v[c, j]


@nb.njit(parallel=True, cache=True)
def _assemble_rows(hidx, real, rows_z, rows_y, rows_x, D, g, inv_h, indptr, indices, data, f, count_only):
    """Rows of ``A = 1/2 sum_s grad_s^T D grad_s`` and ``f = 1/2 sum_s grad_s^T D g`` (gathered per row).

    For row voxel ``p`` the forward/backward difference at voxel ``i`` contributes
    ``D_ab(i) / h^2 (delta_{i + s e_a} - delta_i)(delta_{i + s e_b} - delta_i)^T`` with
    ``i = p`` or ``i = p - s e_a``; the 3x3x3 neighbourhood of ``p`` holds every column.
    ``hidx`` maps voxels to unknowns (-1 = Dirichlet zero); a term is kept only if
    ``i``, ``i + s e_a`` and ``i + s e_b`` are all ``real`` (differences that would cross
    a face with a natural boundary are dropped). The arrays are padded so that every
    neighbour index is in bounds.
    """
    n = rows_z.shape[0]
    for r in nb.prange(n):
        k = rows_z[r]
        j = rows_y[r]
        i = rows_x[r]
        acc = np.zeros(27)
        fp = 0.0
        for si in range(2):
            s = 2 * si - 1
            for a in range(3):
                # offset of e_a in (z, y, x) order; component a = 0 is x
                az = 1 if a == 2 else 0
                ay = 1 if a == 1 else 0
                ax = 1 if a == 0 else 0
                k1 = k - s * az
                j1 = j - s * ay
                i1 = i - s * ax
                ok1 = real[k1, j1, i1] and real[k, j, i]  # i1 and i1 + s e_a (= p)
                okp = real[k, j, i] and real[k + s * az, j + s * ay, i + s * ax]
                for b in range(3):
                    bz = 1 if b == 2 else 0
                    by = 1 if b == 1 else 0
                    bx = 1 if b == 0 else 0
                    if ok1 and real[k1 + s * bz, j1 + s * by, i1 + s * bx]:
                        d1 = D[k1, j1, i1, a, b]
                        # i1 terms: +d1 at (i1 + s e_b), -d1 at i1 (offsets relative to p)
                        acc[((-s * az + s * bz) + 1) * 9 + ((-s * ay + s * by) + 1) * 3 + (-s * ax + s * bx) + 1] += d1
                        acc[(-s * az + 1) * 9 + (-s * ay + 1) * 3 + (-s * ax + 1)] -= d1
                        fp += s * d1 * g[k1, j1, i1, b]
                    if okp and real[k + s * bz, j + s * by, i + s * bx]:
                        dp = D[k, j, i, a, b]
                        # p terms: -dp at (p + s e_b), +dp at p
                        acc[(s * bz + 1) * 9 + (s * by + 1) * 3 + (s * bx + 1)] -= dp
                        acc[13] += dp
                        fp -= s * dp * g[k, j, i, b]
        row = hidx[k, j, i]
        if count_only:
            c = 0
            for q in range(27):
                if acc[q] != 0.0 and hidx[k + q // 9 - 1, j + (q // 3) % 3 - 1, i + q % 3 - 1] >= 0:
                    c += 1
            indptr[row + 1] = c
        else:
            pos = indptr[row]
            for q in range(27):
                col = hidx[k + q // 9 - 1, j + (q // 3) % 3 - 1, i + q % 3 - 1]
                if acc[q] != 0.0 and col >= 0:
                    indices[pos] = col
                    data[pos] = 0.5 * acc[q] * inv_h * inv_h
                    pos += 1
            f[row] = 0.5 * fp * inv_h


def assemble(g: np.ndarray, hull: np.ndarray, h: float, *, params: PoissonParams,
             real: np.ndarray | None = None):
    """System ``A u = f`` of the hull-restricted (anisotropic) Poisson problem.

    Parameters
    ----------
    g : ndarray, shape (nz, ny, nx, 3)
        Gradient (1/m).
    hull : ndarray, shape (nz, ny, nx) bool
        Unknowns; ``u = 0`` elsewhere. Must not touch the array boundary (pad first).
    h : float
        Voxel size, metres.
    real : ndarray, shape (nz, ny, nx) bool, optional
        Cells that exist; differences reaching a non-real cell are dropped (natural
        boundary). Default: every cell is real (Dirichlet zero outside the hull).

    Returns
    -------
    A : scipy.sparse.csr_matrix, shape (n, n)
        SPD, units 1/m^2; unknowns in C order of ``hull``.
    f : ndarray, shape (n,)
        1/m^2 (refractivity units).
    """
    hull = np.asarray(hull, dtype=bool)
    if hull[[0, -1]].any() or hull[:, [0, -1]].any() or hull[:, :, [0, -1]].any():
        raise ValueError("the hull must not touch the array boundary (pad it)")
    rows_mask = ndi.binary_dilation(hull, structure=ndi.generate_binary_structure(3, 1))
    g = np.asarray(g, dtype=np.float64)
    Dfull = np.zeros(hull.shape + (3, 3))
    if params.alpha >= 1.0:
        Dfull[rows_mask] = np.eye(3)
    else:
        Dfull[rows_mask] = diffusion_tensor(g, h, alpha=params.alpha, sigma=params.sigma, k=params.k,
                                            value_scale=params.value_scale, where=rows_mask)
    if real is None:
        real = np.ones(hull.shape, bool)
    real = np.ascontiguousarray(real, dtype=np.bool_)
    n = int(hull.sum())
    hidx = np.full(hull.shape, -1, np.int64)
    hidx[hull] = np.arange(n)
    rz, ry, rx = (np.ascontiguousarray(a) for a in np.nonzero(hull))
    indptr = np.zeros(n + 1, np.int64)
    f = np.zeros(n)
    empty_i = np.empty(0, np.int32)
    empty_d = np.empty(0, np.float64)
    _assemble_rows(hidx, real, rz, ry, rx, Dfull, g, 1.0 / h, indptr, empty_i, empty_d, f, True)
    np.cumsum(indptr, out=indptr)
    indices = np.empty(int(indptr[-1]), np.int32)
    data = np.empty(int(indptr[-1]))
    _assemble_rows(hidx, real, rz, ry, rx, Dfull, g, 1.0 / h, indptr, indices, data, f, False)
    A = sp.csr_matrix((data, indices, indptr), shape=(n, n))
    A.has_sorted_indices = True
    return A, f


# -- geometric multigrid preconditioner ---------------------------------------------
#
# V-cycle for the 7-point Laplacian on the hull (Dirichlet outside), the preconditioner of
# the "mg" solver. The diffusion tensor's eigenvalues lie in [alpha, 1], so the plain
# Laplacian on the same hull is spectrally equivalent to the anisotropic operator
# (condition number of the preconditioned system <= 1 / alpha) and one Laplacian V-cycle
# preconditions both. Matrix-free numba kernels and a setup of a few milliseconds, so it
# is rebuilt for every frame's hull (pyamg's setup alone costs more than the whole solve
# at these sizes).
#
# Hierarchy: cell-centred, on the bounding box of the hull; a coarse cell is active if at
# least ``min_children`` of its 2x2x2 children are. Prolongation is cell-centred trilinear,
# restriction its transpose / 8. Coarse operators are 7-point stencils with per-face
# weights from an aggregation (piecewise-constant) Galerkin product: the weight of a coarse
# face is the number of active fine faces crossing it / 4 (exactly the rediscretised
# Laplacian where the blocks are full), and the Dirichlet part of a coarse diagonal is half
# the sum of its children's (the uncorrected Galerkin value). A plain rediscretisation
# moves the Dirichlet boundary outwards by half a coarse cell per level; the V-cycle then
# over-corrects the smooth modes and *diverges* as a stationary iteration (factor 1.9 per
# cycle even on a full box), which costs CG 15-24 instead of 9-10 iterations on the
# plume hull (benchmarks/poisson.py).
#
# Smoothing: red-black Gauss-Seidel, red then black before the coarse correction and
# black then red after it (the V-cycle is symmetric, as CG requires). Starting from zero,
# the first red half-sweep needs no neighbours and after the black half-sweep the residual
# vanishes on black cells, so the pre-smoothing and the residual each cost about half a
# sweep. The finest level iterates over lists of its active cells (the hull fills under
# half of its bounding box); the coarsest level is solved by sparse LU.


@nb.njit(cache=True)
def _gs_cells(u, f, inv_dg, h2, cells, sy, sz, first):
    """Gauss-Seidel update of the listed cells of one colour (finest level, unit weights).

    ``u``, ``f`` and ``inv_dg`` are flattened boxes whose outer layer is inactive, so
    every neighbour index is in bounds; inactive cells hold zero. With ``first`` the
    neighbours are known to be zero (the red half-sweep from a zero start).
    """
    if first:
        for c in range(cells.shape[0]):
            p = cells[c]
            u[p] = f[p] * h2 * inv_dg[p]
        return
    for c in range(cells.shape[0]):
        p = cells[c]
        u[p] = (f[p] * h2 + u[p - 1] + u[p + 1] + u[p - sy] + u[p + sy] + u[p - sz] + u[p + sz]) * inv_dg[p]


@nb.njit(cache=True)
def _scatter_first(r, flat, is_red, h2, inv_dg, f, u):
    """``f[flat] = r`` and the first red half-sweep from zero (finest level)."""
    for c in range(flat.shape[0]):
        p = flat[c]
        f[p] = r[c]
        if is_red[c]:
            u[p] = r[c] * h2 * inv_dg[p]


@nb.njit(cache=True)
def _gs_red_gather(u, f, inv_dg, h2, flat, is_red, sy, sz, out):
    """The last red half-sweep of the finest level, gathering ``out = u[flat]`` on the way."""
    for c in range(flat.shape[0]):
        p = flat[c]
        if is_red[c]:
            u[p] = (f[p] * h2 + u[p - 1] + u[p + 1] + u[p - sy] + u[p + sy] + u[p - sz] + u[p + sz]) * inv_dg[p]
        out[c] = u[p]


@nb.njit(cache=True)
def _residual_cells(u, f, dg, inv_h2, cells, sy, sz, out):
    """``out = f - A u`` on the listed cells (finest level); other entries untouched.

    After a black half-sweep the residual vanishes on black cells, so the V-cycle
    computes it on the red cells only.
    """
    for c in range(cells.shape[0]):
        p = cells[c]
        s = dg[p] * u[p] - (u[p - 1] + u[p + 1] + u[p - sy] + u[p + sy] + u[p - sz] + u[p + sz])
        out[p] = f[p] - s * inv_h2


@nb.njit(cache=True)
def _gs_weighted(u, f, mask, wx, wy, wz, inv_dg, h2, colour, first):
    """Gauss-Seidel half-sweep on one colour of a coarse level (per-face weights).

    ``wx[k, j, i]`` weights the face between ``(k, j, i)`` and ``(k, j, i + 1)`` (zero at
    the array edge and next to inactive cells), likewise ``wy`` and ``wz``.
    """
    nz, ny, nx = u.shape
    for k in range(nz):
        for j in range(ny):
            for i in range((colour + k + j) % 2, nx, 2):
                if not mask[k, j, i]:
                    continue
                s = f[k, j, i] * h2
                if not first:
                    if i > 0:
                        s += wx[k, j, i - 1] * u[k, j, i - 1]
                    if i < nx - 1:
                        s += wx[k, j, i] * u[k, j, i + 1]
                    if j > 0:
                        s += wy[k, j - 1, i] * u[k, j - 1, i]
                    if j < ny - 1:
                        s += wy[k, j, i] * u[k, j + 1, i]
                    if k > 0:
                        s += wz[k - 1, j, i] * u[k - 1, j, i]
                    if k < nz - 1:
                        s += wz[k, j, i] * u[k + 1, j, i]
                u[k, j, i] = s * inv_dg[k, j, i]


@nb.njit(cache=True)
def _residual_weighted(u, f, mask, wx, wy, wz, dg, inv_h2, colour, out):
    """``out = f - A u`` on the active cells of one colour of a coarse level."""
    nz, ny, nx = u.shape
    for k in range(nz):
        for j in range(ny):
            for i in range((colour + k + j) % 2, nx, 2):
                if not mask[k, j, i]:
                    continue
                s = dg[k, j, i] * u[k, j, i]
                if i > 0:
                    s -= wx[k, j, i - 1] * u[k, j, i - 1]
                if i < nx - 1:
                    s -= wx[k, j, i] * u[k, j, i + 1]
                if j > 0:
                    s -= wy[k, j - 1, i] * u[k, j - 1, i]
                if j < ny - 1:
                    s -= wy[k, j, i] * u[k, j + 1, i]
                if k > 0:
                    s -= wz[k - 1, j, i] * u[k - 1, j, i]
                if k < nz - 1:
                    s -= wz[k, j, i] * u[k + 1, j, i]
                out[k, j, i] = f[k, j, i] - s * inv_h2


@nb.njit(cache=True)
def _restrict(r, mask_c, tx, ty, out):
    """Full weighting: transpose of :func:`_prolong_add` divided by 8.

    Separable: the 1-D weights (1/4, 3/4, 3/4, 1/4) on fine cells ``2K-1 .. 2K+2`` are
    applied along x (into ``tx``), then y (``ty``), then z (fine cells outside the array
    count as zero).
    """
    cz, cy, cx = out.shape
    fz, fy, fx = r.shape
    for k in range(fz):
        for j in range(fy):
            for I in range(cx):
                s = 0.0
                for c in range(4):
                    i = 2 * I - 1 + c
                    if 0 <= i < fx:
                        s += (0.25 if c == 0 or c == 3 else 0.75) * r[k, j, i]
                tx[k, j, I] = s
    for k in range(fz):
        for J in range(cy):
            for I in range(cx):
                s = 0.0
                for b in range(4):
                    j = 2 * J - 1 + b
                    if 0 <= j < fy:
                        s += (0.25 if b == 0 or b == 3 else 0.75) * tx[k, j, I]
                ty[k, J, I] = s
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                if not mask_c[K, J, I]:
                    out[K, J, I] = 0.0
                    continue
                s = 0.0
                for a in range(4):
                    k = 2 * K - 1 + a
                    if 0 <= k < fz:
                        s += (0.25 if a == 0 or a == 3 else 0.75) * ty[k, J, I]
                out[K, J, I] = 0.125 * s


@nb.njit(cache=True)
def _prolong_add(uc, mask_f, ex, ey, uf):
    """Add the trilinear (cell-centred) interpolation of ``uc`` to the active fine cells.

    Fine cell ``k`` takes 3/4 of coarse cell ``k // 2`` and 1/4 of its other neighbour
    (``k // 2 - 1`` for even ``k``, ``k // 2 + 1`` for odd; zero outside the array),
    separably along x (into ``ex``), y (``ey``) and z.
    """
    fz, fy, fx = uf.shape
    cz, cy, cx = uc.shape
    for K in range(cz):
        for J in range(cy):
            for i in range(fx):
                I = i // 2
                In = I - 1 if i % 2 == 0 else I + 1
                s = 0.75 * uc[K, J, I] if I < cx else 0.0
                if 0 <= In < cx:
                    s += 0.25 * uc[K, J, In]
                ex[K, J, i] = s
    for K in range(cz):
        for j in range(fy):
            J = j // 2
            Jn = J - 1 if j % 2 == 0 else J + 1
            for i in range(fx):
                s = 0.75 * ex[K, J, i] if J < cy else 0.0
                if 0 <= Jn < cy:
                    s += 0.25 * ex[K, Jn, i]
                ey[K, j, i] = s
    for k in range(fz):
        K = k // 2
        Kn = K - 1 if k % 2 == 0 else K + 1
        for j in range(fy):
            for i in range(fx):
                if not mask_f[k, j, i]:
                    continue
                s = 0.75 * ey[K, j, i] if K < cz else 0.0
                if 0 <= Kn < cz:
                    s += 0.25 * ey[Kn, j, i]
                uf[k, j, i] += s


@nb.njit(cache=True)
def _fine_level(mask, real, wx, wy, wz, ddir, dg, inv_dg):
    """Finest level: unit face weights between active cells, the Dirichlet part of each
    active diagonal, the diagonal itself, and the active cells as flat indices (all with
    their colour, red, black).

    A neighbour that is inactive but ``real`` is a Dirichlet face; one that is not
    ``real`` is a natural face and counts for nothing. ``mask``'s outer layer is inactive.
    """
    nz, ny, nx = mask.shape
    n = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                n += mask[k, j, i]
    flat = np.empty(n, np.int64)
    is_red = np.zeros(n, np.bool_)
    red = np.empty(n, np.int64)
    black = np.empty(n, np.int64)
    a = nr = nb_ = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if not mask[k, j, i]:
                    continue
                p = (k * ny + j) * nx + i
                flat[a] = p
                if (k + j + i) % 2 == 0:
                    is_red[a] = True
                    red[nr] = p
                    nr += 1
                else:
                    black[nb_] = p
                    nb_ += 1
                a += 1
                wx[k, j, i] = 1.0 if mask[k, j, i + 1] else 0.0
                wy[k, j, i] = 1.0 if mask[k, j + 1, i] else 0.0
                wz[k, j, i] = 1.0 if mask[k + 1, j, i] else 0.0
                d = 0.0
                faces = 0.0
                for dk, dj, di in ((0, 0, -1), (0, 0, 1), (0, -1, 0), (0, 1, 0), (-1, 0, 0), (1, 0, 0)):
                    kk, jj, ii = k + dk, j + dj, i + di
                    if real[kk, jj, ii]:
                        faces += 1.0
                        if not mask[kk, jj, ii]:
                            d += 1.0
                ddir[k, j, i] = d
                dg[k, j, i] = faces
                inv_dg[k, j, i] = 1.0 / faces
    return flat, is_red, red[:nr], black[:nb_]


@nb.njit(cache=True)
def _coarsen(mask, wx, wy, wz, ddir, min_children, dirichlet_scale, mc, Wx, Wy, Wz, Dc):
    """Aggregation-Galerkin coarse level (see the section comment); outputs zero-filled.

    Returns the number of active coarse cells.
    """
    nz, ny, nx = mask.shape
    cz, cy, cx = mc.shape
    cnt = np.zeros(mc.shape, np.int64)
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                K, J, I = k // 2, j // 2, i // 2
                if mask[k, j, i]:
                    cnt[K, J, I] += 1
                    Dc[K, J, I] += dirichlet_scale * ddir[k, j, i]
                # fine faces crossing a block boundary (odd index -> next block)
                if i % 2 == 1 and I + 1 < cx:
                    Wx[K, J, I] += 0.25 * wx[k, j, i]
                if j % 2 == 1 and J + 1 < cy:
                    Wy[K, J, I] += 0.25 * wy[k, j, i]
                if k % 2 == 1 and K + 1 < cz:
                    Wz[K, J, I] += 0.25 * wz[k, j, i]
    active = 0
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                mc[K, J, I] = cnt[K, J, I] >= min_children
                active += mc[K, J, I]
    # faces touching a coarse cell dropped by min_children become Dirichlet faces
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                for d in range(3):
                    K2, J2, I2 = K + (d == 2), J + (d == 1), I + (d == 0)
                    if K2 >= cz or J2 >= cy or I2 >= cx:
                        continue
                    w = Wx[K, J, I] if d == 0 else (Wy[K, J, I] if d == 1 else Wz[K, J, I])
                    if w == 0.0:
                        continue
                    a, b = mc[K, J, I], mc[K2, J2, I2]
                    if not (a and b):
                        if a:
                            Dc[K, J, I] += w
                        if b:
                            Dc[K2, J2, I2] += w
                        if d == 0:
                            Wx[K, J, I] = 0.0
                        elif d == 1:
                            Wy[K, J, I] = 0.0
                        else:
                            Wz[K, J, I] = 0.0
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                if not mc[K, J, I]:
                    Dc[K, J, I] = 0.0
    return active


def _weighted_matrix(mask, wx, wy, wz, dg, h) -> sp.csr_matrix:
    n = int(mask.sum())
    idx = np.full(mask.shape, -1, np.int64)
    idx[mask] = np.arange(n)
    rows, cols, vals = [np.arange(n)], [np.arange(n)], [dg[mask]]
    for w, a, b in ((wx, np.s_[:, :, :-1], np.s_[:, :, 1:]), (wy, np.s_[:, :-1], np.s_[:, 1:]),
                    (wz, np.s_[:-1], np.s_[1:])):
        ia, ib, ww = idx[a].ravel(), idx[b].ravel(), w[a].ravel()
        ok = (ia >= 0) & (ib >= 0) & (ww != 0)
        rows += [ia[ok], ib[ok]]
        cols += [ib[ok], ia[ok]]
        vals += [-ww[ok], -ww[ok]]
    return sp.csr_matrix((np.concatenate(vals) / h ** 2, (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n))


def _diag_counts(real: np.ndarray | None, shape) -> np.ndarray:
    """6 minus the number of in-bounds neighbours that are not ``real`` (natural faces)."""
    dg = np.full(shape, 6.0)
    if real is None:
        return dg
    absent = ~np.asarray(real, dtype=bool)
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis] = slice(0, -1)
        b[axis] = slice(1, None)
        dg[tuple(a)] -= absent[tuple(b)]
        dg[tuple(b)] -= absent[tuple(a)]
    return dg


def laplacian_matrix(mask: np.ndarray, h: float, real: np.ndarray | None = None) -> sp.csr_matrix:
    """The 7-point Laplacian (1/m^2, positive definite) on the active cells, zero outside.

    Neighbours that are not ``real`` (default: all are) are dropped (natural boundary).
    """
    n = int(mask.sum())
    idx = np.full(mask.shape, -1, np.int64)
    idx[mask] = np.arange(n)
    rows = [np.arange(n)]
    cols = [np.arange(n)]
    vals = [_diag_counts(real, mask.shape)[mask] / h ** 2]
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis] = slice(0, -1)
        b[axis] = slice(1, None)
        ia = idx[tuple(a)].ravel()
        ib = idx[tuple(b)].ravel()
        ok = (ia >= 0) & (ib >= 0)
        rows += [ia[ok], ib[ok]]
        cols += [ib[ok], ia[ok]]
        vals += [np.full(int(ok.sum()), -1.0 / h ** 2)] * 2
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


class LaplaceMultigrid:
    """V-cycle preconditioner for the masked Laplacian.

    Parameters
    ----------
    mask : ndarray, shape (nz, ny, nx) bool
        Active cells (unknowns); values outside are zero (Dirichlet).
    h : float
        Grid spacing (metres) of the finest level.
    smooth : int
        Red-black Gauss-Seidel sweeps before (red-black) and after (black-red) the
        coarse correction; the reversed order keeps the V-cycle symmetric.
    coarse_size : int
        Stop coarsening below this many active cells and solve exactly.
    min_children : int
        A coarse cell is active if at least this many of its eight children are.
    real : ndarray, shape (nz, ny, nx) bool, optional
        Cells that exist (as in :func:`assemble`): a neighbour that is not real is
        dropped from the stencil (natural boundary, e.g. beyond a box face the hull
        touches) instead of holding zero. Default: all cells exist (Dirichlet
        everywhere). Without it the preconditioner of a problem with natural faces
        misses the smooth modes there.
    dirichlet_scale : float
        Factor from the children's Dirichlet diagonal to the coarse one (see the
        section comment; 0.5 is the Galerkin value).

    Notes
    -----
    Works on the bounding box of the mask (plus one inactive layer), so the cost scales
    with the hull, not with the grid. As a CG preconditioner it needs 9-10 iterations
    for a 1e-6 residual on the 134k-voxel plume hull of benchmarks/poisson.py, with
    natural or Dirichlet box faces (12-13 for 1e-8), against 180-240 for Jacobi-PCG; a
    V-cycle costs about 2.3 ms there, the setup about 6 ms, and the whole solve is
    5.2-5.9x faster than Jacobi-PCG with the default alpha = 0.8 (4.1-4.5x for plain
    Poisson, whose 7-point operator makes each Jacobi iteration cheaper). Vectors
    passed to :meth:`apply` are ordered like ``mask[mask]`` (C order).
    """

    def __init__(self, mask: np.ndarray, h: float, *, smooth: int = 1, coarse_size: int = 300,
                 min_children: int = 1, real: np.ndarray | None = None, dirichlet_scale: float = 0.5):
        mask = np.asarray(mask, dtype=np.bool_)
        if smooth < 1:
            raise ValueError("smooth must be >= 1")
        lo, hi = [], []
        for axis in range(3):
            occupied = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
            if len(occupied) == 0:
                raise ValueError("empty mask")
            lo.append(int(occupied[0]) - 1)
            hi.append(int(occupied[-1]) + 2)
        # Crop to the bounding box plus one layer; beyond the array the cells are absent
        # from A (zero: Dirichlet), so pad with inactive real cells where the box leaves it.
        pad = [(max(-a, 0), max(b - s, 0)) for a, b, s in zip(lo, hi, mask.shape)]
        box = tuple(slice(max(a, 0), min(b, s)) for a, b, s in zip(lo, hi, mask.shape))
        crop = mask[box]
        crop = np.ascontiguousarray(np.pad(crop, pad) if any(map(any, pad)) else crop)
        if real is None:
            real_c = np.ones(crop.shape, np.bool_)
        else:
            real_c = np.asarray(real, dtype=np.bool_)[box]
            real_c = np.ascontiguousarray(np.pad(real_c, pad, constant_values=True) if any(map(any, pad))
                                          else real_c)
        shape0 = crop.shape
        wx, wy, wz, dd, dg0, inv_dg0 = (np.zeros(shape0) for _ in range(6))
        self._flat, self._is_red, self._red, self._black = _fine_level(
            crop, real_c, wx, wy, wz, dd, dg0, inv_dg0)
        self._dg0, self._inv_dg0 = dg0.ravel(), inv_dg0.ravel()
        self.n = int(len(self._flat))
        self.smooth = int(smooth)
        self._sy, self._sz = shape0[2], shape0[1] * shape0[2]
        self.masks = [crop]
        self.hs = [float(h)]
        self._ops: list[tuple] = [None]
        active = self.n
        while active > coarse_size and min(self.masks[-1].shape) > 2:
            cshape = tuple((s + 1) // 2 for s in self.masks[-1].shape)
            mc = np.zeros(cshape, np.bool_)
            Wx, Wy, Wz, Dd = (np.zeros(cshape) for _ in range(4))
            active = _coarsen(self.masks[-1], wx, wy, wz, dd, int(min_children), float(dirichlet_scale),
                              mc, Wx, Wy, Wz, Dd)
            dg = Dd.copy()
            dg[:, :, :-1] += Wx[:, :, :-1]
            dg[:, :, 1:] += Wx[:, :, :-1]
            dg[:, :-1] += Wy[:, :-1]
            dg[:, 1:] += Wy[:, :-1]
            dg[:-1] += Wz[:-1]
            dg[1:] += Wz[:-1]
            inv_dg = np.where(mc, 1.0 / np.where(mc, dg, 1.0), 0.0)
            self.masks.append(mc)
            self.hs.append(2 * self.hs[-1])
            self._ops.append((Wx, Wy, Wz, dg, inv_dg))
            wx, wy, wz, dd = Wx, Wy, Wz, Dd
        if len(self.masks) > 1:
            Wx, Wy, Wz, dg, _ = self._ops[-1]
            A_c = _weighted_matrix(self.masks[-1], Wx, Wy, Wz, dg, self.hs[-1])
        else:
            A_c = laplacian_matrix(crop, h, real_c)
        self._coarse = spla.splu(A_c.tocsc())
        # Work arrays, reused by every cycle. u and f of each level are only ever written
        # at active cells (u at level 0 is overwritten by the first red half-sweep); the
        # residuals only at active cells of one colour, so their other entries stay zero.
        self._u = [np.zeros(m.shape) for m in self.masks]
        self._f = [np.zeros(m.shape) for m in self.masks]
        self._res = [np.zeros(m.shape) for m in self.masks]
        self._tmp = []
        for fine, coarse in zip(self.masks[:-1], self.masks[1:]):
            fz, fy, _ = fine.shape
            cz, cy, cx = coarse.shape
            self._tmp.append((np.empty((fz, fy, cx)), np.empty((fz, cy, cx)),
                              np.empty((cz, cy, fine.shape[2])), np.empty((cz, fy, fine.shape[2]))))

    @property
    def levels(self) -> int:
        return len(self.masks)

    def _vcycle(self, level: int) -> np.ndarray:
        """V-cycle from zero for ``self._f[level]`` (level >= 1); the result is left in
        ``self._u[level]``."""
        mask, u, f, res = self.masks[level], self._u[level], self._f[level], self._res[level]
        if level == len(self.masks) - 1:
            u[mask] = self._coarse.solve(f[mask])
            return u
        h2 = self.hs[level] ** 2
        wx, wy, wz, dg, inv_dg = self._ops[level]
        for s in range(self.smooth):
            _gs_weighted(u, f, mask, wx, wy, wz, inv_dg, h2, 0, s == 0)
            _gs_weighted(u, f, mask, wx, wy, wz, inv_dg, h2, 1, False)
        _residual_weighted(u, f, mask, wx, wy, wz, dg, 1.0 / h2, 0, res)
        tx, ty, ex, ey = self._tmp[level]
        _restrict(res, self.masks[level + 1], tx, ty, self._f[level + 1])
        uc = self._vcycle(level + 1)
        _prolong_add(uc, mask, ex, ey, u)
        for _ in range(self.smooth):
            _gs_weighted(u, f, mask, wx, wy, wz, inv_dg, h2, 1, False)
            _gs_weighted(u, f, mask, wx, wy, wz, inv_dg, h2, 0, False)
        return u

    def apply(self, r: np.ndarray) -> np.ndarray:
        """One V-cycle from zero for the right-hand side ``r`` (vector over active cells)."""
        r = np.ascontiguousarray(r, dtype=np.float64)
        if r.shape != (self.n,):
            raise ValueError(f"expected a vector of {self.n} values, got shape {r.shape}")
        out = np.empty(self.n)
        u, f = self._u[0].ravel(), self._f[0].ravel()
        if len(self.masks) == 1:
            out[:] = self._coarse.solve(r)
            return out
        h2 = self.hs[0] ** 2
        flat, is_red, red, black = self._flat, self._is_red, self._red, self._black
        inv_dg, sy, sz = self._inv_dg0, self._sy, self._sz
        _scatter_first(r, flat, is_red, h2, inv_dg, f, u)
        _gs_cells(u, f, inv_dg, h2, black, sy, sz, False)
        for _ in range(1, self.smooth):
            _gs_cells(u, f, inv_dg, h2, red, sy, sz, False)
            _gs_cells(u, f, inv_dg, h2, black, sy, sz, False)
        _residual_cells(u, f, self._dg0, 1.0 / h2, red, sy, sz, self._res[0].ravel())
        tx, ty, ex, ey = self._tmp[0]
        _restrict(self._res[0], self.masks[1], tx, ty, self._f[1])
        uc = self._vcycle(1)
        _prolong_add(uc, self.masks[0], ex, ey, self._u[0])
        for s in range(self.smooth):
            _gs_cells(u, f, inv_dg, h2, black, sy, sz, False)
            if s < self.smooth - 1:
                _gs_cells(u, f, inv_dg, h2, red, sy, sz, False)
        _gs_red_gather(u, f, inv_dg, h2, flat, is_red, sy, sz, out)
        return out

    def as_linear_operator(self) -> spla.LinearOperator:
        return spla.LinearOperator((self.n, self.n), matvec=self.apply, dtype=np.float64)


@nb.njit(cache=True, fastmath=True)
def _dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@nb.njit(cache=True, fastmath=True)
def _cg_update(x, r, p, q, alpha):
    """``x += alpha p``, ``r -= alpha q``; returns ``r . r``."""
    s = 0.0
    for i in range(x.shape[0]):
        x[i] += alpha * p[i]
        ri = r[i] - alpha * q[i]
        r[i] = ri
        s += ri * ri
    return s


@nb.njit(cache=True, fastmath=True)
def _cg_direction(p, z, beta):
    for i in range(p.shape[0]):
        p[i] = z[i] + beta * p[i]


def pcg(A: sp.csr_matrix, f: np.ndarray, precond, *, x0: np.ndarray | None = None, tol: float,
        max_iter: int) -> tuple[np.ndarray, int]:
    """Preconditioned conjugate gradients for SPD ``A`` (the solver of "mg" and "jacobi_cg").

    Stops when ``||f - A u|| <= tol ||f||`` (scipy's ``cg`` criterion with ``atol = 0``).
    The vector operations are serial numba loops, not BLAS calls: on a small shared
    machine a multithreaded BLAS ``dot`` on a 10^5-vector costs milliseconds of thread
    wake-up (measured 7 ms against 19 us single-threaded), more than the multigrid
    V-cycle itself; the result is also independent of the BLAS thread count.

    Parameters
    ----------
    A : scipy.sparse.csr_matrix, shape (n, n)
    f : ndarray, shape (n,)
    precond : callable
        ``precond(r) -> z``, a symmetric positive definite approximation of ``A^-1``.
    x0 : ndarray, shape (n,), optional
    tol : float
    max_iter : int

    Returns
    -------
    u : ndarray, shape (n,)
    iterations : int
    """
    f = np.ascontiguousarray(f, dtype=np.float64)
    x = np.zeros_like(f) if x0 is None else np.array(x0, dtype=np.float64, copy=True)
    r = f - A @ x if x0 is not None else f.copy()
    thresh2 = (tol * np.sqrt(_dot(f, f))) ** 2
    rr = _dot(r, r)
    it = 0
    if rr <= thresh2:
        return x, 0
    z = np.ascontiguousarray(precond(r))
    p = z.copy()
    rz = _dot(r, z)
    while it < max_iter:
        q = A @ p
        pq = _dot(p, q)
        if pq <= 0.0:
            break
        alpha = rz / pq
        rr = _cg_update(x, r, p, q, alpha)
        it += 1
        if rr <= thresh2:
            break
        z = np.ascontiguousarray(precond(r))
        rz_new = _dot(r, z)
        _cg_direction(p, z, rz_new / rz)
        rz = rz_new
    return x, it


def _solve(A: sp.csr_matrix, f: np.ndarray, x0: np.ndarray | None, solver: str, tol: float, max_iter: int,
           mask: np.ndarray, h: float, real: np.ndarray | None = None):
    """Solve ``A u = f``; returns (u, iterations, relative residual, setup s, solve s).

    ``real`` (as in :func:`assemble`) gives the multigrid preconditioner the same natural
    faces as ``A``.
    """
    t0 = time.perf_counter()
    f = np.ascontiguousarray(f, dtype=np.float64)
    fn = float(np.sqrt(_dot(f, f)))
    if fn == 0.0:
        return np.zeros_like(f), 0, 0.0, 0.0, 0.0
    if solver == "jacobi_cg":
        dinv = 1.0 / A.diagonal()
        t1 = time.perf_counter()
        u, it = pcg(A, f, lambda v: dinv * v, x0=x0, tol=tol, max_iter=max_iter)
    elif solver == "mg":
        mg = LaplaceMultigrid(mask, h, real=real)
        t1 = time.perf_counter()
        u, it = pcg(A, f, mg.apply, x0=x0, tol=tol, max_iter=max_iter)
    elif solver == "amg":
        import pyamg

        ml = pyamg.smoothed_aggregation_solver(A, symmetry="symmetric", max_coarse=500)
        t1 = time.perf_counter()
        res: list[float] = []
        u = ml.solve(f, x0=x0, tol=tol, maxiter=max_iter, accel="cg", residuals=res)
        it = max(len(res) - 1, 0)
    else:
        raise ValueError(f"unknown Poisson solver {solver!r}; choose one of {SOLVERS}")
    t2 = time.perf_counter()
    res = f - A @ u
    rel = float(np.sqrt(_dot(res, res)) / fn)
    return u, it, rel, t1 - t0, t2 - t1


def integrate(gradient: np.ndarray, hull: np.ndarray, grid: Grid, *, r_ambient: float,
              params: PoissonParams = PoissonParams(), x0: np.ndarray | None = None
              ) -> tuple[np.ndarray, PoissonInfo]:
    """Integrate a gradient field into refractivity inside the visual hull (eq. 8).

    Parameters
    ----------
    gradient : ndarray, shape (nz, ny, nx, 3)
        ``grad n`` in 1/m, component 0 = x.
    hull : ndarray, shape (nz, ny, nx) bool
        Voxels to solve for; outside, ``r = r_ambient`` (Dirichlet).
    grid : Grid
    r_ambient : float
        ``n_ambient - 1``.
    params : PoissonParams
    x0 : ndarray, shape (nz, ny, nx), optional
        Warm start (e.g. the previous frame's refractivity).

    Returns
    -------
    refractivity : ndarray, shape (nz, ny, nx) float64
        ``n - 1``; hull voxels of the wrong sign set to ambient (``params.sign``,
        :func:`sign_constraint`).
    info : PoissonInfo
    """
    hull = np.asarray(hull, dtype=bool)
    g = np.asarray(gradient)
    if g.shape != hull.shape + (3,) or hull.shape != tuple(grid.shape):
        raise ValueError(f"gradient {g.shape} / hull {hull.shape} do not match the grid {grid.shape}")
    out = np.full(grid.shape, float(r_ambient))
    n = int(hull.sum())
    if n == 0:
        return out, PoissonInfo(0, 0.0, params.solver, 0, 0.0, 0.0)
    t0 = time.perf_counter()
    # Pad by one voxel so that the grid boundary is an ordinary Dirichlet boundary
    # (u = 0 just outside the grid) for hulls that touch it.
    pad = ((1, 1), (1, 1), (1, 1))
    hull_p = np.pad(hull, pad)
    if params.box_boundary == "neumann":
        real = np.pad(np.ones(hull.shape, bool), pad)
        rim = ndi.binary_dilation(hull, structure=ndi.generate_binary_structure(3, 1)) & ~hull
        if not rim.any():
            log.warning("the hull fills the box: no Dirichlet cell left, using box_boundary='dirichlet'")
            real = None
    elif params.box_boundary == "dirichlet":
        real = None
    else:
        raise ValueError(f"box_boundary must be 'neumann' or 'dirichlet', not {params.box_boundary!r}")
    A, f = assemble(np.pad(g, pad + ((0, 0),)), hull_p, grid.voxel_size, params=params, real=real)
    t_asm = time.perf_counter() - t0
    u0 = None if x0 is None else np.asarray(x0, dtype=np.float64)[hull] - r_ambient
    u, it, rel, t_setup, t_solve = _solve(A, f, u0, params.solver, params.tol, params.max_iter,
                                          hull_p, grid.voxel_size, real)
    out[hull] += u
    out, applied, clipped = sign_constraint(out, hull, float(r_ambient), sign=params.sign,
                                            max_opposite=params.sign_max_opposite)
    info = PoissonInfo(iterations=it, residual=rel, solver=params.solver, n_unknowns=n,
                       setup_seconds=t_asm + t_setup, solve_seconds=t_solve, sign=applied, clipped=clipped)
    log.debug("integrate: %s", info)
    return out, info
