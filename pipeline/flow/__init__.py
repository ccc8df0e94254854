"""BOS deflection fields: dense optical flow between a reference background and a frame.

Paper section 4 ("Computing BOS deflections"): gradient-based optical flow (Lucas-Kanade,
Horn-Schunck) beats window cross-correlation on BOS data; the flow is smoothed and filtered
for outliers, computed at *full* resolution and only then downsampled to the flow grid.

Conventions (SPEC "Flow sign convention", docs/design.md):

* ``frame(p) ~= reference(p + delta)``; ``delta`` in pixels of the original image.
* Component 0 = u (x, columns), component 1 = v (y, rows).
* Images are float32 grey levels (8- or 16-bit range), indexed ``[row, column]``.

The public entry points are :func:`deflection_field` (full-resolution flow, one of several
methods behind one pyramid driver) and :func:`deflection_stage` (the per camera-frame stage
kernel: flow + outlier removal + smoothing + area downsampling to the
:class:`~schlieren.pipeline.geometry.FlowGrid`).

Modules: :mod:`.params` (:class:`FlowParams` and the rules read off it), :mod:`.stage`
(the two entry points and the pyramid driver), :mod:`.reference` (the prepared reference,
invalid pixels, the frame's pyramid), :mod:`.invalid` (the cells invalid pixels leave
without support; a camera's defective pixels prepared once), :mod:`.images`
(normalisation, pre-smoothing, pyramid, gradients), :mod:`.splines` (exact cubic B-spline
warps, prolongation), :mod:`.focus` (the pre-smoothing a reference's sharpness asks for),
:mod:`.windows` (the LK window and :func:`measurement_sigma`), the methods :mod:`.lk`,
:mod:`.hs`, :mod:`.dis` and :mod:`.correlation`, :mod:`.post` (outliers, smoothing,
downsampling), :mod:`.refine` (the flow measured around a predicted deflection:
re-projection refinement), and the numba kernels in :mod:`._kernels`.
:func:`endpoint_error` lives in :mod:`schlieren.pipeline.metrics`.
"""

from schlieren.pipeline.metrics import endpoint_error

from .images import nonfinite_cells
from .focus import auto_presmooth, reference_blur, resolve_presmooth
from .lk import ici_windows
from .params import (CELL_SOLVE_MIN_CELLS, METHODS, FlowParams, camera_window, px_per_voxel, uses_cell_solve,
                     window_for_voxel)
from .invalid import InvalidPixels, prepare_invalid
from .post import downsample_flow, remove_outliers, smooth_flow
from .reference import PreparedReference, frame_pyramid, invalid_pixels, prepare_reference
from .refine import RefineParams, cells_to_pixels, predicted_reference, refined_deflection
from .roi import RefineRegion, flow_reach, refine_region, refined_deflection_in_region
from .splines import prolong_flow, spline_coefficients, warp_coefficient_rows, warp_coefficients, warp_image
from .stage import deflection_field, deflection_stage
from .windows import measurement_sigma

__all__ = [
    "FlowParams",
    "METHODS",
    "PreparedReference",
    "prepare_reference",
    "frame_pyramid",
    "InvalidPixels",
    "prepare_invalid",
    "nonfinite_cells",
    "deflection_field",
    "deflection_stage",
    "remove_outliers",
    "smooth_flow",
    "downsample_flow",
    "warp_image",
    "spline_coefficients",
    "warp_coefficients",
    "warp_coefficient_rows",
    "endpoint_error",
    "invalid_pixels",
    "window_for_voxel",
    "camera_window",
    "px_per_voxel",
    "measurement_sigma",
    "auto_presmooth",
    "reference_blur",
    "resolve_presmooth",
    "uses_cell_solve",
    "CELL_SOLVE_MIN_CELLS",
    "ici_windows",
    "prolong_flow",
    "cells_to_pixels",
    "refined_deflection",
    "RefineParams",
    "RefineRegion",
    "predicted_reference",
    "flow_reach",
    "refine_region",
    "refined_deflection_in_region",
]
