"""The re-projection refinement computed only where it can differ from the plain flow.

A refined flow (:func:`~.refine.refined_deflection`) is ``p + W (d - p)`` with ``p`` the
tomography's prediction projected into the camera. Where ``p`` is zero (the camera's rays
miss the solution's support) and stays zero over the flow's whole reach, the refined flow
is the plain one ``W d``. So per camera-frame the refined flow is needed only on the region
where ``|p|`` exceeds a tolerance, grown by the flow's reach (:func:`flow_reach`: the
half-widths of the LK window on every pyramid level, of the spline prefilter and of the
smoothing kernels, from the camera's :class:`~.params.FlowParams`); the stored plain flow
holds elsewhere. That region is computed on a crop grown by the reach once more, so that its
edges (where the crop's borders replace the image's content) are out of the region's reach:
the region's cells then see the same pixels as in the full image (:func:`refine_region`).
The crop's origin lies on flow-cell and pyramid-cell boundaries, so its flow grid and every
pyramid level's pixels (and LK cells) coincide with the full image's.

What the crop cannot see: three image-wide statistics of the deflection stage, the LK
regularisation weight (relative to the mean structure tensor), the textureless-pixel
threshold (relative to the median local contrast) and the adaptive smoothing's noise scale,
are the crop's own. On a stationary background they differ from the image's by sampling
alone; tests/pipeline/test_flow_roi.py bounds what that leaves. Measurements:
benchmarks/results/refine_roi.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .images import _gaussian_taps
from .params import FlowParams
from .refine import refined_deflection

__all__ = ["RefineRegion", "flow_reach", "prediction_reach", "refine_region", "refined_deflection_in_region"]

#: The pole of the cubic B-spline prefilter (``sqrt(3) - 2``): an interpolated field's
#: influence decays by its magnitude per sample.
SPLINE_POLE = 2.0 - math.sqrt(3.0)
#: Relative size below which a B-spline prefilter's tail is taken as nothing.
SPLINE_TOLERANCE = 1e-6
#: Edge a crop needs on every axis for ``levels`` pyramid levels (the pyramid stops below
#: 16 pixels: :func:`~.images._pyramid`).
_MIN_LEVEL_EDGE = 16


def _spline_reach(tolerance: float = SPLINE_TOLERANCE) -> int:
    """Samples beyond which a cubic B-spline prefilter's response is below ``tolerance``."""
    return int(math.ceil(math.log(tolerance) / math.log(SPLINE_POLE)))


def _gaussian_blur_reach(sigma: float) -> int:
    """Half-width of OpenCV's Gaussian kernel for ``sigma`` on float images (``ksize`` 0:
    ``round(8 sigma + 1)``, made odd)."""
    return 0 if sigma <= 0 else (int(round(8.0 * sigma + 1.0)) | 1) // 2


def flow_reach(*, window: int = FlowParams.window, levels: int = FlowParams.levels,
               factor: int = FlowParams.factor, presmooth: float,
               smoothing_sigma: float = FlowParams.smoothing_sigma, adaptive_sigma: float = FlowParams.adaptive_sigma,
               displacement: float = 0.0) -> int:
    """Distance (full-resolution pixels) beyond which the images change a flow cell of
    :func:`~.stage.deflection_stage` (Lucas-Kanade) by float noise only.

    The LK window's half-width on every pyramid level (``2**l`` pixels per level pixel),
    the pre-smoothing Gaussian, the finest level's B-spline prefilter tail (to
    :data:`SPLINE_TOLERANCE`), the displacement the warps read at, and on the flow grid the
    texture-bias correction's and the smoothing's Gaussians. Not a strict support: the
    warping iterations repeat a level's window around a nearly converged flow, a coarser
    level only starts the finer one, and the median test, the cell windows and the
    gradient stencils reach a few pixels past a window whose Gaussian weights are 3e-4 at
    its edge; what they add beyond this reach stays below 1e-4 px
    (tests/pipeline/test_flow_roi.py measures it).

    Parameters
    ----------
    window, levels, factor, smoothing_sigma, adaptive_sigma
        The camera's :class:`~.params.FlowParams` (LK).
    presmooth : float
        Its pre-smoothing, resolved (pixels; a run resolves ``auto`` per camera).
    displacement : float
        Largest displacement (pixels) the flow's warps read at (the deflections').

    Returns
    -------
    int
    """
    if isinstance(presmooth, str):
        raise ValueError("flow_reach needs the pre-smoothing resolved (a run resolves 'auto' per camera)")
    f, half = int(factor), int(window) // 2
    reach = len(_gaussian_taps(float(presmooth))) // 2 if presmooth > 0 else 0
    reach += half * (2 ** int(levels) - 1) + _spline_reach() + int(math.ceil(displacement))
    reach += f * (_gaussian_blur_reach(window / 4.0 / f) + _gaussian_blur_reach(smoothing_sigma / f)
                  + _gaussian_blur_reach(adaptive_sigma / f))
    return int(reach)


