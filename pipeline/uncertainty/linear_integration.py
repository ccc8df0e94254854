"""The frame's integration (paper eq. 8) as a linear map from gradient perturbations to refractivity.

:func:`~schlieren.pipeline.poisson.integrate` solves ``A u = f(g)`` on the hull. Its
diffusion tensor ``D`` (Appendix) depends on the gradient, so the map is linearised
around the frame's estimate: ``A`` and ``D`` are those of the estimate's gradient, and a
perturbation ``dg`` of the gradient moves the refractivity by ``du = A^-1 f_D(dg)`` (for
the default ``alpha = 1``, ``D = 1``, this is exact). The sign constraint that follows
the integration is left out: it only sets voxels to ambient, and the standard error of the
unconstrained value is kept there (conservative). The box faces get the integration's
own rule (:class:`~schlieren.pipeline.poisson.PoissonParams` ``box_boundary``).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.linalg.cg import pcg
from schlieren.pipeline.poisson.assembly import assemble, tensor_field
from schlieren.pipeline.poisson.integration import PoissonParams
from schlieren.pipeline.poisson.multigrid import LaplaceMultigrid

__all__ = ["LinearisedIntegration"]

_PAD = ((1, 1), (1, 1), (1, 1))


class LinearisedIntegration:
    """``dg (nz, ny, nx, 3) -> du (nz, ny, nx)``: the integration of a gradient perturbation
    with the operator (and diffusion tensor) of the frame's estimate.

    Parameters
    ----------
    hull : ndarray, shape (nz, ny, nx) bool
    grid : Grid
    poisson : PoissonParams
        As the run's integration (``alpha``, ``box_boundary``, the tensor's constants).
    gradient : ndarray, shape (nz, ny, nx, 3)
        The estimate the tensor is taken from (unused for ``alpha >= 1``).
    tol : float
        Relative residual of each solve (conjugate gradients preconditioned by the
        integration's multigrid V-cycle); a standard error needs two digits.
    """

    def __init__(self, hull: np.ndarray, grid: Grid, *, poisson: PoissonParams = PoissonParams(),
                 gradient: np.ndarray | None = None, tol: float = 1e-4, max_iter: int = 500):
        self.hull = np.asarray(hull, dtype=bool)
        if self.hull.shape != tuple(grid.shape):
            raise ValueError(f"hull {self.hull.shape} does not match the grid {grid.shape}")
        self.h = float(grid.voxel_size)
        self.params = poisson
        self.tol, self.max_iter = float(tol), int(max_iter)
        self.n = int(self.hull.sum())
        self.hull_p = np.pad(self.hull, _PAD)
        self.real = None
        if poisson.box_boundary == "neumann":  # as integrate(): natural faces unless the hull fills the box
            rim = ndi.binary_dilation(self.hull, structure=ndi.generate_binary_structure(3, 1)) & ~self.hull
            if rim.any():
                self.real = np.pad(np.ones(self.hull.shape, bool), _PAD)
        if self.n == 0:
            return
        g = np.zeros(self.hull.shape + (3,)) if gradient is None else np.asarray(gradient, dtype=np.float64)
        g_p = np.pad(g, _PAD + ((0, 0),))
        self.tensor = tensor_field(g_p, self.hull_p, self.h, params=poisson)
        self.A, _ = assemble(g_p, self.hull_p, self.h, params=poisson, real=self.real, tensor=self.tensor)
        self.mg = LaplaceMultigrid(self.hull_p, self.h, real=self.real)

    def __call__(self, dg: np.ndarray) -> np.ndarray:
        """The refractivity perturbation of gradient perturbation ``dg`` (1/m); zero outside the hull."""
        out = np.zeros(self.hull.shape)
        if self.n == 0:
            return out
        _, f = assemble(np.pad(np.asarray(dg, dtype=np.float64), _PAD + ((0, 0),)), self.hull_p, self.h,
                        params=self.params, real=self.real, tensor=self.tensor)
        if not np.any(f):
            return out
        u, _ = pcg(self.A, f, self.mg.apply, tol=self.tol, max_iter=self.max_iter)
        out[self.hull] = u
        return out
