"""Parameters of the tomography stage (frozen params classes; field names = kernel keywords)."""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["TomoParams", "RefractivityParams"]



@parameters
class TomoParams:
    """Gradient-field tomography (paper sec. 5, eqs. 4-6)."""

    step: float = param(
        0.25, unit="voxels", gt=0, le=1,
        help="Ray-marching step of the basis functions' line integrals (midpoint rule); part of the geometry "
             "cache key.")
    prune: float = param(
        0.05, unit="1", ge=0, lt=1,
        help="Projection entries below this fraction of their row's largest (nodes a ray only grazes) are "
             "dropped and the row rescaled to keep its sum, which speeds the solves; 0 keeps every entry.",
        tuned=True)
    ray_binning: int = param(
        0, unit="flow cells", ge=0, le=16,
        help="Flow cells per tomography ray along each image axis: 1 = a ray per flow cell (the paper), `b` = "
             "one ray through each `b x b` block of cells measuring its mean flow, 0 = the run chooses.",
        derived="for 0, the largest `b` that leaves at least 1.25 rays per voxel edge at the box centre (only "
                "flow grids finer than the voxels are binned).",
        see="benchmarks/results/tomography_speed_auto.md", tuned=True)
    hull_dilation: int = param(
        1, unit="voxels", ge=0, le=10,
        help="Basis functions kept per frame: the hull dilated by this many voxels; 1 keeps every basis "
             "function whose support touches the hull, as in the paper.")
    prior: str = param(
        "second-differences", choices=("first-differences", "second-differences"),
        help="Smoothness term of the solve: the squared first differences of each gradient component (the "
             "paper's) or the squared Laplacian, a curvature penalty that lets smooth ramps through.",
        see="benchmarks/results/realistic_first_differences.md", tuned=True)
    reg_weight: float = param(
        0.1, unit="1", ge=0, le=1e6,
        help="Weight of the smoothness term relative to the mean of `diag(S^T S)` (0: plain least squares, "
             "which semi-converges with noisy data); used as given with `reg_choice: fixed`.",
        derived="with `reg_choice: discrepancy`, the weight chosen on the middle frame (this value is then "
                "only the fallback when no noise can be measured).")
    reg_choice: str = param(
        "discrepancy", choices=("discrepancy", "fixed"),
        help="`discrepancy`: the run picks, on the middle frame, the weight whose data residual matches the "
             "noise measured outside the masks (Morozov's principle) and uses it for every frame; `fixed`: "
             "`reg_weight`.")
    reg_tau: float = param(
        0.7, unit="1", gt=0, le=100,
        help="Safety factor of the discrepancy principle: the residual target is `reg_tau` times the measured "
             "noise, below 1 because the solution fits part of the spatially correlated flow noise.",
        tuned=True)
    curl_weight: float = param(
        3.0, unit="1", ge=0, le=1e6,
        help="Weight of the integrability term (the discrete curl of the gradient field), relative like "
             "`reg_weight`: a refractive-index gradient is curl-free, so coupling the components removes "
             "null-space parts that are not gradients. 0 solves the components independently (the paper).",
        see="benchmarks/results/realistic_second_differences.md", tuned=True)
    model_flow_window: bool = param(
        True,
        help="Model the flow's image averaging (LK window, smoothing, block mean) in the data term instead of "
             "rays through the cell centres (beyond the paper); the widths are stored as `flow_window`.",
        see="benchmarks/results/realistic_curl.md", tuned=True)
    flow_window_space: str = param(
        "volume", choices=("volume", "image"),
        help="Where `model_flow_window` averages: `volume`, one Gaussian over the basis coefficients (fast, "
             "exact for parallel rays), or `image`, each camera's Gaussian over its flow cells (slower).",
        see="benchmarks/results/realistic_flow_window.md", tuned=True)
    flow_window_scale: float = param(
        0.9, unit="1", gt=0, le=10,
        help="Factor on the width of the modelled flow averaging (`measurement_sigma` times this), below 1 "
             "because that formula's width exceeds the flow's real averaging.",
        see="benchmarks/results/realistic_window_scale_rebased.md", tuned=True)
    max_iter: int = param(
        25, unit="1", ge=1, le=10000,
        help="Iteration cap of the conjugate-gradient solver (CGLS-equivalent).")
    tol: float = param(
        5e-3, unit="1", gt=0, lt=1,
        help="Stop when the normal-equation residual of every component has dropped by this factor.")
    discrepancy: float = param(
        0.0, unit="1", ge=0, le=100,
        help="If > 0, also stop when the data residual of every component is below "
             "`discrepancy * noise_rms * sqrt(m)` (Morozov's principle); 0 disables it.")
    n_ambient: float = param(
        1.00029, unit="1", ge=1, le=3,
        help="Refractive index of the surrounding air: the right-hand side is `n_ambient * (d_out - d_in)` "
             "(eq. 3).",
        derived="from the session's `medium.n_ambient`.")


@parameters
class RefractivityParams:
    """Direct refractivity reconstruction (beyond the paper): solve for ``r = n - 1``."""

    reg_weight: float = param(
        0.02, unit="1", ge=0, le=1e6,
        help="First-difference smoothness of `r` relative to the mean diagonal of the data normal matrix.")
    max_iter: int = param(
        150, unit="1", ge=1, le=100000,
        help="Iteration cap of the CGLS solver.")
    tol: float = param(
        1e-4, unit="1", gt=0, lt=1,
        help="Relative normal-equation residual at which to stop.")
    n_ambient: float = param(
        1.00029, unit="1", ge=1, le=3,
        help="Refractive index of the surrounding air (scales the right-hand side).",
        derived="from the session's `medium.n_ambient`.")
