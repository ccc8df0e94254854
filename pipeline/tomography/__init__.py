"""Gradient-field tomography (paper sec. 5): rays, projection operator, per-frame solve.

Per session: :func:`build_geometry` (cache it by :func:`content_hash`; convert with
:func:`save_geometry` / :func:`load_geometry`). Per frame: :func:`solve_gradient` (from
deflections or right-hand sides), :func:`solve_gradient_d_out` (from exact exit
directions) or :func:`solve_refractivity` (direct ``n - 1`` reconstruction).
"""

from schlieren.pipeline.tomography.binning import bin_cells, bin_quiet, binned_sigma, ray_binning, ray_grid
from schlieren.pipeline.tomography.blur import MeasurementBlur, VolumeBlur, volume_sigma
from schlieren.pipeline.tomography.direct import RefractivityInfo, solve_refractivity
from schlieren.pipeline.tomography.geometry import (
    TomoGeometry,
    build_geometry,
    content_hash,
    load_geometry,
    save_geometry,
)
from schlieren.pipeline.tomography.params import RefractivityParams, TomoParams
from schlieren.pipeline.tomography.rays import approximate_d_out, rhs_from_d_out, rhs_from_flows
from schlieren.pipeline.tomography.reg_choice import RegularisationChoice, choose_reg_weight, rhs_noise, rhs_snr
from schlieren.pipeline.tomography.solve import SolveInfo, block_support, solve_gradient, solve_gradient_d_out

__all__ = [
    "TomoParams", "RefractivityParams", "TomoGeometry", "build_geometry", "content_hash",
    "save_geometry", "load_geometry", "approximate_d_out", "rhs_from_d_out", "rhs_from_flows",
    "SolveInfo", "solve_gradient", "solve_gradient_d_out", "RefractivityInfo",
    "solve_refractivity", "RegularisationChoice", "choose_reg_weight", "rhs_noise", "rhs_snr", "MeasurementBlur",
    "VolumeBlur", "volume_sigma", "block_support", "ray_binning", "ray_grid", "bin_cells", "bin_quiet",
    "binned_sigma",
]
