"""What the capture corrections of one camera need on every frame and that does not change
between its frames, prepared once (:func:`prepare_capture`; a worker keeps one per camera
beside the camera's prepared reference).

The static region, the defective pixels and the flow grid are fixed for a camera, so are
the registration's samples on every pyramid level (:func:`~.registration.sample_region`),
the flow's treatment of the defective pixels (their data weights, the cells they empty and
the nearest-cell fill of those: :func:`~schlieren.pipeline.flow.prepare_invalid`) and the
flow cells the remaining motion is fitted on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.flow import FlowParams, InvalidPixels, PreparedReference, prepare_invalid
from schlieren.pipeline.geometry import FlowGrid

from .defects import valid_pixels
from .params import CaptureParams
from .registration import SampleRegion, sample_region
from .static_region import static_cells

__all__ = ["CameraCapture", "prepare_capture"]


@dataclass(frozen=True, eq=False)
class CameraCapture:
    """One camera's fixed inputs of :func:`~.correction.corrected_deflection`.

    Attributes
    ----------
    bad : ndarray, shape (H, W), bool, or None
        Defective pixels (None: none).
    invalid : InvalidPixels or None
        ``bad`` prepared for the flow.
    region : SampleRegion
        The registration's samples.
    cells : ndarray, shape (rows, cols), bool
        Flow cells the remaining motion is fitted on (:func:`_fit_cells`).
    """

    bad: np.ndarray | None
    invalid: InvalidPixels | None
    region: SampleRegion
    cells: np.ndarray


def prepare_capture(reference: PreparedReference, flow: FlowParams = FlowParams(),
                    capture: CaptureParams = CaptureParams(), *, static: np.ndarray | None = None,
                    defects: np.ndarray | None = None) -> CameraCapture:
    """A camera's :class:`CameraCapture` (arguments as those of
    :func:`~.correction.corrected_deflection`; ``reference`` prepared with ``flow``'s
    pre-smoothing and levels)."""
    bad = None if defects is None or not np.any(defects) else np.asarray(defects) != 0
    region = sample_region(reference, static=static, valid=valid_pixels(defects),
                           min_static_fraction=capture.min_static_fraction)
    H, W = reference.shape
    return CameraCapture(bad, prepare_invalid(reference, bad, flow), region,
                         _fit_cells((H, W), static, flow.factor, flow.window, region.fallback))


def _fit_cells(shape: tuple[int, int], static: np.ndarray | None, factor: int, window: int,
               fallback: bool) -> np.ndarray:
    """Flow cells to measure the remaining motion on: the static ones, or every cell when
    the static region is too small (the fit's weights then drop the plume's), every
    second one along each axis or, with LK windows wider than four cells, one every half
    window (neighbouring cells' windows overlap: their flows' noise is shared, so the
    cells left out add little information)."""
    H, W = shape
    h, w = FlowGrid((W, H), factor).shape
    cells = np.ones((h, w), bool) if static is None or fallback else static_cells(static, factor)
    stride = max(2, int(window) // (2 * int(factor)))
    thin = np.zeros_like(cells)
    thin[::stride, ::stride] = True
    return cells & thin
