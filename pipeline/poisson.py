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

__all__ = ["PoissonParams", "PoissonInfo", "integrate", "diffusion_tensor", "assemble",
           "SOLVERS", "LaplaceMultigrid", "laplacian_matrix", "pcg"]

log = logging.getLogger(__name__)

SOLVERS = ("mg", "amg", "jacobi_cg")


@dataclass(frozen=True)
class PoissonParams:
    """Parameters of :func:`integrate`.

    Attributes
    ----------
    alpha : float
        Data fidelity of the diffusion tensor (Appendix); 1 = plain Poisson.
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
    """

    alpha: float = 0.8
    sigma: float = 0.5
    k: float = 0.5e-5
    value_scale: float = 255.0
    box_boundary: str = "neumann"
    solver: str = "mg"
    tol: float = 1e-6
    max_iter: int = 5000


@dataclass(frozen=True)
class PoissonInfo:
    """Receipt of one integration."""

    iterations: int
    residual: float
    solver: str
    n_unknowns: int
    setup_seconds: float
    solve_seconds: float


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
    J = np.empty((n, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            comp = ndi.gaussian_filter(gh[..., a] * gh[..., b], sigma, mode="constant")[where]
            J[:, a, b] = comp
            J[:, b, a] = comp
    # J is positive semi-definite (Gaussian-weighted sum of g g^T), so every eigenvalue gap
    # is at most trace(J). Where even that bound makes both exponentials underflow to
    # exactly 0 (exp(-x) == 0.0 for x > 745.2) all eigenvalues are alpha and D = alpha I
    # exactly: skip the eigendecomposition there (almost everywhere with the default units).
    tr = J[:, 0, 0] + J[:, 1, 1] + J[:, 2, 2]
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        inert = (tr <= 0) | (M / (k * (1.01 * tr) ** 2) > 800.0)
    D = np.zeros((n, 3, 3))
    D[inert] = alpha * np.eye(3)
    act = ~inert
    if act.any():
        lam, V = np.linalg.eigh(J[act])  # ascending: lam[:, 2] = lambda0
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            d01 = (lam[:, 2] - lam[:, 1]) ** 2
            d02 = (lam[:, 2] - lam[:, 0]) ** 2
            e1 = np.where(d01 > 0, np.exp(-M / (k * d01)), 0.0)
            e2 = np.where(d02 > 0, np.exp(-M / (k * d02)), 0.0)
        lt = np.empty((len(lam), 3))
        lt[:, 2] = alpha
        lt[:, 1] = alpha + (1 - alpha) * e1
        lt[:, 0] = alpha + (1 - alpha) * e2
        D[act] = np.einsum("nij,nj,nkj->nik", V, lt, V)
    return D


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
# preconditions both. Matrix-free numba kernels and no setup beyond coarsening the mask,
# so it is rebuilt for every frame's hull at negligible cost (pyamg's setup alone costs
# more than the whole solve at these sizes). Cell-centred hierarchy on the bounding box
# of the hull: a coarse cell is active if at least ``min_children`` of its 2x2x2 children
# are; prolongation is cell-centred trilinear and restriction its transpose / 8; coarse
# operators are rediscretised (spacing doubles); red-black Gauss-Seidel before and
# black-red after the coarse correction keeps the V-cycle symmetric (required inside
# CG); the coarsest level is solved by sparse LU.


@nb.njit(parallel=True, cache=True)
def _rbgs(u, f, mask, dg, h2, colour_first):
    """One symmetric-half red-black Gauss-Seidel sweep (colour ``colour_first`` then the other).

    ``dg`` is the diagonal of ``h^2 A`` per cell: 6, less one per neighbour across a
    natural (Neumann) face. Neighbours outside ``mask`` hold zero.
    """
    nz, ny, nx = u.shape
    for c in range(2):
        colour = (colour_first + c) % 2
        for k in nb.prange(nz):
            for j in range(ny):
                i0 = (colour + k + j) % 2
                for i in range(i0, nx, 2):
                    if not mask[k, j, i]:
                        continue
                    s = f[k, j, i] * h2
                    if i > 0:
                        s += u[k, j, i - 1]
                    if i < nx - 1:
                        s += u[k, j, i + 1]
                    if j > 0:
                        s += u[k, j - 1, i]
                    if j < ny - 1:
                        s += u[k, j + 1, i]
                    if k > 0:
                        s += u[k - 1, j, i]
                    if k < nz - 1:
                        s += u[k + 1, j, i]
                    u[k, j, i] = s / dg[k, j, i]


@nb.njit(parallel=True, cache=True)
def _residual(u, f, mask, dg, inv_h2, out):
    nz, ny, nx = u.shape
    for k in nb.prange(nz):
        for j in range(ny):
            for i in range(nx):
                if not mask[k, j, i]:
                    out[k, j, i] = 0.0
                    continue
                s = dg[k, j, i] * u[k, j, i]
                if i > 0:
                    s -= u[k, j, i - 1]
                if i < nx - 1:
                    s -= u[k, j, i + 1]
                if j > 0:
                    s -= u[k, j - 1, i]
                if j < ny - 1:
                    s -= u[k, j + 1, i]
                if k > 0:
                    s -= u[k - 1, j, i]
                if k < nz - 1:
                    s -= u[k + 1, j, i]
                out[k, j, i] = f[k, j, i] - s * inv_h2


@nb.njit(parallel=True, cache=True)
def _restrict(r, mask_c, out):
    """Full weighting: transpose of :func:`_prolong_add` divided by 8.

    Separable: the 1-D weights (1/4, 3/4, 3/4, 1/4) on fine cells ``2K-1 .. 2K+2`` are
    applied along x, then y, then z (fine cells outside the array count as zero).
    """
    cz, cy, cx = out.shape
    fz, fy, fx = r.shape
    tx = np.empty((fz, fy, cx))
    for k in nb.prange(fz):
        for j in range(fy):
            for I in range(cx):
                s = 0.0
                for c in range(4):
                    i = 2 * I - 1 + c
                    if 0 <= i < fx:
                        s += (0.25 if c == 0 or c == 3 else 0.75) * r[k, j, i]
                tx[k, j, I] = s
    ty = np.empty((fz, cy, cx))
    for k in nb.prange(fz):
        for J in range(cy):
            for I in range(cx):
                s = 0.0
                for b in range(4):
                    j = 2 * J - 1 + b
                    if 0 <= j < fy:
                        s += (0.25 if b == 0 or b == 3 else 0.75) * tx[k, j, I]
                ty[k, J, I] = s
    for K in nb.prange(cz):
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


@nb.njit(parallel=True, cache=True)
def _prolong_add(uc, mask_f, uf):
    """Add the trilinear (cell-centred) interpolation of ``uc`` to the active fine cells.

    Fine cell ``k`` takes 3/4 of coarse cell ``k // 2`` and 1/4 of its other neighbour
    (``k // 2 - 1`` for even ``k``, ``k // 2 + 1`` for odd; zero outside the array),
    separably along x, y and z.
    """
    fz, fy, fx = uf.shape
    cz, cy, cx = uc.shape
    ex = np.empty((cz, cy, fx))
    for K in nb.prange(cz):
        for J in range(cy):
            for i in range(fx):
                I = i // 2
                In = I - 1 if i % 2 == 0 else I + 1
                s = 0.75 * uc[K, J, I] if I < cx else 0.0
                if 0 <= In < cx:
                    s += 0.25 * uc[K, J, In]
                ex[K, J, i] = s
    ey = np.empty((cz, fy, fx))
    for K in nb.prange(cz):
        for j in range(fy):
            J = j // 2
            Jn = J - 1 if j % 2 == 0 else J + 1
            for i in range(fx):
                s = 0.75 * ex[K, J, i] if J < cy else 0.0
                if 0 <= Jn < cy:
                    s += 0.25 * ex[K, Jn, i]
                ey[K, j, i] = s
    for k in nb.prange(fz):
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


# Serial twins of the smoothing/transfer kernels for small (coarse) levels, where the
# cost of waking the thread pool exceeds the work.
_rbgs_serial = nb.njit(cache=True)(_rbgs.py_func)
_residual_serial = nb.njit(cache=True)(_residual.py_func)
_restrict_serial = nb.njit(cache=True)(_restrict.py_func)
_prolong_add_serial = nb.njit(cache=True)(_prolong_add.py_func)
_PARALLEL_MIN_CELLS = 200_000


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
        misses the smooth modes there (22-24 instead of 15 CG iterations on the plume).

    Notes
    -----
    Works on the bounding box of the mask (plus one cell), so the cost scales with the
    hull, not with the grid. The coarse operators are rediscretised, not Galerkin, so
    as a stationary iteration the V-cycle stalls on smooth modes near the irregular hull
    boundary; as a CG preconditioner (symmetric positive definite) it needs 15-19
    iterations for a 1e-8 residual on a 134k-voxel plume hull with Dirichlet faces
    (about 24 with natural faces at the floor and top), against 220-240 for
    Jacobi-PCG; one V-cycle costs about five sparse products with the assembled
    operator, so the wall-time gain is 2-4x (benchmarks/poisson.py). Transfers are
    separable (x, then y, then z). Vectors passed to :meth:`apply` are ordered like
    ``mask[mask]`` (C order).
    """

    def __init__(self, mask: np.ndarray, h: float, *, smooth: int = 1, coarse_size: int = 1500,
                 min_children: int = 1, real: np.ndarray | None = None):
        mask = np.asarray(mask, dtype=np.bool_)
        nzidx = np.nonzero(mask)
        if len(nzidx[0]) == 0:
            raise ValueError("empty mask")
        lo = [max(int(a.min()) - 1, 0) for a in nzidx]
        hi = [min(int(a.max()) + 2, s) for a, s in zip(nzidx, mask.shape)]
        box = (slice(lo[0], hi[0]), slice(lo[1], hi[1]), slice(lo[2], hi[2]))
        crop = np.ascontiguousarray(mask[box])
        real_l = None if real is None else np.ascontiguousarray(np.asarray(real, dtype=bool)[box])
        self._flat = np.flatnonzero(crop)
        self.masks = [crop]
        self.reals = [real_l]
        self.hs = [float(h)]
        while self.masks[-1].sum() > coarse_size and min(self.masks[-1].shape) > 2:
            m = self.masks[-1]
            pad = [(0, s % 2) for s in m.shape]
            mp = np.pad(m, pad)
            nz, ny, nx = (s // 2 for s in mp.shape)
            mc = mp.reshape(nz, 2, ny, 2, nx, 2).sum(axis=(1, 3, 5)) >= min_children
            self.masks.append(np.ascontiguousarray(mc))
            if real_l is not None:
                # A coarse cell exists if any child does (the natural face moves outwards by
                # at most half a fine cell: the coarse operator stays SPD and close).
                rp = np.pad(real_l, pad, constant_values=True)
                real_l = np.ascontiguousarray(rp.reshape(nz, 2, ny, 2, nx, 2).any(axis=(1, 3, 5)) | mc)
                self.reals.append(real_l)
            else:
                self.reals.append(None)
            self.hs.append(2 * self.hs[-1])
        self.dgs = [_diag_counts(r, m.shape) for r, m in zip(self.reals, self.masks)]
        self.smooth = int(smooth)
        self._coarse = spla.splu(laplacian_matrix(self.masks[-1], self.hs[-1], self.reals[-1]).tocsc())
        self._res = [np.zeros(m.shape) for m in self.masks]
        self.n = int(len(self._flat))

    @property
    def levels(self) -> int:
        return len(self.masks)

    def _vcycle(self, level: int, f: np.ndarray) -> np.ndarray:
        mask = self.masks[level]
        if level == len(self.masks) - 1:
            u = np.zeros(mask.shape)
            u[mask] = self._coarse.solve(f[mask])
            return u
        h2 = self.hs[level] ** 2
        par = mask.size >= _PARALLEL_MIN_CELLS
        rbgs = _rbgs if par else _rbgs_serial
        u = np.zeros(mask.shape)
        res = self._res[level]
        dg = self.dgs[level]
        for _ in range(self.smooth):
            rbgs(u, f, mask, dg, h2, 0)
        (_residual if par else _residual_serial)(u, f, mask, dg, 1.0 / h2, res)
        fc = np.empty(self.masks[level + 1].shape)
        (_restrict if par else _restrict_serial)(res, self.masks[level + 1], fc)
        uc = self._vcycle(level + 1, fc)
        (_prolong_add if par else _prolong_add_serial)(uc, mask, u)
        for _ in range(self.smooth):
            rbgs(u, f, mask, dg, h2, 1)
        return u

    def apply(self, r: np.ndarray) -> np.ndarray:
        """One V-cycle from zero for the right-hand side ``r`` (vector over active cells)."""
        f = np.zeros(self.masks[0].shape)
        f.ravel()[self._flat] = r
        return self._vcycle(0, f).ravel()[self._flat]

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
        ``n - 1``.
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
    info = PoissonInfo(iterations=it, residual=rel, solver=params.solver, n_unknowns=n,
                       setup_seconds=t_asm + t_setup, solve_seconds=t_solve)
    log.debug("integrate: %s", info)
    return out, info
