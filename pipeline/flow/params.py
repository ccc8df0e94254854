"""Parameters of the deflection stage and the rules read off them.

:class:`FlowParams` (one frozen params class; field names = the kernels' keyword names),
:data:`METHODS`, when the finest LK level is solved per flow cell
(:func:`uses_cell_solve`) and the LK window a reconstruction voxel asks for
(:func:`window_for_voxel`, :func:`camera_window`).
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.geometry import pixel_footprint
from schlieren.pipeline.params import param, parameters

__all__ = ["METHODS", "FlowParams", "CELL_SOLVE_MIN_CELLS", "uses_cell_solve", "window_for_voxel",
           "px_per_voxel", "camera_window"]


METHODS = ("lk", "hs", "dis", "correlation")


@parameters
class FlowParams:
    """Parameters of the deflection stage (paper sec. 4; field names = keyword names of the kernels)."""

    method: str = param(
        "lk", choices=METHODS,
        help="Optical-flow method: Lucas-Kanade (paper sec. 4), Horn-Schunck, OpenCV DIS or window "
             "cross-correlation.")
    window: int = param(
        17, unit="px", ge=3, le=255, odd=True,
        help="Edge of the Lucas-Kanade integration window: larger windows lower the flow's noise and blur "
             "its detail.",
        derived="with `window_per_voxel` > 0, each camera's window spans `window_per_voxel` voxel footprints "
                "in its pixels (odd, 5 to 25 px).")
    window_type: str = param(
        "gaussian", choices=("box", "gaussian"),
        help="Weights of the LK window: uniform (`box`) or a Gaussian of sigma `window / 4` truncated at the "
             "window (`gaussian`).")
    levels: int = param(
        3, unit="1", ge=1, le=8,
        help="Pyramid levels of the flow (1 = full resolution only); each level halves the image, so larger "
             "deflections converge.")
    iterations: int = param(
        2, unit="1", ge=1, le=50,
        help="Warping iterations on each coarser pyramid level (LK and HS).")
    fine_iterations: int = param(
        1, unit="1", ge=1, le=50,
        help="Warping iterations on the full-resolution level (LK and HS): the costliest, and after a "
             "converged coarser level one reaches the accuracy of several.",
        tuned=True)
    presmooth: float | str = param(
        "auto", unit="px", ge=0, le=20, choices=("auto",),
        help="Gaussian sigma applied to both images before the flow, against sensor noise and the texture's "
             "finest band; 0 disables.",
        derived="with `auto`, per camera from the sharpness of its reference (pipeline/flow/focus.py): the "
                "in-focus width on an in-focus background, less on a blurred one.",
        see="benchmarks/results/realistic_focus.md")
    regularisation: float = param(
        1e-3, unit="1", ge=0, le=1e3,
        help="LK Tikhonov weight, relative to half the mean trace of the structure tensor: pulls the flow of "
             "textureless windows towards zero.")
    gradient: str = param(
        "frame", choices=("frame", "symmetric", "reference"),
        help="LK image gradient: the frame's, the mean of the frame's and the warped reference's, or the "
             "warped reference's alone. Noise in the gradient biases LK towards zero, so `reference` suits a "
             "reference averaged over many frames.")
    alpha: float = param(
        0.3, unit="1", gt=0, le=1e3,
        help="Horn-Schunck smoothness weight, in units of the normalised image gradient.")
    inner_iterations: int = param(
        30, unit="1", ge=1, le=1000,
        help="Horn-Schunck Jacobi iterations per warp.")
    dis_preset: str = param(
        "medium", choices=("ultrafast", "fast", "medium"),
        help="OpenCV DIS preset (speed against accuracy).")
    corr_window: int = param(
        32, unit="px", ge=8, le=512, even=True,
        help="Edge of the cross-correlation interrogation window.")
    corr_step: int = param(
        16, unit="px", ge=1, le=512,
        help="Spacing of the interrogation windows; half the window is the classic 50 % overlap.")
    corr_taper: bool = param(
        False,
        help="Hann-taper the interrogation windows against edge effects (false: the classic top-hat window).")
    outlier_threshold: float = param(
        3.0, unit="1", ge=0, le=100,
        help="Threshold of the normalised median test (Westerweel & Scarano 2005) on the flow grid; 0 "
             "disables.")
    outlier_epsilon: float = param(
        0.01, unit="px", ge=0, le=10,
        help="Noise floor of the normalised median test.")
    smoothing_sigma: float = param(
        0.5, unit="px", ge=0, le=100,
        help="Gaussian smoothing of the flow in full-resolution pixels (on the flow grid, "
             "`smoothing_sigma / factor` cells); 0 disables.")
    adaptive_sigma: float = param(
        0.0, unit="px", ge=0, le=200,
        help="Structure-adaptive smoothing: the larger Gaussian sigma applied where the flow is smooth (mostly "
             "noise), keeping the `smoothing_sigma` result across structure; for strong, smooth flows. 0 "
             "disables.",
        tuned=True)
    adaptive_threshold: float = param(
        3.0, unit="1", gt=0, le=100,
        help="Deviation between the `adaptive_sigma`- and the `smoothing_sigma`-smoothed flow, in units of "
             "its lower quartile over the image (a robust noise scale), at which the larger scale gets weight "
             "`1 / e`.")
    texture_correction: bool = param(
        True,
        help="LK: subtract the first-order bias of the texture-weighted window mean where the deflection "
             "varies inside the window.")
    factor: int = param(
        3, unit="px per flow cell", ge=1, le=32,
        help="Area-downsampling factor from image pixels to the flow grid (H // factor rows, W // factor "
             "columns), applied after the full-resolution flow.",
        derived="with `auto_factor`, the largest factor up to this one that leaves at least one flow cell "
                "per voxel edge.")
    auto_factor: bool = param(
        True,
        help="Let the run take a finer flow grid than `factor` where the voxels span few pixels: one flow "
             "cell per voxel edge is the Nyquist rate of the linear basis. False: `factor` as given.",
        see="benchmarks/results/realistic_factor3.md", tuned=True)
    invalid_check: bool = param(
        True,
        help="Give pixels that cannot carry a deflection (non-finite, clipped, textureless) zero weight in the "
             "flow, and return NaN on the flow cells they dominate.")
    texture_threshold: float = param(
        0.1, unit="1", ge=0, le=1,
        help="A pixel is textureless where the local (7x7) standard deviation of the image is below this "
             "fraction of its median over the image.")
    window_per_voxel: float = param(
        3.8, unit="1", ge=0, le=50,
        help="When > 0, each camera's LK window (and its invalid-pixel check) spans this many voxel "
             "footprints in its pixels instead of `window`, so the flow resolves what the voxels can hold; 0 "
             "uses `window`.",
        tuned=True)
    ici_gamma: float = param(
        0.0, unit="1", ge=0, le=10,
        help="LK with the frame gradient: > 0 chooses each pixel's window from `ici_min_window` up to "
             "`window` by the intersection of confidence intervals, `ici_gamma` predicted standard "
             "deviations wide; 0 uses `window` everywhere.")
    ici_min_window: int = param(
        5, unit="px", ge=3, le=255, odd=True,
        help="Smallest window of the ICI ladder.")
    cell_solve: str = param(
        "auto", choices=("auto", "on", "off"),
        help="LK (frame gradient, no ICI, `factor` > 1): solve the full-resolution level once per flow cell "
             "instead of at every pixel, at a fraction of the cost. `auto`: where the window spans at least "
             "`CELL_SOLVE_MIN_CELLS` cells; `on` / `off`: always / never.",
        tuned=True)


#: ``FlowParams.cell_solve = "auto"`` solves per cell when the LK window spans at least this
#: many flow cells (``window >= CELL_SOLVE_MIN_CELLS * factor``).
CELL_SOLVE_MIN_CELLS = 5


def uses_cell_solve(params: FlowParams) -> bool:
    """Whether :func:`deflection_stage` solves the finest LK level per flow cell (:func:`_lk_cells`)."""
    if params.cell_solve == "off" or params.method != "lk" or params.gradient != "frame" \
            or params.ici_gamma > 0 or params.factor <= 1:
        return False
    return params.cell_solve == "on" or params.window >= CELL_SOLVE_MIN_CELLS * params.factor


def window_for_voxel(px_per_voxel: float, window_per_voxel: float, *, smallest: int = 5,
                     largest: int = 25) -> int:
    """The odd LK window (pixels) spanning ``window_per_voxel`` voxel footprints."""
    w = int(round(window_per_voxel * px_per_voxel))
    w = min(max(w, smallest), largest)
    return w if w % 2 else w + 1


def px_per_voxel(camera, grid) -> float:
    """Image pixels the reconstruction voxel spans in ``camera`` at the box centre."""
    centre = 0.5 * (np.asarray(grid.vmin) + np.asarray(grid.vmax))
    return grid.voxel_size / pixel_footprint(camera, centre)


def camera_window(camera, grid, *, window: int = FlowParams.window,
                  window_per_voxel: float = FlowParams.window_per_voxel) -> int:
    """The LK window a run uses for ``camera``: :func:`window_for_voxel` of the voxel's
    footprint (:func:`px_per_voxel`) when ``window_per_voxel`` > 0, else ``window``."""
    if window_per_voxel <= 0:
        return window
    return window_for_voxel(px_per_voxel(camera, grid), window_per_voxel)
