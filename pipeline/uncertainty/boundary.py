"""How much the integration's boundary condition, not the data, sets the refractivity.

The integration (paper sec. 5, eq. 8) pins ``r = r_ambient`` outside the visual hull. Its
reconstructed gradient ``g`` carries errors (the ray noise, the prior's and the views'
bias, the flow's error inside the plume) that integrate into a slowly varying error of
``r``, largest far from the hull boundary; and where the hull cuts through the plume (a
mask that missed it) the pinned boundary is simply wrong. Both show in the same
measurement: integrate ``g`` once more with a *natural* boundary on the hull surface
(differences that cross it dropped, ``r_N``, its constant fixed so that the median of each
connected part's surface layer is ambient) and compare with the pinned integration ``r_D``.
Their difference ``r_N - r_D`` is harmonic inside the hull (the two solves share the
interior equations) with the surface values of ``r_N``: how far the data, integrated on
their own, say the boundary is from ambient, carried into the interior. Its local RMS, scaled
(``UncertaintyParams.boundary_scale``, fitted on the realistic family's tune cases with the
bias term's, ``benchmarks/results/uncertainty_fit.md``), is the boundary term.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.linalg.cg import pcg
from schlieren.pipeline.poisson.assembly import assemble
from schlieren.pipeline.poisson.integration import PoissonParams
from schlieren.pipeline.poisson.multigrid import LaplaceMultigrid
from schlieren.pipeline.uncertainty.linear_integration import LinearisedIntegration

__all__ = ["natural_integration", "boundary_sensitivity"]

_PAD = ((1, 1), (1, 1), (1, 1))


def natural_integration(gradient: np.ndarray, hull: np.ndarray, grid: Grid, *,
                        poisson: PoissonParams = PoissonParams(), tensor: np.ndarray | None = None,
                        tol: float = 1e-5, max_iter: int = 1000) -> np.ndarray:
    """``r - r_ambient`` integrated from ``gradient`` inside ``hull`` with a natural boundary on
    the hull surface (eq. 8 without the Dirichlet condition), each connected part's constant
    set so that the median over its surface layer is 0; zero outside the hull.

    Parameters
    ----------
    gradient : ndarray, shape (nz, ny, nx, 3)
    hull : ndarray, shape (nz, ny, nx) bool
    grid : Grid
    poisson : PoissonParams
        The integration's (``alpha`` and the tensor's constants).
    tensor : ndarray, shape (nz + 2, ny + 2, nx + 2, 3, 3), optional
        The diffusion tensor on the padded grid (e.g. :attr:`LinearisedIntegration.tensor`).
    """
    hull = np.asarray(hull, dtype=bool)
    out = np.zeros(hull.shape)
    if not hull.any():
        return out
    hull_p = np.pad(hull, _PAD)
    g_p = np.pad(np.asarray(gradient, dtype=np.float64), _PAD + ((0, 0),))
    A, f = assemble(g_p, hull_p, float(grid.voxel_size), params=poisson, real=hull_p, tensor=tensor)
    # singular (one constant per connected part) but consistent: f = D^T g lies in A's range, and
    # CG on it with a positive definite preconditioner converges in that range. The V-cycle of
    # the pinned problem (Dirichlet outside the hull) is one; the natural problem's own V-cycle
    # is not (its coarsest level is singular).
    mg = LaplaceMultigrid(hull_p, float(grid.voxel_size))
    u, _ = pcg(A, f, mg.apply, tol=tol, max_iter=max_iter)
    out[hull] = u
    labels, n = ndi.label(hull)  # face-connected parts, as the 7-point stencil couples them
    surface = hull & ~ndi.binary_erosion(hull)  # every part has one (the grid's edge erodes too)
    med = np.asarray(ndi.median(out, labels=np.where(surface, labels, 0), index=np.arange(1, n + 1)))
    out[hull] -= med.reshape(-1)[labels[hull] - 1]
    return out


def boundary_sensitivity(gradient: np.ndarray, integration: LinearisedIntegration, grid: Grid, *,
                         poisson: PoissonParams = PoissonParams()) -> np.ndarray:
    """``r_N - r_D``: the natural-boundary integration of ``gradient``
    (:func:`natural_integration`) minus the pinned one (``integration``, the frame's
    linearised integration, without the sign constraint); zero outside the hull.

    Returns
    -------
    ndarray, shape (nz, ny, nx) float64
    """
    hull = integration.hull
    if not hull.any():
        return np.zeros(hull.shape)
    r_d = integration(gradient)
    r_n = natural_integration(gradient, hull, grid, poisson=poisson, tensor=integration.tensor)
    return np.where(hull, r_n - r_d, 0.0)