def prediction_reach(amplitude: float, tolerance: float) -> int:
    """Cells beyond the last non-zero cell where :func:`~.refine.cells_to_pixels` of a
    field of peak ``amplitude`` stays below ``tolerance`` (the cubic B-spline's support
    of 2 cells and its prefilter's tail)."""
    if amplitude <= tolerance:
        return 0
    return 2 + int(math.ceil(math.log(tolerance / amplitude) / math.log(SPLINE_POLE)))


@dataclass(frozen=True)
class RefineRegion:
    """Where a camera-frame's refined flow is computed and where it is used.

    Attributes
    ----------
    crop : (x0, y0, x1, y1)
        Image pixels the refined flow is computed on (columns ``x0 .. x1 - 1``, rows
        ``y0 .. y1 - 1``); ``x0``, ``y0`` multiples of ``factor * 2**(levels - 1)``.
    cells : (r0, c0, r1, c1)
        Flow-grid cells (rows ``r0 .. r1 - 1``, columns ``c0 .. c1 - 1``) that take the
        crop's flow; the others keep the plain flow. Empty (``r1 <= r0``): the prediction is
        below the tolerance everywhere.
    """

    crop: tuple[int, int, int, int]
    cells: tuple[int, int, int, int]

    @property
    def empty(self) -> bool:
        r0, c0, r1, c1 = self.cells
        return r1 <= r0 or c1 <= c0

    def share(self, image_size: tuple[int, int]) -> float:
        """The crop's share of the image's pixels."""
        x0, y0, x1, y1 = self.crop
        return 0.0 if self.empty else (x1 - x0) * (y1 - y0) / float(image_size[0] * image_size[1])


