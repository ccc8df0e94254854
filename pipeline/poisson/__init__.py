"""Anisotropic Poisson integration of the reconstructed gradient (paper sec. 5, eq. 8, Appendix).

Solves ``div(D grad n) = div(D g)`` for the refractivity inside the visual hull with the
Dirichlet condition ``r = r_ambient`` outside (paper: ``n = n_air`` outside the hull).
Beyond the paper: where the hull touches a face of the reconstruction box (a plume
rising from a source on the floor or leaving through the top) the flow is not ambient
beyond the face, so by default the differences crossing the box faces are dropped
there (natural boundary, ``box_boundary="neumann"``; docs/tuning.md, "Poisson").

Modules: :mod:`~schlieren.pipeline.poisson.params` (:class:`PoissonParams`),
:mod:`~schlieren.pipeline.poisson.tensor` (the Appendix's diffusion tensor and the
sign constraint), :mod:`~schlieren.pipeline.poisson.assembly` (the discretised eq. 8),
:mod:`~schlieren.pipeline.poisson.multigrid` (the "mg" solver's preconditioner) and
:mod:`~schlieren.pipeline.poisson.integration` (:func:`integrate`, the per-frame driver);
the conjugate-gradient loop is :func:`schlieren.pipeline.linalg.pcg`.
"""

from schlieren.pipeline.linalg.cg import pcg
from schlieren.pipeline.poisson.assembly import assemble, laplacian_matrix
from schlieren.pipeline.poisson.integration import PoissonInfo, integrate
from schlieren.pipeline.poisson.multigrid import LaplaceMultigrid
from schlieren.pipeline.poisson.params import SIGNS, SOLVERS, PoissonParams
from schlieren.pipeline.poisson.tensor import diffusion_tensor, sign_constraint

__all__ = ["PoissonParams", "PoissonInfo", "integrate", "sign_constraint", "diffusion_tensor", "assemble",
           "SOLVERS", "SIGNS", "LaplaceMultigrid", "laplacian_matrix", "pcg"]
