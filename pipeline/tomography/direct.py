"""Direct refractivity reconstruction (beyond the paper).

Instead of reconstructing the three gradient components independently and integrating
them afterwards (paper sec. 5), solve for the refractivity perturbation
``u = r - r_amb`` on the hull voxels directly, with the projection composed with a
discrete gradient:

    min ||S G u - b||^2 + mu^2 ||L u||^2,   u = 0 outside the hull,

where ``G`` is the central-difference gradient (1/m; a grid vector of ``u`` values maps
to gradient coefficients on the basis set), ``b = n_amb (d_out - d_in)`` for all three
components at once and ``L`` first differences on the hull (the smoothness regulariser;
it also removes the checkerboard null space of central differences). The result is
curl-free by construction, and the Dirichlet condition ``r = r_amb`` outside the hull is
built in, so no separate Poisson step is needed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.tomography.geometry import TomoGeometry
from schlieren.pipeline.tomography.params import RefractivityParams
from schlieren.pipeline.linalg.cgls import cgls
from schlieren.pipeline.tomography.regularisers import difference_operator
from schlieren.pipeline.tomography.solve import frame_rhs, prepare_frame, valid_rays

__all__ = ["RefractivityInfo", "solve_refractivity", "central_gradient_operators"]


@dataclass(frozen=True)
class RefractivityInfo:
    """Receipt of a direct refractivity solve (fields as in ``SolveInfo``)."""

    iterations: int
    residual: float
    n_unknowns: int
    n_rays: int
    stop_reason: str
    seconds: float


def central_gradient_operators(hull: np.ndarray, inset: np.ndarray, h: float) -> list[sp.csr_matrix]:
    """Central differences from hull voxels (columns) to basis-set voxels (rows), per axis.

    ``u`` is zero outside the hull; rows are the ``inset`` voxels in C order.

    Returns
    -------
    [Gx, Gy, Gz] : list of scipy.sparse.csr_matrix, each shape (inset.sum(), hull.sum()), 1/m
    """
    shape = hull.shape
    n_h = int(hull.sum())
    hmap = np.full(hull.size, -1, np.int64)
    hmap[hull.ravel()] = np.arange(n_h)
    smap = np.full(hull.size, -1, np.int64)
    smap[inset.ravel()] = np.arange(int(inset.sum()))
    idx = np.arange(hull.size).reshape(shape)
    ops = []
    for axis in (2, 1, 0):  # x, y, z
        rows, cols, vals = [], [], []
        for sign in (+1, -1):
            src = [slice(None)] * 3
            dst = [slice(None)] * 3
            if sign > 0:  # row i gets +u[i+1]
                dst[axis] = slice(0, shape[axis] - 1)
                src[axis] = slice(1, shape[axis])
            else:  # row i gets -u[i-1]
                dst[axis] = slice(1, shape[axis])
                src[axis] = slice(0, shape[axis] - 1)
            d = idx[tuple(dst)].ravel()
            s = idx[tuple(src)].ravel()
            ok = (hmap[s] >= 0) & (smap[d] >= 0)
            rows.append(smap[d[ok]])
            cols.append(hmap[s[ok]])
            vals.append(np.full(int(ok.sum()), sign / (2.0 * h)))
        G = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(int(inset.sum()), n_h))
        ops.append(G)
    return ops


def solve_refractivity(geom: TomoGeometry, rhs_or_flows: np.ndarray, hull: np.ndarray, grid: Grid, *,
                       r_ambient: float, params: RefractivityParams = RefractivityParams(),
                       x0: np.ndarray | None = None) -> tuple[np.ndarray, RefractivityInfo]:
    """Reconstruct ``r = n - 1`` directly from deflections (one regularised least squares).

    Parameters
    ----------
    geom : TomoGeometry
    rhs_or_flows : ndarray, shape (C, h, w, 2) or (C, h, w, 3)
        Deflections (pixels) or right-hand sides ``n_amb (d_out - d_in)``.
    hull : ndarray, shape (nz, ny, nx) bool
    grid : Grid
    r_ambient : float
        Refractivity outside the hull (``n_ambient - 1``).
    params : RefractivityParams
    x0 : ndarray, shape (nz, ny, nx), optional
        Warm start (previous frame's refractivity).

    Returns
    -------
    refractivity : ndarray, shape (nz, ny, nx) float64
    info : RefractivityInfo
    """
    t0 = time.perf_counter()
    hull = np.asarray(hull, dtype=bool)
    data = np.asarray(rhs_or_flows)
    sys_ = prepare_frame(geom, hull, dilation=1, rows=valid_rays(data))
    op = sys_.op
    out = np.full(grid.shape, float(r_ambient))
    n_h = int(hull.sum())
    if n_h == 0 or op.m == 0:
        return out, RefractivityInfo(0, 0.0, n_h, op.m, "empty", time.perf_counter() - t0)
    b = frame_rhs(geom, data, op.rows, n_ambient=params.n_ambient)
    G = central_gradient_operators(hull, sys_.inset, grid.voxel_size)
    GT = [g.T.tocsr() for g in G]
    L = difference_operator(hull)
    LT = L.T.tocsr()
    # Jacobi-like column scaling: diag(G^T diag(S^T S) G) summed over components.
    d = sum(np.asarray(g.multiply(g).T @ sys_.colsumsq).ravel() for g in G)
    mu2 = params.reg_weight * float(np.mean(d))
    mu = np.sqrt(mu2)
    lsq = np.asarray(L.multiply(L).sum(axis=0)).ravel()
    diag = d + mu2 * lsq
    P = (1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)))[:, None]
    m = op.m

    def A(z):
        u = (P * z)[:, 0]
        X = np.stack([g @ u for g in G], axis=1)
        return [op.matvec3(X).reshape(-1, 1), mu * (L @ u)[:, None]]

    def AT(rs):
        Y = op.rmatvec3(rs[0].reshape(m, 3))
        g = sum(GT[k] @ Y[:, k] for k in range(3)) + mu * (LT @ rs[1][:, 0])
        return P * g[:, None]

    if x0 is not None:
        z0 = ((np.asarray(x0, dtype=np.float64)[hull] - r_ambient)[:, None]) / P
    else:
        z0 = np.zeros((n_h, 1))
    res = cgls(A, AT, [b.reshape(-1, 1), np.zeros((L.shape[0], 1))], z0, max_iter=params.max_iter,
               tol=params.tol, n_data_parts=1)
    u = (P * res.x)[:, 0]
    out[hull] += u
    rel = float(res.data_residual[0] / res.rhs_norm[0]) if res.rhs_norm[0] > 0 else 0.0
    return out, RefractivityInfo(res.iterations, rel, n_h, m, res.stop_reason, time.perf_counter() - t0)