def refine_region(prediction: np.ndarray, cell_factor: int, image_size: tuple[int, int], *, reach: int,
                  factor: int, levels: int, tolerance: float = 1e-5) -> RefineRegion:
    """The :class:`RefineRegion` of a camera-frame from its prediction.

    Parameters
    ----------
    prediction : ndarray, shape (rows, cols, 2)
        Predicted deflection (pixels) per ``cell_factor`` x ``cell_factor`` cell (the ray
        grid; NaN read as 0).
    cell_factor : int
        Pixels per prediction cell edge.
    image_size : (int, int)
        Width and height.
    reach : int
        :func:`flow_reach` of the camera's flow (the prediction's own displacement is added
        here).
    factor, levels : int
        The flow's ``factor`` and pyramid ``levels``.
    tolerance : float
        Prediction (pixels) taken as none: outside the region's cells the refined flow differs
        from the plain one by about this.

    Returns
    -------
    RefineRegion
        Its cells: every cell within the flow's reach of a pixel where the prediction
        exceeds ``tolerance``; its crop: those cells grown by the reach once more, aligned
        to ``factor * 2**(levels - 1)`` pixels and clipped to the image (at least 16 level
        pixels on each axis, as the pyramid needs).
    """
    W, H = image_size
    f = int(factor)
    rows, cols = H // f, W // f
    mag = np.hypot(*np.moveaxis(np.nan_to_num(np.asarray(prediction, np.float64)), -1, 0))
    amp = float(mag.max()) if mag.size else 0.0
    support = mag > 0.25 * tolerance  # a few tails below a quarter of it add up to less than it
    if amp <= tolerance or not support.any():
        return RefineRegion((0, 0, 0, 0), (0, 0, 0, 0))
    rr, cc = np.nonzero(support.any(axis=1))[0], np.nonzero(support.any(axis=0))[0]
    grow = prediction_reach(amp, tolerance) * cell_factor
    reach = int(reach) + int(math.ceil(amp))
    # pixels where |p| may exceed the tolerance, then every cell within the reach of them
    px = (cc[0] * cell_factor - grow, rr[0] * cell_factor - grow,
          (cc[-1] + 1) * cell_factor + grow, (rr[-1] + 1) * cell_factor + grow)
    cells = (max((px[1] - reach) // f, 0), max((px[0] - reach) // f, 0),
             min(-(-(px[3] + reach) // f), rows), min(-(-(px[2] + reach) // f), cols))
    a = f * 2 ** (int(levels) - 1)
    need = _MIN_LEVEL_EDGE * 2 ** (int(levels) - 1)
    x0, x1 = _aligned(cells[1] * f - reach, cells[3] * f + reach, a, W, need)
    y0, y1 = _aligned(cells[0] * f - reach, cells[2] * f + reach, a, H, need)
    return RefineRegion((x0, y0, x1, y1), tuple(int(v) for v in cells))


def _aligned(lo: int, hi: int, a: int, n: int, need: int) -> tuple[int, int]:
    """``[lo, hi)`` grown to a start on a multiple of ``a``, clipped to ``[0, n)``, at least
    ``need`` long where ``n`` allows."""
    lo = max(lo, 0) // a * a
    hi = min(max(hi, lo + need), n)
    while hi - lo < need and lo > 0:
        lo -= a
    return int(max(lo, 0)), int(hi)


def refined_deflection_in_region(reference: np.ndarray, frame: np.ndarray, prediction: np.ndarray,
                                 plain: np.ndarray, region: RefineRegion, params: FlowParams = FlowParams(), *,
                                 deflection: Callable | None = None, around=None) -> np.ndarray:
    """:func:`~.refine.refined_deflection` of one camera-frame computed on ``region`` alone.

    Parameters
    ----------
    reference : ndarray, shape (H, W)
        The camera's background (grey levels).
    frame : ndarray, shape (H, W)
    prediction : ndarray, shape (y1 - y0, x1 - x0, 2)
        Predicted deflection on the region's crop (:func:`~.refine.cells_to_pixels` of the
        prediction :func:`refine_region` was given, with ``box=region.crop``; pixels).
    plain : ndarray, shape (H // f, W // f, 2)
        The plain flow of the frame (what the refined flow is outside the region).
    region : RefineRegion
    params : FlowParams
    deflection : callable, optional
        As :func:`~.refine.refined_deflection`'s, called on the crop.
    around : PreparedReference, optional
        :func:`~.refine.predicted_reference` of the crop of ``reference`` and ``prediction``
        when already made (frames that share the prediction).

    Returns
    -------
    flow : ndarray, shape (H // f, W // f, 2), float32
        The crop's refined flow on the region's cells, ``plain`` elsewhere.
    """
    out = np.array(plain, np.float32, copy=True)
    if region.empty:
        return out
    x0, y0, x1, y1 = region.crop
    ref = np.asarray(reference, np.float32)[y0:y1, x0:x1]
    crop = refined_deflection(ref, np.asarray(frame)[y0:y1, x0:x1], prediction, params, deflection=deflection,
                              around=around)
    f = int(params.factor)
    r0, c0, r1, c1 = region.cells
    out[r0:r1, c0:c1] = crop[r0 - y0 // f:r1 - y0 // f, c0 - x0 // f:c1 - x0 // f]
    return out
