"""Parameters of the Poisson integration (paper sec. 5, eq. 8 and Appendix): :class:`PoissonParams`,
with the solver and sign keywords (:data:`SOLVERS`, :data:`SIGNS`). Their own module, so the
tensor, assembly and driver modules can all take their defaults from it."""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["PoissonParams", "SOLVERS", "SIGNS"]

#: Solvers of :func:`~schlieren.pipeline.poisson.integrate` (``PoissonParams.solver``).
SOLVERS = ("mg", "amg", "jacobi_cg")
#: Signs of :func:`~schlieren.pipeline.poisson.sign_constraint` (``PoissonParams.sign``).
SIGNS = ("auto", "negative", "positive", "none")


@parameters
class PoissonParams:
    """Parameters of :func:`~schlieren.pipeline.poisson.integrate`."""

    alpha: float = param(
        1.0, unit="1", gt=0, le=1,
        help="Data fidelity of the Appendix's diffusion tensor; 1 is plain Poisson integration.",
        tuned=True)
    sigma: float = param(
        0.5, unit="voxels", ge=0, le=20,
        help="Gaussian smoothing of the structure tensor.")
    k: float = param(
        0.5e-5, unit="1", gt=0, le=1e3,
        help="Edge constant of the Appendix's diffusion tensor, in the units of `pipeline.poisson.tensor`.")
    value_scale: float = param(
        255.0, unit="1", gt=0, le=1e9,
        help="The field range the edge constant's units assume (255: an 8-bit volume).")
    box_boundary: str = param(
        "neumann", choices=("neumann", "dirichlet"),
        help="Where the hull touches a face of the box: `neumann` drops the differences across the face (a "
             "plume from the floor or through the top), `dirichlet` holds `r` at ambient beyond it (the "
             "paper); inside the box the hull boundary is always Dirichlet.")
    solver: str = param(
        "mg", choices=SOLVERS,
        help="`mg`: CG preconditioned by a geometric-multigrid V-cycle of the hull Laplacian; `amg`: by "
             "pyamg smoothed aggregation (its setup dominates); `jacobi_cg`: the paper's Jacobi-preconditioned "
             "CG.")
    tol: float = param(
        1e-6, unit="1", gt=0, lt=1,
        help="Relative residual `||f - A u|| / ||f||` at which to stop.")
    max_iter: int = param(
        5000, unit="1", ge=1, le=100000,
        help="Iteration cap.")
    sign: str = param(
        "auto", choices=SIGNS,
        help="Sign of the refractivity offset: `negative` for hot or light gas, `positive` for cold or dense "
             "gas; hull voxels of the other sign (the ringing of few views) are set to ambient. `auto`: the "
             "frame's dominant sign, if the other holds at most `sign_max_opposite`; `none`: keep every "
             "value (the paper).",
        see="benchmarks/results/realistic_no_sign.md")
    sign_max_opposite: float = param(
        0.1, unit="1", ge=0, le=0.5,
        help="`auto` applies the sign only when the opposite sign holds at most this share of the summed "
             "`|r - r_ambient|` (a flow of both signs is left as it is).")
