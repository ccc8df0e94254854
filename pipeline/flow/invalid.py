"""Pixels the flow must not use, and the flow-grid cells they leave without support:
the per-frame maps (:func:`_fill_bad_cells`) and a camera's known-unusable pixels
prepared once for all its frames (:class:`InvalidPixels`, :func:`prepare_invalid`).

A pixel that cannot carry a deflection (clipped, textureless, a defective sensor pixel)
gets zero weight in the Lucas-Kanade and Horn-Schunck data terms (paper sec. 4); a cell
whose own pixels or whose LK window are mostly such pixels has no measurement of its own.
A camera's defective pixels are the same in every frame, so their weights, their empty
cells and the nearest-cell fill of those cells are computed once per camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.geometry import FlowGrid

from .params import FlowParams
from .post import _block_mean, _nearest_fill, _nearest_index
from .reference import PreparedReference, _weight_pyramid
from .windows import _window_filter, _window_taps

__all__ = ["InvalidPixels", "prepare_invalid"]


@dataclass(frozen=True, eq=False)
class InvalidPixels:
    """A camera's known-unusable pixels with what the flow derives from them alone.

    Build it with :func:`prepare_invalid`; pass it as ``invalid`` to
    :func:`~.stage.deflection_stage` (the same results as the boolean map, without
    recomputing these on every frame). Used as they are only when the frame and the
    reference have no invalid pixels of their own (``invalid_check``); otherwise the map is
    combined with theirs as a boolean ``invalid`` is.

    Attributes
    ----------
    mask : ndarray, shape (H, W), bool
        The unusable pixels.
    valid : ndarray, shape (H, W), bool
        ``~mask``.
    weights : list of ndarray
        The LK/HS data weights per pyramid level (:func:`~.reference._weight_pyramid`).
    bad_cells : ndarray, shape (rows, cols), bool
        Flow-grid cells without support (:func:`_bad_cells`).
    fill_index : tuple of four ndarray, or None
        The rows and columns of the cells without support, and those of their nearest
        supported cells (None: no cell lacks support, or none has it).
    """

    mask: np.ndarray
    valid: np.ndarray
    weights: list
    bad_cells: np.ndarray
    fill_index: tuple | None

    def fill(self, comps: list):
        """:func:`_fill_bad_cells` of these pixels alone: ``(comps with the bad cells
        filled, None)``, or ``(None, None)`` when no cell has support."""
        if self.bad_cells.all():
            return None, None
        if self.fill_index is None:
            return comps, None
        i, j, si, sj = self.fill_index
        out = [np.array(c, copy=True) for c in comps]
        for o, c in zip(out, comps):
            o[i, j] = c[si, sj]
        return out, None


def prepare_invalid(reference: PreparedReference, invalid: np.ndarray | None,
                    params: FlowParams = FlowParams()) -> InvalidPixels | None:
    """A camera's known-unusable pixels (defective sensor pixels) prepared for
    :func:`~.stage.deflection_stage` with ``params`` and ``reference``'s pyramid; None
    when ``invalid`` holds none."""
    if invalid is None or not np.any(invalid):
        return None
    mask = np.asarray(invalid, bool)
    valid = ~mask
    H, W = mask.shape
    shape = FlowGrid((W, H), params.factor).shape
    bad = _bad_cells(valid, params.window, params.window_type, params.factor, shape)
    index = None
    if bad.any() and not bad.all():
        near = _nearest_index(bad)
        i, j = np.nonzero(bad)
        index = (i, j, near[0][i, j], near[1][i, j])
    return InvalidPixels(mask, valid, _weight_pyramid(valid, len(reference.pyramid)), bad, index)


def _fill_bad_cells(comps: list, valid: np.ndarray, checked: np.ndarray | None, params: FlowParams):
    """The flow-grid cells that ``valid`` leaves without support (:func:`_bad_cells`) filled
    from their nearest good cell, and the cells to return as NaN: those of ``checked`` (the
    ``invalid_check`` map; the cells that only the caller's ``invalid`` pixels emptied keep
    their filled value). ``(None, None)`` when no cell has support."""
    shape = comps[0].shape
    bad = _bad_cells(valid, params.window, params.window_type, params.factor, shape)
    if bad.all():
        return None, None
    filled = _nearest_fill(np.dstack(comps), bad)
    comps = [np.ascontiguousarray(filled[..., 0]), np.ascontiguousarray(filled[..., 1])]
    if checked is not valid:
        bad = _bad_cells(checked, params.window, params.window_type, params.factor, shape) \
            if checked is not None else None
    return comps, bad


def _bad_cells(valid: np.ndarray, window: int, window_type: str, f: int, shape: tuple[int, int]) -> np.ndarray:
    """Flow-grid cells where invalid pixels hold half or more of the cell or of the LK
    window weight around its pixels."""
    # a cell is kept if most of the window weight around its pixels lies on valid ones
    w0 = _weight_pyramid(valid, 1)[0]
    support = _block_mean(_window_filter(w0, _window_taps(window, window_type)), f, shape)
    return (_block_mean(w0, f, shape) < 0.5) | (support < 0.5)
