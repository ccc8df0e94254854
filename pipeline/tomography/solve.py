"""Per-frame gradient tomography: hull restriction, regularised fused CGLS (paper sec. 5).

Least squares ``S n_{x,y,z} = n_amb (d_out - d_in)_{x,y,z}`` (eq. 5) for the three
components at once, restricted to the basis functions whose support touches the visual
hull and to the rays that hit them. Plain LSQR/CGLS semi-converges on noisy deflections,
so the normal equations are regularised with a smoothness term on the basis set built
from first differences ``L`` (differences to the zero-valued basis functions outside the
set included, so the gradient fades to zero at the hull boundary):

    min ||S x - b||^2 + mu^2 x^T R x + mu_c^2 ||C x||^2,
    mu^2 = reg_weight * mean(diag(S^T S)),   mu_c^2 = curl_weight * mean(diag(S^T S)),

with ``R = L^T L`` (``prior: first-differences``, the paper's) or ``R = (L^T L)^2``
(``second-differences``, the default: a curvature penalty, see ``TomoParams.prior``) and
``C`` the discrete curl of the gradient field (:func:`curl_normal`; beyond the paper, which
solves the components independently: ``curl_weight: 0``). From optical flow the data term is
``||S G x - b||^2`` with ``G`` the flow's image averaging moved to the volume (a Gaussian
over the basis coefficients, :class:`VolumeBlur`; ``TomoParams.model_flow_window``, beyond
the paper, whose rows are the cell-centre rays) or ``||W S x - b||^2`` with ``W`` the same
averaging in image space (:class:`MeasurementBlur`, ``flow_window_space: image``),

solved by conjugate gradients on the Jacobi-scaled normal equations (the CGLS iteration;
one fused pass over ``S`` per iteration applies ``S^T S`` to the three components),
stopped when the normal residual has dropped by ``tol`` or, optionally, by the
discrepancy principle. Warm start from the previous frame's gradient (on the full grid).
The regularisation weight (0.1) and the stop were chosen on the accuracy table of
benchmarks/tomography.py (16 cameras, plume at t = 0): with 0.05 px deflection noise
plain CG semi-converges (48.5 dB after 10 iterations, 38.6 dB after 80) while the
regularised solve is stable (50.6 dB at its tolerance stop, 17 iterations); on
noise-free deflections it costs 1.0 dB (58.9 -> 57.8 dB).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time
from dataclasses import dataclass, field

import cv2
import numba as nb
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp

from schlieren.pipeline.tomography.geometry import TomoGeometry
from schlieren.pipeline.tomography._restriction_kernels import _move3, matvec3, row_dot3
from schlieren.pipeline.tomography.restriction import (
    RestrictedOperator,
    SubsetOperator,
    restrict_with_setup,
    shared_restriction,
)
from schlieren.pipeline.tomography.params import TomoParams
from schlieren.pipeline.tomography.rays import rhs_from_d_out, rhs_from_flows

__all__ = ["SolveInfo", "solve_gradient", "solve_gradient_d_out", "basis_set",
           "difference_operator", "difference_normal", "regulariser_normal", "regulariser", "SquaredLaplacian", "curl_normal", "CurlNormal", "cgls", "prepare_frame", "FrameSystem", "MeasurementBlur", "VolumeBlur", "volume_sigma", "finite_rhs",
           "valid_rays", "rhs_noise", "RegularisationChoice", "choose_reg_weight", "block_support",
           "RUN_SMALLEST_WEIGHT"]

log = logging.getLogger(__name__)

#: Smallest weight the run's regularisation stage searches (``choose_reg_weight``'s
#: ``smallest``; the function's own default, 1e-4, serves converged solves). The search
#: solves each weight to convergence, but a run's frames get at most ``tomography.max_iter``
#: (25) CG iterations, which stop before fitting what a smaller weight would let in: on the
#: realistic family's 16-camera rigs at the flow grid's factor 2 the data residual stays
#: above the discrepancy target down to 1e-4 (11 solves, 40 s of a 3-frame run instead of
#: 7 s), while the run's volumes are equal from 0.004 down (plume1 16 cameras 44.16 / 29.35
#: dB whole box / in plume at 0.0039, 44.16 / 29.36 at 1.2e-4; H.264 29.13 / 14.12 and
#: 29.11 / 14.09), and Table 1's rigs that ended below it gain (half ring 8 cameras, 0.00049
#: -> 0.0039: 45.53 -> 45.56 dB; full ring 15 cameras, 0.00195 -> 0.0039: 47.25 -> 47.27).
RUN_SMALLEST_WEIGHT = 2.0 ** -8


@dataclass(frozen=True)
class SolveInfo:
    """Receipt of one tomographic solve.

    Attributes
    ----------
    iterations : int
        Conjugate-gradient iterations run (CGLS-equivalent).
    residual : float
        Largest relative data residual ``||S x - b|| / ||b||`` over the components.
    residual_components : tuple of float
        The same per component (x, y, z).
    n_unknowns : int
        Basis functions per component.
    n_rays : int
        Rays (rows) used.
    nnz : int
        Non-zeros of the restricted matrix.
    stop_reason : str
        ``"tol"``, ``"discrepancy"``, ``"max_iter"`` or ``"empty"``.
    setup_seconds, solve_seconds : float
        Restriction / right-hand side time and iteration time.
    restriction : str
        ``"frame"`` (restricted for this frame), ``"shared-built"`` / ``"shared-kept"``
        (selected inside a shared restriction built by this call / kept from an earlier
        one, ``solve_gradient``'s ``support``) or ``"given"`` (``system``).
    """

    iterations: int
    residual: float
    residual_components: tuple = field(default=())
    n_unknowns: int = 0
    n_rays: int = 0
    nnz: int = 0
    stop_reason: str = ""
    setup_seconds: float = 0.0
    solve_seconds: float = 0.0
    restriction: str = ""


def basis_set(hull: np.ndarray, dilation: int) -> np.ndarray:
    """Basis functions kept for a hull: the hull dilated by ``dilation`` voxels (3x3x3)."""
    hull = np.asarray(hull, dtype=bool)
    if dilation <= 0:
        return hull.copy()
    return ndi.binary_dilation(hull, structure=np.ones((3, 3, 3), bool), iterations=dilation)


def difference_operator(inset: np.ndarray) -> sp.csr_matrix:
    """First differences along x, y, z between neighbours where at least one is in the set.

    Columns are the set's voxels in C order; neighbours outside the set count as zero.

    Parameters
    ----------
    inset : ndarray, shape (nz, ny, nx) bool

    Returns
    -------
    L : scipy.sparse.csr_matrix, shape (n_pairs, inset.sum())
        Dimensionless (differences of coefficients, not divided by the voxel size).
    """
    shape = inset.shape
    colmap = np.full(inset.size, -1, np.int64)
    flat = inset.ravel()
    colmap[flat] = np.arange(int(flat.sum()))
    rows_all, cols_all, vals_all = [], [], []
    nrow = 0
    for axis in range(3):
        sl_p = [slice(None)] * 3
        sl_q = [slice(None)] * 3
        sl_p[axis] = slice(0, shape[axis] - 1)
        sl_q[axis] = slice(1, shape[axis])
        idx = np.arange(inset.size).reshape(shape)
        p = idx[tuple(sl_p)].ravel()
        q = idx[tuple(sl_q)].ravel()
        keep = flat[p] | flat[q]
        p, q = p[keep], q[keep]
        r = nrow + np.arange(len(p))
        nrow += len(p)
        mq = flat[q]
        mp = flat[p]
        rows_all += [r[mq], r[mp]]
        cols_all += [colmap[q[mq]], colmap[p[mp]]]
        vals_all += [np.ones(int(mq.sum())), -np.ones(int(mp.sum()))]
    rows = np.concatenate(rows_all)
    cols = np.concatenate(cols_all)
    vals = np.concatenate(vals_all)
    return sp.csr_matrix((vals, (rows, cols)), shape=(nrow, int(flat.sum())))


@nb.njit(cache=True)
def _difference_normal_kernel(inset, indptr, indices, data):
    nz, ny, nx = inset.shape
    idx = np.full(inset.shape, -1, np.int64)
    n = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if inset[k, j, i]:
                    idx[k, j, i] = n
                    n += 1
    pos = 0
    row = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if not inset[k, j, i]:
                    continue
                # neighbours in increasing C order: -z, -y, -x, self, +x, +y, +z
                deg = (k > 0) + (k < nz - 1) + (j > 0) + (j < ny - 1) + (i > 0) + (i < nx - 1)
                for dk, dj, di in ((-1, 0, 0), (0, -1, 0), (0, 0, -1), (0, 0, 0), (0, 0, 1), (0, 1, 0),
                                   (1, 0, 0)):
                    kk, jj, ii = k + dk, j + dj, i + di
                    if dk == 0 and dj == 0 and di == 0:
                        indices[pos] = row
                        data[pos] = deg
                        pos += 1
                    elif 0 <= kk < nz and 0 <= jj < ny and 0 <= ii < nx and inset[kk, jj, ii]:
                        indices[pos] = idx[kk, jj, ii]
                        data[pos] = -1.0
                        pos += 1
                row += 1
                indptr[row] = pos
    return pos


def difference_normal(inset: np.ndarray) -> sp.csr_matrix:
    """``L^T L`` for ``L = difference_operator(inset)``, built directly.

    Every in-grid neighbour pair with at least one voxel in the set is a row of ``L``, so
    ``L^T L`` is the 7-point graph Laplacian of the set: the diagonal counts a voxel's
    in-grid neighbours, and neighbours that are both in the set are coupled by -1.
    """
    inset = np.ascontiguousarray(inset, dtype=np.bool_)
    n = int(inset.sum())
    indptr = np.zeros(n + 1, np.int64)
    indices = np.empty(7 * n, np.int32)
    data = np.empty(7 * n)
    nnz = _difference_normal_kernel(inset, indptr, indices, data)
    M = sp.csr_matrix((data[:nnz], indices[:nnz], indptr), shape=(n, n))
    M.has_sorted_indices = True
    return M


class SquaredLaplacian:
    """``(L^T L)^2`` kept as its factor ``M = L^T L`` (the set's 7-point Laplacian).

    Applied as two products with ``M`` (2 x 7 entries per row instead of the 25 of the
    formed square, and no sparse matrix product per frame: 30 ms at paper scale).
    ``M`` is symmetric, so ``diag(M^2)`` is the row sums of ``M``'s squared entries.
    """

    def __init__(self, M: sp.csr_matrix):
        self.M = M

    def diagonal(self) -> np.ndarray:
        # every row holds its diagonal entry, so no row is empty (reduceat needs that);
        # 1 ms instead of 21 for scipy's elementwise product at paper scale
        M = self.M
        if M.shape[0] == 0:
            return np.zeros(0)
        return np.add.reduceat(np.asarray(M.data, dtype=np.float64) ** 2, M.indptr[:-1])


def regulariser(inset: np.ndarray, prior: str = "second-differences") -> sp.csr_matrix | SquaredLaplacian:
    """The smoothness term's normal matrix as the solver applies it: :func:`difference_normal`
    for ``first-differences``, :class:`SquaredLaplacian` of it for ``second-differences``
    (equal to :func:`regulariser_normal`, never formed)."""
    if prior not in ("first-differences", "second-differences"):
        raise ValueError(f"prior must be 'first-differences' or 'second-differences', not {prior!r}")
    M = difference_normal(inset)
    return M if prior == "first-differences" else SquaredLaplacian(M)


def _apply_regulariser(R, X: np.ndarray) -> np.ndarray:
    """``R @ X`` for three columns (``R`` from :func:`regulariser`)."""
    if isinstance(R, SquaredLaplacian):
        return _apply_cols(R.M, _apply_cols(R.M, X))
    return _apply_cols(R, X)


def regulariser_normal(inset: np.ndarray, prior: str = "second-differences") -> sp.csr_matrix:
    """The normal matrix of the smoothness term (``TomoParams.prior``) on the set ``inset``,
    formed: :func:`regulariser` as an explicit matrix (for tests and inspection).

    ``first-differences``: :func:`difference_normal` (``L^T L``); ``second-differences``:
    its square ``(L^T L)^2``, the squared graph Laplacian (a 25-point stencil inside the set).
    """
    R = regulariser(inset, prior)
    if not isinstance(R, SquaredLaplacian):
        return R
    B = (R.M @ R.M).tocsr()
    B.sort_indices()
    return B


#: Gradient components (0 = x) of the three plaquette planes of :class:`CurlNormal`.
_PLANES = ((0, 1), (0, 2), (1, 2))


@nb.njit(cache=True)
def _plaquettes(colmap, n):
    """Corners of every 2x2 plaquette of the three coordinate planes with at least one
    corner in the set: ``(P, 4)`` unknown indices ``(p, p+e_a, p+e_c, p+e_a+e_c)`` (``n`` =
    outside the set, i.e. zero) and the plane (index into ``_PLANES``) of each."""
    nz, ny, nx = colmap.shape
    # a voxel is a corner of at most 4 plaquettes per plane: at most 12 n of them
    cap = 12 * n
    corners = np.empty((cap, 4), np.int32)
    planes = np.empty(cap, np.int8)
    k = 0
    for plane in range(3):
        ca, cc = _PLANES[plane]
        a, c = 2 - ca, 2 - cc  # grid axes (z, y, x order) of components ca, cc
        da = np.zeros(3, np.int64)
        dc = np.zeros(3, np.int64)
        da[a] = 1
        dc[c] = 1
        for z in range(nz - da[0] - dc[0]):
            for y in range(ny - da[1] - dc[1]):
                for x in range(nx - da[2] - dc[2]):
                    q0 = colmap[z, y, x]
                    qa = colmap[z + da[0], y + da[1], x + da[2]]
                    qc = colmap[z + dc[0], y + dc[1], x + dc[2]]
                    qac = colmap[z + da[0] + dc[0], y + da[1] + dc[1], x + da[2] + dc[2]]
                    if q0 < 0 and qa < 0 and qc < 0 and qac < 0:
                        continue
                    corners[k, 0] = q0 if q0 >= 0 else n
                    corners[k, 1] = qa if qa >= 0 else n
                    corners[k, 2] = qc if qc >= 0 else n
                    corners[k, 3] = qac if qac >= 0 else n
                    planes[k] = plane
                    k += 1
    return corners[:k].copy(), planes[:k].copy()


@nb.njit(cache=True, fastmath=True)
def _curl_apply(corners, planes, x, w, out):
    """``out += w C^T C x`` (``x``, ``out`` (n, 3); corner index ``n`` = outside, zero)."""
    n = x.shape[0]
    for k in range(corners.shape[0]):
        ca, cc = _PLANES[planes[k]]
        p0 = corners[k, 0]
        pa = corners[k, 1]
        pc = corners[k, 2]
        pac = corners[k, 3]
        # circulation: (g_c(pa) + g_c(pac) - g_c(p0) - g_c(pc)) - (g_a(pc) + g_a(pac) - g_a(p0) - g_a(pa))
        v = 0.0
        if p0 < n:
            v += x[p0, ca] - x[p0, cc]
        if pa < n:
            v += x[pa, cc] + x[pa, ca]
        if pc < n:
            v -= x[pc, cc] + x[pc, ca]
        if pac < n:
            v += x[pac, cc] - x[pac, ca]
        v *= w
        if p0 < n:
            out[p0, ca] += v
            out[p0, cc] -= v
        if pa < n:
            out[pa, cc] += v
            out[pa, ca] += v
        if pc < n:
            out[pc, cc] -= v
            out[pc, ca] -= v
        if pac < n:
            out[pac, cc] += v
            out[pac, ca] -= v


@nb.njit(cache=True)
def _curl_diagonal(corners, planes, n):
    d = np.zeros((n, 3))
    for k in range(corners.shape[0]):
        ca, cc = _PLANES[planes[k]]
        for q in range(4):
            j = corners[k, q]
            if j < n:
                d[j, ca] += 1.0
                d[j, cc] += 1.0
    return d


class CurlNormal:
    """``C^T C`` for the discrete curl ``C`` of a gradient field on a set of voxels,
    applied matrix-free (:func:`curl_normal`)."""

    def __init__(self, corners: np.ndarray, planes: np.ndarray, n: int):
        self.corners = corners
        self.planes = planes
        self.n = int(n)

    def diagonal3(self) -> np.ndarray:
        """``diag(C^T C)`` as (n, 3)."""
        return _curl_diagonal(self.corners, self.planes, self.n)

    def apply3(self, x: np.ndarray, weight: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
        """``out + weight C^T C x`` for x of shape (n, 3) (``out`` updated in place if given)."""
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(self.n, 3)
        out = np.zeros((self.n, 3)) if out is None else out
        _curl_apply(self.corners, self.planes, x, float(weight), out)
        return out

    def curl_matrix(self) -> sp.csr_matrix:
        """``C`` itself, shape (plaquettes, 3 n), columns ``3 i + c`` (for tests)."""
        rows, cols, vals = [], [], []
        r = np.arange(len(self.planes))
        comps = np.array(_PLANES)[self.planes.astype(np.int64)]
        ca, cc = comps[:, 0], comps[:, 1]
        p0, pa, pc, pac = self.corners.T.astype(np.int64)
        for q, comp, sign in ((pa, cc, 1.0), (pac, cc, 1.0), (p0, cc, -1.0), (pc, cc, -1.0),
                              (pc, ca, -1.0), (pac, ca, -1.0), (p0, ca, 1.0), (pa, ca, 1.0)):
            ok = q < self.n
            rows.append(r[ok])
            cols.append(3 * q[ok] + comp[ok])
            vals.append(np.full(int(ok.sum()), sign))
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(len(r), 3 * self.n))


def curl_normal(inset: np.ndarray) -> CurlNormal:
    """``C^T C`` for the discrete curl ``C`` of a gradient field on the set ``inset``.

    The unknowns are the solver's ``(n, 3)`` arrays (row ``i`` = the set's voxels in C order,
    column ``c`` = x, y, z). For each pair of components ``(a, c)`` and each 2x2 plaquette of
    voxels in their plane with at least one voxel in the set, ``C`` has one row, the
    circulation of ``g`` around the plaquette:

        (g_c(p+e_a) + g_c(p+e_a+e_c) - g_c(p) - g_c(p+e_c))
      - (g_a(p+e_c) + g_a(p+e_a+e_c) - g_a(p) - g_a(p+e_a)),

    i.e. ``2 h (d_a g_c - d_c g_a)`` averaged over the plaquette: zero for the gradient of
    any field that is quadratic across it (second-order accurate for smooth fields). Voxels
    outside the set count as zero, like the smoothness term's differences. ``C^T C`` is
    symmetric positive semi-definite and couples the three components; its null space is
    the curl-free fields, which the per-component null spaces of a few-view tomography
    mostly are not (see ``TomoParams.curl_weight``). Applied matrix-free (a plaquette list
    per frame: 2 ms instead of 0.22 s for the sparse product at paper scale).

    Parameters
    ----------
    inset : ndarray, shape (nz, ny, nx) bool

    Returns
    -------
    CurlNormal
    """
    inset = np.ascontiguousarray(inset, dtype=bool)
    n = int(inset.sum())
    colmap = np.full(inset.shape, -1, np.int32)
    colmap[inset] = np.arange(n, dtype=np.int32)
    corners, planes = _plaquettes(colmap, n)
    return CurlNormal(corners, planes, n)


def _apply_cols(M: sp.csr_matrix, X: np.ndarray) -> np.ndarray:
    """``M @ X`` for three columns in one pass over ``M``."""
    X = np.ascontiguousarray(X, dtype=np.float64)
    out = np.empty((M.shape[0], 3))
    matvec3(M.indptr, M.indices, M.data, X, out)
    return out


@dataclass
class CGLSResult:
    x: np.ndarray
    iterations: int
    stop_reason: str
    data_residual: np.ndarray  # ||S x - b|| per column
    rhs_norm: np.ndarray


def cgls(A, AT, b_parts: list[np.ndarray], x0: np.ndarray, *, max_iter: int, tol: float,
         n_data_parts: int = 1, stop_data_norm: np.ndarray | None = None, callback=None
         ) -> CGLSResult:
    """CGLS for ``min sum_k ||A_k x - b_k||^2`` on several independent columns at once.

    Parameters
    ----------
    A : callable
        ``A(x) -> list of arrays`` (the stacked operator applied to x of shape (n, k)).
    AT : callable
        ``AT(list of arrays) -> (n, k)``, the adjoint.
    b_parts : list of ndarray
        Right-hand side blocks, each shape (m_i, k).
    x0 : ndarray, shape (n, k)
        Initial guess.
    max_iter : int
    tol : float
        Stop when ``||A^T r|| <= tol * ||A^T b||`` for every column.
    n_data_parts : int
        The first ``n_data_parts`` blocks form the data term (for the residual report
        and the discrepancy stop).
    stop_data_norm : ndarray, shape (k,), optional
        Discrepancy principle: stop when the data residual of every column is below it.
    callback : callable, optional
        ``callback(iteration, x)`` after every iteration.

    Notes
    -----
    Each column has its own step lengths, so this is exactly ``k`` independent CGLS
    runs sharing the operator passes (PyLops-style step-wise loop).
    """
    x = np.array(x0, dtype=np.float64, copy=True)
    Ax = A(x)
    r = [b - a for b, a in zip(b_parts, Ax)]
    s = AT(r)
    p = s.copy()
    gamma = np.einsum("ij,ij->j", s, s)
    if np.any(x):
        # Warm start: measure convergence against ||A^T b|| (the cold-start reference),
        # not against the (already small) initial normal residual.
        sb = AT(b_parts)
        gamma0 = np.einsum("ij,ij->j", sb, sb)
    else:
        gamma0 = gamma.copy()
    rhs_norm = np.sqrt(sum(np.einsum("ij,ij->j", b, b) for b in b_parts[:n_data_parts]))

    def data_res():
        return np.sqrt(sum(np.einsum("ij,ij->j", ri, ri) for ri in r[:n_data_parts]))

    it = 0
    reason = "max_iter"
    active = (gamma > 0) & (np.sqrt(gamma) > tol * np.sqrt(gamma0))
    if not np.any(active):
        reason = "tol"
    while it < max_iter and np.any(active):
        if stop_data_norm is not None and np.all(data_res() <= stop_data_norm):
            reason = "discrepancy"
            break
        q = A(p)
        qq = sum(np.einsum("ij,ij->j", qi, qi) for qi in q)
        alpha = np.where(active & (qq > 0), gamma / np.where(qq > 0, qq, 1.0), 0.0)
        x += alpha * p
        for ri, qi in zip(r, q):
            ri -= alpha * qi
        s = AT(r)
        gamma_new = np.einsum("ij,ij->j", s, s)
        beta = np.where(active, gamma_new / np.where(gamma > 0, gamma, 1.0), 0.0)
        p = s + beta * p
        gamma = np.where(active, gamma_new, gamma)
        it += 1
        if callback is not None:
            callback(it, x)
        active = active & (np.sqrt(gamma) > tol * np.sqrt(gamma0))
        if not np.any(active):
            reason = "tol"
    return CGLSResult(x=x, iterations=it, stop_reason=reason, data_residual=data_res(),
                      rhs_norm=rhs_norm)


class MeasurementBlur:
    """The flow's image-space averaging, per camera, at flow-cell resolution: ``W``.

    A measured deflection is a weighted mean of the per-pixel deflections around the cell
    (the LK window, smoothing and block mean: :func:`schlieren.pipeline.flow.measurement_sigma`),
    while a row of ``S`` is the single ray through the cell centre. With ``W`` the data
    term becomes ``||W S x - b||^2``: ``W`` is a separable Gaussian over neighbouring cells
    of the same camera (``sigma`` in cells, taps out to ``ceil(2 sigma)``, at least one),
    zero-padded at the image border so that it is symmetric (``W^T = W``).

    Parameters
    ----------
    flow_shape : (C, h, w)
    sigmas : sequence of float
        Per camera, in flow cells; <= 0 leaves that camera's rays as they are.
    """

    def __init__(self, flow_shape, sigmas):
        self.flow_shape = tuple(int(v) for v in flow_shape)
        sig = np.asarray(sigmas, dtype=np.float64).reshape(-1)
        if len(sig) != self.flow_shape[0]:
            raise ValueError(f"one sigma per camera expected ({self.flow_shape[0]}), got {len(sig)}")
        self.sigmas = sig
        self.taps = []
        for v in sig:
            if v <= 0:
                self.taps.append(None)
                continue
            K = max(1, int(np.ceil(2.0 * v)))
            k = np.exp(-0.5 * (np.arange(-K, K + 1) / v) ** 2)
            self.taps.append((k / k.sum()).astype(np.float32))

    def apply(self, Y: np.ndarray) -> np.ndarray:
        """``W Y`` for ``Y`` of shape (C, h, w, k) (float32 result)."""
        import cv2

        Y = np.ascontiguousarray(Y, dtype=np.float32)
        out = np.empty_like(Y)
        for c, t in enumerate(self.taps):
            if t is None:
                out[c] = Y[c]
                continue
            for j in range(Y.shape[-1]):
                out[c, ..., j] = cv2.sepFilter2D(Y[c, ..., j], cv2.CV_32F, t, t, borderType=cv2.BORDER_CONSTANT)
        return out

    def restricted(self, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``(W Y)[rows]`` where ``Y`` is ``values`` (len(rows), k) on ``rows`` and zero
        elsewhere (float32)."""
        C, h, w = self.flow_shape
        k = values.shape[1]
        full = np.zeros((C * h * w, k), np.float32)
        full[rows] = values
        return self.apply(full.reshape(C, h, w, k)).reshape(-1, k)[rows]


def volume_sigma(cell_sigmas, cameras, grid, factor: int) -> float:
    """Width (voxels) of the volume Gaussian equivalent to the flow's per-camera image
    averaging: each camera's ``sigma`` (flow cells, :func:`~schlieren.pipeline.flow.measurement_sigma`
    over ``factor``) times ``factor`` pixels per cell times its pixel footprint at the box
    centre (metres per pixel), over the voxel size; the mean over the cameras with a
    width (0 if none has one).
    """
    from schlieren.pipeline.geometry import pixel_footprint

    sig = np.asarray(cell_sigmas, dtype=np.float64).reshape(-1)
    if len(sig) != len(cameras):
        raise ValueError(f"one width per camera expected ({len(cameras)}), got {len(sig)}")
    vals = [s * factor * pixel_footprint(cam, grid.center) / grid.voxel_size for s, cam in zip(sig, cameras) if s > 0]
    return float(np.mean(vals)) if vals else 0.0


class VolumeBlur:
    """``G``: a Gaussian over the basis coefficients (``sigma`` in voxels), restricted to the
    basis set (zero outside it on input and output, so ``G^T = G``).

    The flow's image-space averaging of a projection equals the projection of the volume
    averaged by a Gaussian of the same width at the volume (exact for parallel rays, the
    width scaled by depth for a pinhole), so ``W S x ~ S G x``: the data term keeps the
    single fused pass over ``S`` of the point-ray model (:meth:`RestrictedOperator.normal3`)
    and adds two cheap volume filters (taps out to ``ceil(2 sigma)``).
    """

    def __init__(self, inset: np.ndarray, sigma: float):
        self.sigma = float(sigma)
        if not self.sigma > 0:
            raise ValueError(f"VolumeBlur: sigma must be > 0 voxels, got {sigma}")
        K = max(1, int(np.ceil(2.0 * self.sigma)))
        k = np.exp(-0.5 * (np.arange(-K, K + 1) / self.sigma) ** 2)
        self.taps = (k / k.sum()).astype(np.float32)
        inset = np.asarray(inset, dtype=bool)
        nz = [np.flatnonzero(inset.any(axis=tuple(j for j in range(3) if j != i))) for i in range(3)]
        lo = [int(a[0]) if len(a) else 0 for a in nz]
        hi = [int(a[-1]) + 1 if len(a) else 0 for a in nz]
        self.box = tuple(slice(a, b) for a, b in zip(lo, hi))
        sub = inset[self.box]
        self.shape = sub.shape
        self.idx = np.flatnonzero(sub).astype(np.int64)
        # The set's box as one OpenCV image of nz * (ny + 2K) rows, nx columns and the 3
        # components as channels, K zero rows above and below each z-plane: one sepFilter2D
        # (zero borders) filters every plane along x and y without mixing planes, a second
        # one along z treats each plane as one row. 3.1x faster than the point-by-point numba
        # filter at paper scale (1.8 against 5.8 ms per product, 45 per late frame).
        nzb, nyb, nxb = self.shape
        self._K = (len(self.taps) - 1) // 2
        self._rows = nyb + 2 * self._K
        z, r = np.divmod(self.idx, max(nyb * nxb, 1))
        y, xx = np.divmod(r, max(nxb, 1))
        self._pidx = ((z * self._rows + y + self._K) * nxb + xx).astype(np.int64)
        self._a = np.zeros((nzb * self._rows, nxb, 3), np.float32)  # zero off the set, always

    _ONE = np.ones(1, np.float32)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``G x`` for ``x`` of shape (n, 3) (float64 result)."""
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(-1, 3)
        out = np.empty((len(self.idx), 3))
        if len(self.idx):
            _move3(x, self._a.reshape(-1, 3), self._pidx, True)
            xy = cv2.sepFilter2D(self._a, cv2.CV_32F, self.taps, self.taps, borderType=cv2.BORDER_CONSTANT)
            xyz = cv2.sepFilter2D(xy.reshape(self.shape[0], -1), cv2.CV_32F, self._ONE, self.taps,
                                  borderType=cv2.BORDER_CONSTANT)
            _move3(xyz.reshape(-1, 3), out, self._pidx, False)
        return out


@dataclass
class FrameSystem:
    """The per-frame restricted system (also used by the direct refractivity solve)."""

    op: RestrictedOperator
    inset: np.ndarray  # (nz, ny, nx) bool: kept basis functions
    LtL: sp.csr_matrix | SquaredLaplacian  # smoothness term's normal matrix on the set (regulariser)
    _colsumsq: np.ndarray | None = None  # diag(S^T S), shape (n,); computed on first use
    CtC: CurlNormal | None = None  # curl_normal(inset) when TomoParams.curl_weight > 0

    @property
    def n(self) -> int:
        return self.op.n

    @property
    def colsumsq(self) -> np.ndarray:
        """``diag(S^T S)``, shape (n,) (the gradient solve gets it from its fused setup pass)."""
        if self._colsumsq is None:
            self._colsumsq = self.op.column_sumsq()
        return self._colsumsq


def valid_rays(data: np.ndarray) -> np.ndarray | None:
    """Flat indices of the rays whose measurement (last axis) is finite, or None if all are.

    The flow stage returns NaN where the images cannot carry a deflection (dead,
    clipped or textureless regions): those rays are left out of the system rather than
    read as "no deflection".
    """
    data = np.asarray(data)
    # the channel sum is finite exactly when every channel is (NaN and inf propagate; the
    # values are deflections in pixels or O(1e-3) right-hand sides, far from overflow):
    # 4x faster than isfinite().all(axis=-1) over a trailing axis of 2 or 3
    total = data[..., 0].copy()
    for k in range(1, data.shape[-1]):
        total += data[..., k]
    ok = np.isfinite(total).ravel()
    return None if ok.all() else np.flatnonzero(ok)


def prepare_frame(geom: TomoGeometry, hull: np.ndarray, *, dilation: int,
                  rows: np.ndarray | None = None, prior: str = "second-differences",
                  curl: bool = False) -> FrameSystem:
    """Restrict the session's projection to a frame's hull (basis functions and rays;
    ``rows``: only these rays, e.g. :func:`valid_rays`; ``curl``: also build
    :func:`curl_normal` for ``TomoParams.curl_weight``)."""
    hull = np.asarray(hull, dtype=bool)
    if hull.shape != geom.grid.shape:
        raise ValueError(f"hull shape {hull.shape} does not match the grid {geom.grid.shape}")
    inset = basis_set(hull, dilation)
    flat = inset.ravel()
    colmap = np.full(flat.size, -1, np.int32)
    n = int(flat.sum())
    colmap[flat] = np.arange(n, dtype=np.int32)
    op = RestrictedOperator.from_full(geom.S, np.arange(geom.S.shape[0]) if rows is None else rows, colmap, n)
    return FrameSystem(op=op, inset=inset, LtL=regulariser(inset, prior),
                       CtC=curl_normal(inset) if curl else None)


def finite_rhs(b: np.ndarray) -> np.ndarray:
    """Zero (and report) non-finite right-hand sides that are left (invalid deflections are
    dropped before, :func:`valid_rays`; this only guards the arithmetic)."""
    bad = ~np.isfinite(b)
    if bad.any():
        log.warning("%d non-finite right-hand-side value(s) replaced by 0", int(bad.sum()))
        b = np.where(bad, 0.0, b)
    return b


def _scatter(inset: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.zeros(inset.shape + (values.shape[1],), np.float32)
    out[inset] = values
    return out


def solve_gradient(geom: TomoGeometry, rhs_or_flows: np.ndarray, hull: np.ndarray, *,
                   params: TomoParams = TomoParams(), x0: np.ndarray | None = None,
                   noise_rms: float | None = None, system: FrameSystem | None = None,
                   blur: MeasurementBlur | None = None,
                   volume_blur: float = 0.0, support: np.ndarray | None = None) -> tuple[np.ndarray, SolveInfo]:
    """Reconstruct the refractive-index gradient of one frame (paper sec. 5, eq. 5).

    Parameters
    ----------
    geom : TomoGeometry
        Per-session geometry (:func:`build_geometry`).
    rhs_or_flows : ndarray, shape (C, h, w, 2) or (C, h, w, 3)
        Either deflections ``delta`` (pixels; converted with :func:`approximate_d_out`) or
        the right-hand side ``n_amb * (d_out - d_in)`` (dimensionless, e.g. from exact
        exit directions via :func:`rhs_from_d_out`).
    hull : ndarray, shape (nz, ny, nx) bool
        Visual hull of the frame.
    params : TomoParams
    x0 : ndarray, shape (nz, ny, nx, 3), optional
        Warm start (previous frame's gradient, 1/m).
    noise_rms : float, optional
        RMS noise of one right-hand-side component, for the discrepancy stop.
    system : FrameSystem, optional
        A restriction already prepared for this hull (reuse across calls).
    blur : MeasurementBlur, optional
        Model the flow's image-space averaging (``W S x = b``; :class:`MeasurementBlur`);
        None: each measurement is the ray through its cell centre.
    volume_blur : float
        Or model it in the volume (``S G x = b``, :class:`VolumeBlur` of this sigma in
        voxels, :func:`volume_sigma`): the same fit at the cost of the point-ray model's
        single pass over ``S`` per iteration. 0: off.
    support : ndarray, shape (nz, ny, nx) bool, optional
        Basis functions shared by several frames, a superset of this frame's set (e.g.
        :func:`block_support` of a warm-start block): the projection is restricted to it
        once per thread and the frame's system selected inside it (:class:`SubsetOperator`;
        the same system, its products cost a pass over the shared restriction). Without a
        ``blur`` only; ignored with ``system``.

    Returns
    -------
    gradient : ndarray, shape (nz, ny, nx, 3) float32
        ``grad n`` in 1/m, component 0 = x; zero outside the basis set.
    info : SolveInfo
    """
    t0 = time.perf_counter()
    data = np.asarray(rhs_or_flows)
    if data.shape[:-1] != tuple(geom.flow_shape) or data.shape[-1] not in (2, 3):
        raise ValueError(f"expected shape {tuple(geom.flow_shape)} + (2,) or (3,), got {data.shape}")

    def rhs(rows):
        if data.shape[-1] == 2:
            b = rhs_from_flows(geom, data, n_ambient=params.n_ambient, rays=rows)
        else:
            b = np.asarray(data, dtype=np.float64).reshape(-1, 3)[rows]
        return finite_rhs(b)

    if blur is not None and volume_blur > 0:
        raise ValueError("solve_gradient: give either blur (image space) or volume_blur, not both")
    products = None
    G = None
    how = "given"
    if system is not None:
        sys_ = system
        if volume_blur > 0 and sys_.inset.any():
            G = VolumeBlur(sys_.inset, volume_blur)
    else:
        # Restriction fused with the solver's setup pass (diag(S^T S), S^T b, S^T S x0).
        hull = np.asarray(hull, dtype=bool)
        if hull.shape != geom.grid.shape:
            raise ValueError(f"hull shape {hull.shape} does not match the grid {geom.grid.shape}")
        inset = basis_set(hull, params.hull_dilation)
        flat = inset.ravel()
        n = int(flat.sum())
        colmap = np.full(flat.size, -1, np.int32)
        colmap[flat] = np.arange(n, dtype=np.int32)
        x_warm = _warm(x0, inset)
        G = VolumeBlur(inset, volume_blur) if volume_blur > 0 and inset.any() else None
        if G is not None and x_warm is not None:  # the unknowns are G's input: S^T S G x0
            x_warm = G.apply(x_warm)
        if support is not None and blur is None:
            op, b_k, products, how = _subset_system(geom, inset, support, valid_rays(data), rhs, x_warm)
        else:
            how = "frame"
            op, b_k, products = restrict_with_setup(geom.S, colmap, n, rhs, x_warm if blur is None else None,
                                                    reuse_buffers=True, rows=valid_rays(data))
        sys_ = FrameSystem(op=op, inset=inset, LtL=regulariser(inset, params.prior), _colsumsq=products[0],
                           CtC=curl_normal(inset) if params.curl_weight > 0 else None)
    op = sys_.op
    if op.n == 0 or op.m == 0:
        info = SolveInfo(iterations=0, residual=0.0, residual_components=(0.0, 0.0, 0.0),
                         stop_reason="empty", setup_seconds=time.perf_counter() - t0, restriction=how)
        return np.zeros(geom.grid.shape + (3,), np.float32), info
    b = b_k if products is not None else rhs(op.rows)
    if blur is not None:
        products = None  # S^T b and the warm start's product go through W (_solve_restricted)
    x, it, reason, res, t_solve = _solve_restricted(sys_, b, params, x0, noise_rms, products, blur=blur, volume=G)
    t1 = time.perf_counter()
    grad = _scatter(sys_.inset, x)
    info = SolveInfo(iterations=it, residual=float(np.max(res)), residual_components=tuple(map(float, res)),
                     n_unknowns=op.n, n_rays=op.m, nnz=op.nnz, stop_reason=reason,
                     setup_seconds=t1 - t0 - t_solve, solve_seconds=t_solve, restriction=how)
    log.debug("solve_gradient: %s", info)
    return grad, info


def block_support(hulls, dilation: int) -> np.ndarray:
    """The union of several frames' basis sets (:func:`basis_set`), e.g. a warm-start
    block's: the shared restriction of :func:`solve_gradient`'s ``support``."""
    out = None
    for h in hulls:
        s = basis_set(h, dilation)
        out = s if out is None else (out | s)
    if out is None:
        raise ValueError("block_support needs at least one hull")
    return out


def _subset_system(geom: TomoGeometry, inset: np.ndarray, support: np.ndarray, valid: np.ndarray | None,
                   rhs=None, x_warm: np.ndarray | None = None):
    """The frame's system (basis set ``inset``, rays ``valid``) inside the restriction of
    the projection to ``support`` (built once per thread and support), with its right-hand
    side ``rhs(rows)`` and setup products (:meth:`SubsetOperator.setup_products`, fused with
    the restriction when this call builds it).

    Returns
    -------
    op : SubsetOperator
    b : ndarray (op.m, 3) or None (without ``rhs``)
    products : tuple or None
    how : str
        ``"shared-built"`` or ``"shared-kept"`` (:attr:`SolveInfo.restriction`).
    """
    support = np.asarray(support, dtype=bool)
    if support.shape != inset.shape:
        raise ValueError(f"support shape {support.shape} does not match the grid {inset.shape}")
    if np.any(inset & ~support):
        raise ValueError("support must contain the frame's basis set (the dilated hull)")
    digest = hashlib.blake2b(np.packbits(support).tobytes(), digest_size=16).hexdigest()
    sel = np.flatnonzero(inset.ravel()[support.ravel()])
    flag = None
    if valid is not None:
        flag = np.zeros(geom.S.shape[0], bool)
        flag[valid] = True
    x_sup = None
    if x_warm is not None:
        x_sup = np.zeros((int(support.sum()), 3))
        x_sup[sel] = x_warm
    rhs_valid = rhs
    if rhs is not None and flag is not None:
        def rhs_valid(rows):  # the support's rays include invalid ones: never evaluated
            out = np.zeros((len(rows), 3))
            ok = flag[rows]
            out[ok] = rhs(rows[ok])
            return out
    base, fused = shared_restriction(geom.S, support, (geom.key, geom.S.shape, geom.S.nnz, digest),
                                     rhs=rhs_valid, x=x_sup, valid=flag)
    op = SubsetOperator(base, sel, None if flag is None else flag[base.rows])
    how = "shared-kept" if fused is None else "shared-built"
    if rhs is None:
        return op, None, None, how
    if fused is not None:  # products over the support's rows: keep the frame's rows and columns
        b_all, prods = fused
        return op, b_all[op._live_idx], tuple(p[sel] for p in prods), how
    b = rhs(op.rows)
    return op, b, op.setup_products(b, x_warm), how


def _warm(x0, inset):
    """Warm start restricted to the basis set (None for no or an all-zero warm start)."""
    if x0 is not None and np.any(x0):
        return np.asarray(x0, dtype=np.float64)[inset]
    return None


@nb.njit(cache=True)
def _cg_apply(P, d, indptr, indices, data, mu2, x, p, q):
    """``q = P (d + mu2 M x)`` (``M`` in CSR, ``P`` a row scaling); returns ``p . q`` per column."""
    pq = np.zeros(3)
    for i in range(q.shape[0]):
        r0 = d[i, 0]
        r1 = d[i, 1]
        r2 = d[i, 2]
        if mu2 > 0.0:
            a0, a1, a2 = row_dot3(indptr, indices, data, x, i)
            r0 += mu2 * a0
            r1 += mu2 * a1
            r2 += mu2 * a2
        q[i, 0] = P[i] * r0
        q[i, 1] = P[i] * r1
        q[i, 2] = P[i] * r2
        pq[0] += p[i, 0] * q[i, 0]
        pq[1] += p[i, 1] * q[i, 1]
        pq[2] += p[i, 2] * q[i, 2]
    return pq


@nb.njit(cache=True)
def _cg_update3(z, StSx, r, p, q, Sp, alpha):
    """``z += alpha p``, ``StSx += alpha Sp``, ``r -= alpha q`` per column; returns ``r . r``."""
    rr = np.zeros(3)
    for i in range(z.shape[0]):
        for c in range(3):
            a = alpha[c]
            z[i, c] += a * p[i, c]
            StSx[i, c] += a * Sp[i, c]
            v = r[i, c] - a * q[i, c]
            r[i, c] = v
            rr[c] += v * v
    return rr


@nb.njit(cache=True)
def _cg_direction3(p, r, beta, P, x):
    """``p = r + beta p`` per column and ``x = P p``."""
    for i in range(p.shape[0]):
        for c in range(3):
            v = r[i, c] + beta[c] * p[i, c]
            p[i, c] = v
            x[i, c] = P[i] * v


def _solve_restricted(sys_: FrameSystem, b: np.ndarray, params: TomoParams, x0, noise_rms, products=None,
                      blur: MeasurementBlur | None = None, volume: VolumeBlur | None = None,
                      state: dict | None = None):
    """Jacobi-scaled CG on the regularised normal equations, three columns at once.

    ``P (S^T S + mu^2 L^T L) P z = P S^T b``, ``x = P z``. Mathematically the CGLS
    iteration; the normal operator is applied by a fused kernel that reads each row of
    ``S`` once per iteration (half the memory traffic of a forward plus an adjoint
    product), and ``diag(S^T S)``, ``S^T b`` and the warm start's ``S^T S x0`` come from
    one more shared pass (:meth:`RestrictedOperator.setup_products`, or fused with the
    restriction: ``products``). The data residual ``||S x - b||`` is tracked from
    ``||b||^2 - 2 x^T S^T b + x^T S^T S x`` without extra passes.

    ``state`` (a dict; not with ``volume``) receives ``products`` for a next solve of the
    same system and data warm-started from this one's result ``x`` (also stored there, as
    float64 over the basis set): ``diag(S^T S)``, ``S^T b`` and ``S^T S x``, the last kept up
    to date by the iteration itself, so that solve needs no setup pass.
    """
    t = time.perf_counter()
    op = sys_.op
    if state is not None and volume is not None:
        raise ValueError("state is not kept for volume-blurred solves")
    x_warm = _warm(x0, sys_.inset)
    # One pass over S for diag(S^T S), S^T b and the warm start's S^T S x0 (or already
    # done while restricting: ``products``).
    if volume is not None:
        # data operator S G (VolumeBlur): G^T S^T S G as two volume filters around the fused
        # pass; products (from the restriction or computed here) are S^T b and S^T S G x0,
        # G^T applied below; the Jacobi scaling keeps diag(S^T S) (G averages neighbours)
        def normal(v):
            return volume.apply(op.normal3(volume.apply(v)))
        if products is None:
            products = op.setup_products(b, volume.apply(x_warm) if x_warm is not None else None)
        colsumsq = products[0]
        Stb = volume.apply(products[1])
        StSx0 = volume.apply(products[2]) if x_warm is not None else products[2]
    elif blur is None:
        normal = op.normal3
        colsumsq, Stb, StSx0 = products if products is not None else op.setup_products(b, x_warm)
    else:
        # data operator W S (MeasurementBlur): S^T W^T W S x as two passes over S and two
        # image-space filters; the Jacobi scaling and mu keep diag(S^T S) (W only averages
        # neighbouring rays of a camera, which cross a voxel alike)
        rows = op.rows

        def normal(v):  # float32 passes, as op.normal3
            Sv = op.matvec3_f32(v)
            return op.rmatvec3_f32(blur.restricted(rows, blur.restricted(rows, Sv)))

        if products is not None:  # S^T (W b) and S^T W^T W S x0 (``state`` of a previous solve)
            colsumsq, Stb, StSx0 = products
        else:
            colsumsq = sys_.colsumsq
            Stb = op.rmatvec3(blur.restricted(rows, b).astype(np.float64))
            StSx0 = normal(x_warm) if x_warm is not None else np.zeros((op.n, 3))
    if sys_._colsumsq is None:
        sys_._colsumsq = colsumsq
    mu2 = params.reg_weight * float(np.mean(colsumsq))
    LtL = sys_.LtL
    diag = colsumsq + mu2 * LtL.diagonal()
    # Curl coupling (TomoParams.curl_weight): one joint CG over the three components.
    muc2 = params.curl_weight * float(np.mean(colsumsq)) if params.curl_weight > 0 else 0.0
    CtC = None
    if muc2 > 0:
        CtC = sys_.CtC if sys_.CtC is not None else curl_normal(sys_.inset)
        sys_.CtC = CtC
        diag = diag + muc2 * CtC.diagonal3().mean(axis=1)

    def curl_term(v, out=None):
        return CtC.apply3(v, muc2, out)
    P = (1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)))[:, None]
    bb = np.einsum("ij,ij->j", b, b)

    P1 = np.ascontiguousarray(P[:, 0])

    rhs = P * Stb
    if x_warm is not None:
        z = x_warm / P
        StSx = StSx0
        Nz = P * (StSx0 + (mu2 * _apply_regulariser(LtL, x_warm) if mu2 > 0 else 0.0)
                  + (curl_term(x_warm) if CtC is not None else 0.0))
    else:
        z = np.zeros((op.n, 3))
        StSx, Nz = np.zeros((op.n, 3)), np.zeros((op.n, 3))
    r = rhs - Nz
    p = r.copy()
    rr = np.einsum("ij,ij->j", r, r)
    ref = np.sqrt(np.einsum("ij,ij->j", rhs, rhs))
    if CtC is not None:  # coupled: one CG, its residual and reference over all components
        rr = np.full(3, rr.sum())
        ref = np.full(3, np.sqrt(np.sum(ref ** 2)))

    def data_res():
        x = P * z
        val = bb - 2 * np.einsum("ij,ij->j", x, Stb) + np.einsum("ij,ij->j", x, StSx)
        return np.sqrt(np.maximum(val, 0.0))

    stop = None
    if params.discrepancy > 0 and noise_rms is not None:
        stop = params.discrepancy * noise_rms * np.sqrt(op.m)
    active = np.sqrt(rr) > params.tol * ref
    it = 0
    reason = "tol" if not np.any(active) else "max_iter"
    # The vector work of an iteration runs in three fused serial kernels (x = P p with the
    # new direction; q = P (S^T S x + mu^2 L^T L x) with p.q; the updates with r.r).
    x = P * p
    q = np.empty_like(p)
    # (L^T L)^2 x as M (M x): the inner product into ``Mx``, the outer one fused below
    squared = isinstance(LtL, SquaredLaplacian) and mu2 > 0
    Mr = LtL.M if isinstance(LtL, SquaredLaplacian) else LtL
    Mx = np.empty_like(p) if squared else x
    while it < params.max_iter and np.any(active):
        if stop is not None and np.all(data_res() <= stop):
            reason = "discrepancy"
            break
        Sp = normal(x)
        d = curl_term(x, Sp.copy()) if CtC is not None else Sp
        if squared:
            matvec3(Mr.indptr, Mr.indices, Mr.data, x, Mx)
        pq = _cg_apply(P1, d, Mr.indptr, Mr.indices, Mr.data, float(mu2), Mx if squared else x, p, q)
        if CtC is not None:
            pq = np.full(3, pq.sum())
        alpha = np.where(active & (pq > 0), rr / np.where(pq > 0, pq, 1.0), 0.0)
        rr_new = _cg_update3(z, StSx, r, p, q, Sp, alpha)
        if CtC is not None:
            rr_new = np.full(3, rr_new.sum())
        beta = np.where(active, rr_new / np.where(rr > 0, rr, 1.0), 0.0)
        rr = np.where(active, rr_new, rr)
        it += 1
        active = active & (np.sqrt(rr) > params.tol * ref)
        if not np.any(active):
            reason = "tol"
        else:
            _cg_direction3(p, r, beta, P1, x)
    x = P * z
    rel = data_res() / np.sqrt(np.where(bb > 0, bb, 1.0))
    if state is not None:
        state.update(products=(colsumsq, Stb, StSx), x=x)
    return x, it, reason, rel, time.perf_counter() - t


def solve_gradient_d_out(geom: TomoGeometry, d_out: np.ndarray, hull: np.ndarray, *,
                         params: TomoParams = TomoParams(), x0: np.ndarray | None = None,
                         noise_rms: float | None = None) -> tuple[np.ndarray, SolveInfo]:
    """:func:`solve_gradient` from exit directions (exact ones from a ray tracer).

    Parameters
    ----------
    d_out : ndarray, shape (C, h, w, 3)
        Unit exit directions (world).
    """
    rhs = rhs_from_d_out(geom, d_out, n_ambient=params.n_ambient)
    return solve_gradient(geom, rhs, hull, params=params, x0=x0, noise_rms=noise_rms)


def rhs_noise(rhs: np.ndarray, quiet: np.ndarray) -> np.ndarray:
    """Robust RMS noise of each right-hand-side component over rays that see no flow.

    Parameters
    ----------
    rhs : ndarray, shape (C, h, w, 3)
        ``n_amb (d_out - d_in)`` of every ray (e.g. :func:`rhs_from_flows`).
    quiet : ndarray, shape (C, h, w) bool
        Rays whose true right-hand side is zero: outside every flow mask (their
        measurement is pure noise: sensor noise, compression, optical-flow error).

    Returns
    -------
    sigma : ndarray, shape (3,)
        ``1.4826 * MAD`` per world component (x, y, z); NaN where no quiet ray is finite.
    """
    b = np.asarray(rhs, dtype=np.float64).reshape(-1, 3)[np.asarray(quiet, bool).ravel()]
    b = b[np.isfinite(b).all(axis=1)]
    if b.shape[0] < 10:
        return np.full(3, np.nan)
    return 1.4826 * np.median(np.abs(b - np.median(b, axis=0)), axis=0)


def rhs_snr(rhs: np.ndarray, seen: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Signal-to-noise ratio of the rays that see the flow, per world component.

    ``sqrt(max(mean(b^2) - sigma^2, 0)) / sigma`` over the finite rays of ``seen`` (e.g.
    inside a flow mask), ``sigma`` from :func:`rhs_noise`: the RMS of the signal the rays
    carry, its noise removed, in units of the noise. A receipt (the regularisation stage
    logs and records it): on the realistic family the 16-camera PNG cases have 7.7-10
    (x, y), the 8-camera ones 15-20, the H.264 ones 2-4 (``TomoParams.flow_window_scale``).

    Returns
    -------
    snr : ndarray, shape (3,)
        NaN where no seen ray is finite or the noise is not positive.
    """
    b = np.asarray(rhs, dtype=np.float64).reshape(-1, 3)[np.asarray(seen, bool).ravel()]
    b = b[np.isfinite(b).all(axis=1)]
    sigma = np.asarray(noise, dtype=np.float64).reshape(3)
    if b.shape[0] == 0:
        return np.full(3, np.nan)
    power = np.maximum(np.mean(b * b, axis=0) - sigma * sigma, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sigma > 0, np.sqrt(power) / sigma, np.nan)


