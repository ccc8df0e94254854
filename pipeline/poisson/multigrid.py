"""Geometric multigrid preconditioner of the Poisson solve (the "mg" solver).

V-cycle for the 7-point Laplacian on the hull (Dirichlet outside), the preconditioner of
the "mg" solver. The diffusion tensor's eigenvalues lie in [alpha, 1], so the plain
Laplacian on the same hull is spectrally equivalent to the anisotropic operator
(condition number of the preconditioned system <= 1 / alpha) and one Laplacian V-cycle
preconditions both. Matrix-free numba kernels and a setup of a few milliseconds, so it
is rebuilt for every frame's hull (pyamg's setup alone costs more than the whole solve
at these sizes).

Hierarchy: cell-centred, on the bounding box of the hull; a coarse cell is active if at
least ``min_children`` of its 2x2x2 children are. Prolongation is cell-centred trilinear,
restriction its transpose / 8. Coarse operators are 7-point stencils with per-face
weights from an aggregation (piecewise-constant) Galerkin product: the weight of a coarse
face is the number of active fine faces crossing it / 4 (exactly the rediscretised
Laplacian where the blocks are full), and the Dirichlet part of a coarse diagonal is half
the sum of its children's (the uncorrected Galerkin value). A plain rediscretisation
moves the Dirichlet boundary outwards by half a coarse cell per level; the V-cycle then
over-corrects the smooth modes and *diverges* as a stationary iteration (even on a full
box), which costs CG more iterations (docs/tuning.md, "Poisson").

Smoothing: red-black Gauss-Seidel, red then black before the coarse correction and
black then red after it (the V-cycle is symmetric, as CG requires). Starting from zero,
the first red half-sweep needs no neighbours and after the black half-sweep the residual
vanishes on black cells, so the pre-smoothing and the residual each cost about half a
sweep. The finest level iterates over lists of its active cells (the hull fills under
half of its bounding box); the coarsest level is solved by sparse LU.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from schlieren.pipeline.poisson._multigrid_kernels import (
    _coarsen,
    _fine_level,
    _gs_cells,
    _gs_red_gather,
    _gs_weighted,
    _prolong_add,
    _residual_cells,
    _residual_weighted,
    _restrict,
    _scatter_first,
)
from schlieren.pipeline.poisson.assembly import laplacian_matrix

__all__ = ["LaplaceMultigrid"]


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
    with the hull, not with the grid. As a CG preconditioner it needs an order of
    magnitude fewer iterations than Jacobi-PCG, with natural or Dirichlet box faces, and
    its setup is cheap enough to rebuild per frame (benchmarks/results/poisson.md;
    docs/tuning.md, "Poisson"). Vectors passed to :meth:`apply` are ordered like
    ``mask[mask]`` (C order).
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
