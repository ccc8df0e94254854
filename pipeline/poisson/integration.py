"""Per-frame Poisson integration (paper sec. 5, eq. 8): parameters, the solvers and
:func:`integrate` (pad, assemble, solve, sign constraint)."""

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
from schlieren.pipeline.params import param
from schlieren.pipeline.poisson.assembly import assemble
from schlieren.pipeline.poisson.multigrid import LaplaceMultigrid
from schlieren.pipeline.poisson.tensor import SIGNS, sign_constraint

__all__ = ["PoissonParams", "PoissonInfo", "integrate", "SOLVERS"]

log = logging.getLogger(__name__)

SOLVERS = ("mg", "amg", "jacobi_cg")


@dataclass(frozen=True)
class PoissonParams:
    """Parameters of :func:`integrate`.

    Attributes
    ----------
    alpha : float
        Data fidelity of the diffusion tensor (Appendix); 1 = plain Poisson (the
        default: the paper's 0.8 measured no gain on the realistic family, see the
        notes of :mod:`schlieren.pipeline.poisson.tensor`).
    sigma : float
        Gaussian smoothing of the structure tensor, voxels.
    k : float
        Edge constant of the Appendix, in the units described in the docstring of
        :mod:`schlieren.pipeline.poisson.tensor`.
    value_scale : float
        The field range those units assume (255: 8-bit volume; see the notes of
        :mod:`schlieren.pipeline.poisson.tensor`).
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
