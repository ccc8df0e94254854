"""Per-frame Poisson integration (paper sec. 5, eq. 8): the solvers and :func:`integrate`
(pad, assemble, solve, sign constraint); the parameters are :class:`~.params.PoissonParams`."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.linalg._cg_kernels import dot
from schlieren.pipeline.linalg.cg import pcg
from schlieren.pipeline.poisson.assembly import assemble
from schlieren.pipeline.poisson.multigrid import LaplaceMultigrid
from schlieren.pipeline.poisson.params import SOLVERS, PoissonParams
from schlieren.pipeline.poisson.tensor import sign_constraint

__all__ = ["PoissonParams", "PoissonInfo", "integrate", "SOLVERS"]

log = logging.getLogger(__name__)


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


def _solve(A: sp.csr_matrix, f: np.ndarray, x0: np.ndarray | None, solver: str, tol: float, max_iter: int,
           mask: np.ndarray, h: float, real: np.ndarray | None = None):
    """Solve ``A u = f``; returns (u, iterations, relative residual, setup s, solve s).

    ``real`` (as in :func:`assemble`) gives the multigrid preconditioner the same natural
    faces as ``A``.
    """
    t0 = time.perf_counter()
    f = np.ascontiguousarray(f, dtype=np.float64)
    fn = float(np.sqrt(dot(f, f)))
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
    rel = float(np.sqrt(dot(res, res)) / fn)
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