@dataclass(frozen=True)
class RegularisationChoice:
    """Receipt of :func:`choose_reg_weight`.

    Attributes
    ----------
    reg_weight : float
        The chosen weight (the same units as :attr:`TomoParams.reg_weight`).
    target : float
        Discrepancy target ``tau^2 m sum_c sigma_c^2`` of the summed squared data residual.
    path : tuple of (float, float)
        ``(reg_weight, sum_c ||S x - b_c||^2 / target)`` of every weight tried, largest first.
    """

    reg_weight: float
    target: float
    path: tuple


def choose_reg_weight(geom: TomoGeometry, rhs_or_flows: np.ndarray, hull: np.ndarray, noise: np.ndarray, *,
                      params: TomoParams = TomoParams(), tau: float | None = None, largest: float = 4.0,
                      smallest: float = 1e-4, factor: float = 2.0, plateau: float = 0.02,
                      start: float = 0.125, blur: MeasurementBlur | None = None) -> RegularisationChoice:
    """Choose the regularisation weight of one frame by Morozov's discrepancy principle.

    The weights tried lie on the grid ``largest, largest / factor, ...`` down to
    ``smallest``; the result is the largest weight whose data residual has fallen to the
    noise: ``sum_c ||S x_c - b_c||^2 <= tau^2 m sum_c sigma_c^2`` (``m`` rays, ``sigma_c``
    the noise of component ``c``, e.g. from :func:`rhs_noise`), interpolated geometrically
    between the two grid weights around the crossing. Less regularisation would fit the
    noise; more would leave signal in the residual. The residual grows with the weight, so
    the search brackets the crossing from the grid weight nearest ``start``: upwards while
    the residual is below the target, downwards while it is above (each solve warm-started
    from the last, converged to ``tol`` = 1e-3, and started from the last one's ``S^T S x``
    without a setup pass). Where the residual crosses the target, that is the bracket a
    search down from ``largest`` finds, in fewer solves: the weights chosen on the realistic
    family lie between 0.025 and 0.24, and a cold solve at a large weight is the slowest
    (37 iterations at 4 on the paper-scale session benchmark).

    If, going down, the residual levels off above the target (model error dominates, or the
    noise outside the masks understates the misfit inside), so that dividing the weight by
    ``factor`` lowers it by less than ``plateau`` (2 %), the search stops and returns the
    larger weight of that step (only steps below ``start`` are looked at; a residual that
    levels off above it is as level below): less regularisation no longer buys a better fit (on the
    paper-scale session benchmark, whose noise-free renders leave the target 68x below the
    reachable misfit, that ends the search at 0.0156 instead of the smallest weight; its
    volumes are 51.50 / 51.37 dB at those weights). ``smallest`` bounds the search.

    Parameters
    ----------
    geom, rhs_or_flows, hull :
        As for :func:`solve_gradient`.
    noise : ndarray, shape (3,)
        RMS noise of each right-hand-side component (dimensionless).
    params : TomoParams
        All but ``reg_weight`` / ``tol`` / ``max_iter`` are used.
    tau : float, optional
        Safety factor of the discrepancy principle (1 = the noise level exactly);
        default ``params.reg_tau``.
    largest, smallest, factor : float
        The grid of weights: ``largest``, ``largest / factor``, ... down to ``smallest``.
    plateau : float
        Stop when a step down lowers the residual by less than this fraction (see above); 0 never.
    start : float
        Where the search starts (snapped to the grid); only its cost depends on it.
    blur : MeasurementBlur, optional
        The data operator's image averaging, as for :func:`solve_gradient`.
        (The weight is chosen with the image-space model also for volume solves: the
        volume model's misfit levels off above the discrepancy target.)

    Returns
    -------
    RegularisationChoice
    """
    tau = float(params.reg_tau if tau is None else tau)
    # The smoothness weight is chosen without the curl term: with it, the discrepancy
    # principle trades smoothness for integrability (on the realistic family's tune cases
    # the weight fell 12-35x, -0.4 dB on 16 cameras); the curl term is then added on top.
    params = dataclasses.replace(params, curl_weight=0.0)
    noise = np.asarray(noise, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(noise)) or not noise.any():
        raise ValueError(f"the noise estimate must be finite and positive, got {noise}")
    if not (largest > 0 and factor > 1 and 0 < smallest <= largest and start > 0):
        raise ValueError(f"need largest >= smallest > 0, factor > 1 and start > 0, got largest {largest}, "
                         f"smallest {smallest}, factor {factor}, start {start}")
    data = np.asarray(rhs_or_flows)
    rows = valid_rays(data)
    sys_ = prepare_frame(geom, hull, dilation=params.hull_dilation, rows=rows, prior=params.prior)
    op = sys_.op
    if op.n == 0 or op.m == 0:
        return RegularisationChoice(reg_weight=float(params.reg_weight), target=0.0, path=())
    if data.shape[-1] == 2:
        b = rhs_from_flows(geom, data, n_ambient=params.n_ambient, rays=op.rows)
    else:
        b = np.asarray(data, dtype=np.float64).reshape(-1, 3)[op.rows]
    b = finite_rhs(b)
    bb = float(np.einsum("ij,ij->", b, b))
    target = tau ** 2 * op.m * float(np.sum(noise ** 2))
    last = int(np.floor(np.log(largest / smallest) / np.log(factor) + 1e-9))  # grid index of the smallest

    def weight(j):
        return float(largest / factor ** j)

    ratios: dict[int, float] = {}
    carry: dict = {}

    def ratio_at(j):
        p = dataclasses.replace(params, reg_weight=weight(j), max_iter=200, tol=1e-3, discrepancy=0.0)
        x0 = None
        if carry:  # the previous solve's result, exactly (float64), and its S^T S x: no setup pass
            x0 = np.zeros(sys_.inset.shape + (3,))
            x0[sys_.inset] = carry["x"]
        _x, _it, _reason, rel, _t = _solve_restricted(sys_, b, p, x0, None, products=carry.get("products"),
                                                      blur=blur, state=carry)
        res2 = float(np.sum((rel * np.sqrt(np.maximum(np.einsum("ij,ij->j", b, b), 1e-300))) ** 2)) if bb > 0 else 0.0
        ratios[j] = res2 / target if target > 0 else 0.0
        return ratios[j]

    def result(mu):
        path = tuple((weight(j), ratios[j]) for j in sorted(ratios))
        return RegularisationChoice(reg_weight=float(mu), target=target, path=path)

    def crossing(j):  # grid weight j - 1 above the target, j at or below it
        r0, r1 = ratios[j - 1], ratios[j]
        t = np.log(r0) / (np.log(r0) - np.log(r1)) if r0 > 0 and r1 > 0 and r0 != r1 else 1.0
        mu0, mu1 = weight(j - 1), weight(j)
        return float(np.exp(np.log(mu0) + np.clip(t, 0.0, 1.0) * (np.log(mu1) - np.log(mu0))))

    j = int(np.clip(np.round(np.log(largest / start) / np.log(factor)), 0, last))
    if ratio_at(j) <= 1.0:  # upwards to the first weight above the target
        while j > 0:
            if ratio_at(j - 1) > 1.0:
                return result(crossing(j))
            j -= 1
        return result(weight(0))
    while j < last:  # downwards to the first weight at or below the target
        if ratio_at(j + 1) <= 1.0:
            return result(crossing(j + 1))
        j += 1
        if ratios[j] > (1.0 - plateau) * ratios[j - 1]:
            log.info("regularisation: the data residual levels off %.3gx above the discrepancy target "
                     "(%.3g -> %.3g from weight %.3g to %.3g); taking %.3g", ratios[j], ratios[j - 1],
                     ratios[j], weight(j - 1), weight(j), weight(j - 1))
            return result(weight(j - 1))
    return result(weight(j))
