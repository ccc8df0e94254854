"""The discretised anisotropic Poisson equation (paper sec. 5, eq. 8) on the hull.

Discretisation ("first-order forward and backward differences, similar to central
differences", sec. 5): with ``u = r - r_ambient`` (zero outside the hull and outside the
grid) minimise

    E(u) = 1/4 sum_i sum_{s=+,-} (grad_s u_i - g_i)^T D_i (grad_s u_i - g_i),

where ``grad_+`` / ``grad_-`` are the forward / backward difference gradients at voxel
``i``. The normal equations ``A u = f`` with ``A = 1/2 sum_s grad_s^T D grad_s`` are
symmetric positive definite; for ``D = 1`` ``A`` is the 7-point Laplacian and ``f`` the
central-difference divergence of ``g``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp

from schlieren.pipeline.poisson._assembly_kernels import _assemble_rows
from schlieren.pipeline.poisson.tensor import diffusion_tensor

if TYPE_CHECKING:
    from schlieren.pipeline.poisson.params import PoissonParams

__all__ = ["assemble", "laplacian_matrix"]


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
