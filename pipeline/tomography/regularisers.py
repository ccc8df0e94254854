"""The smoothness and integrability terms of the per-frame gradient solve (beyond the paper).

Both act on the basis set's coefficients (:func:`~schlieren.pipeline.tomography.solve.basis_set`),
voxels outside the set counting as zero, so the gradient fades to zero at the hull boundary:
first differences ``L`` (:func:`difference_operator`) and their normal matrix ``L^T L``, the
set's 7-point graph Laplacian (:func:`difference_normal`), applied squared for the default
curvature prior (:class:`SquaredLaplacian`, ``TomoParams.prior``); and the discrete curl ``C``
of the gradient field, whose ``C^T C`` couples the three components (:func:`curl_normal`,
``TomoParams.curl_weight``). The numba kernels are in
:mod:`~schlieren.pipeline.tomography._regulariser_kernels`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from schlieren.pipeline.tomography._regulariser_kernels import (
    _PLANES,
    _curl_apply,
    _curl_diagonal,
    _difference_normal_kernel,
    _plaquettes,
)
from schlieren.pipeline.tomography._restriction_kernels import matvec3
from schlieren.pipeline.tomography.params import TomoParams

__all__ = ["difference_operator", "difference_normal", "SquaredLaplacian", "regulariser", "regulariser_normal",
           "CurlNormal", "curl_normal", "apply_regulariser"]


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
    formed square, and no sparse matrix product per frame; docs/tuning.md, "Speed").
    ``M`` is symmetric, so ``diag(M^2)`` is the row sums of ``M``'s squared entries.
    """

    def __init__(self, M: sp.csr_matrix):
        self.M = M

    def diagonal(self) -> np.ndarray:
        # every row holds its diagonal entry, so no row is empty (reduceat needs that);
        # far cheaper than scipy's elementwise product (docs/tuning.md, "Speed")
        M = self.M
        if M.shape[0] == 0:
            return np.zeros(0)
        return np.add.reduceat(np.asarray(M.data, dtype=np.float64) ** 2, M.indptr[:-1])


def regulariser(inset: np.ndarray, prior: str = TomoParams.prior) -> sp.csr_matrix | SquaredLaplacian:
    """The smoothness term's normal matrix as the solver applies it: :func:`difference_normal`
    for ``first-differences``, :class:`SquaredLaplacian` of it for ``second-differences``
    (equal to :func:`regulariser_normal`, never formed)."""
    if prior not in ("first-differences", "second-differences"):
        raise ValueError(f"prior must be 'first-differences' or 'second-differences', not {prior!r}")
    M = difference_normal(inset)
    return M if prior == "first-differences" else SquaredLaplacian(M)


def apply_regulariser(R, X: np.ndarray) -> np.ndarray:
    """``R @ X`` for three columns (``R`` from :func:`regulariser`)."""
    if isinstance(R, SquaredLaplacian):
        return _apply_cols(R.M, _apply_cols(R.M, X))
    return _apply_cols(R, X)


def regulariser_normal(inset: np.ndarray, prior: str = TomoParams.prior) -> sp.csr_matrix:
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
    per frame instead of a sparse matrix product; docs/tuning.md, "Speed").

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
