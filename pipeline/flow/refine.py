"""Re-projection refinement of the flow: the deflection measured around a prediction.

Lucas-Kanade returns the texture-weighted mean of the deflection over its window
(:func:`~.lk._lk_level`), not its value at the window's centre: where the deflection
varies inside the window (a plume's edges and fine structure), the flow is biased by
``(W - I) d``, and the bias is the same in every frame that sees the same structure, so
averaging in time does not remove it. Given a prediction ``p`` of the deflection (the
tomography's reconstruction projected into the camera, :func:`~schlieren.pipeline.residuals.predict_flows`),
the reference is resampled at ``q + p(q)`` (exact cubic B-splines,
:func:`~.splines.warp_image`), the flow then measures only the residual ``d - p``, and the
prediction's cell means are added back: the result is ``p + W (d - p)``, whose bias
``(W - I)(d - p)`` is that of the residual alone. The better the prediction resolves the
deflection's variation inside the window, the smaller the bias; the flow's noise is that
of the plain flow.

The kernels: :func:`cells_to_pixels` (a flow-grid field to every image pixel) and
:func:`refined_deflection` (one camera-frame's refined flow); :class:`RefineParams` says how
many times a run's tomography task re-measures its frame's flows around its own solution
and solves again (beyond the paper; off by default). Where the prediction is zero the refined
flow is the plain one: :mod:`.roi` measures it only where the prediction reaches. Measurements:
benchmarks/results/flow_refinement.md.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy import ndimage

from schlieren.pipeline.geometry import FlowGrid
from schlieren.pipeline.params import param, parameters

from .params import FlowParams
from .post import _block_mean
from .reference import PreparedReference, prepare_reference
from .splines import warp_image
from .stage import deflection_stage

__all__ = ["RefineParams", "cells_to_pixels", "predicted_reference", "refined_deflection"]

_PAD = 8  # cells added beyond each edge: the B-spline prefilter's edge error decays as 0.27 per cell
_SCIPY_PAD = 12  # edge padding scipy's map_coordinates(mode="nearest") gives its prefilter


@parameters
class RefineParams:
    """Re-projection refinement of the flows (beyond the paper): the flow re-measured around
    the tomography's own prediction."""

    passes: int = param(
        0, unit="1", ge=0, le=4,
        help="Times each frame's flows are measured again around the deflections its solution predicts "
             "(flow of the residual, prediction added back) and solved again (with `refine.window_scale` of the "
             "flow-window model); "
             "each pass costs about one deflection stage and one solve per frame. 0: the paper's single flow.",
        see="benchmarks/results/flow_refinement.md")
    window_scale: float = param(
        0.0, unit="1", ge=0, le=2,
        help="Factor on the modelled flow window (the stored `flow_window`) in the solves of the refined flows: "
             "a refined flow is a window mean of the residual only, so part of the window model still fits; "
             "0 solves them without it.",
        see="benchmarks/results/tomography_gap.md")
    crop: bool = param(
        True,
        help="Measure each refined flow only on the crop of the image where the prediction, grown by the flow's "
             "reach, exceeds 1e-5 px, keeping the stored plain flow elsewhere (the whole image's refined flow "
             "differs from it there by under 1e-4 px beyond its resampling's own floor); false: the whole image.",
        see="benchmarks/results/refine_roi.md")


def cells_to_pixels(cells: np.ndarray, factor: int, size: tuple[int, int], *,
                    box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """A field given per flow cell, cubic-interpolated from the cells' centres to every pixel.

    Parameters
    ----------
    cells : ndarray, shape (rows, cols, 2)
        Values at the centres of ``factor`` x ``factor`` pixel cells (``FlowGrid`` layout:
        cell ``i`` covers pixels ``factor i .. factor i + factor - 1``). NaN is read as 0.
    factor : int
        Pixels per cell edge.
    size : (int, int)
        Image width and height.
    box : (x0, y0, x1, y1), optional
        Only these pixels (columns ``x0 .. x1 - 1``, rows ``y0 .. y1 - 1``): the same values
        as the full image's there.

    Returns
    -------
    ndarray, shape (H, W, 2) or (y1 - y0, x1 - x0, 2), float32
        Cubic B-spline interpolation of the cell values, the cells continued beyond the
        edges by point reflection about the edge cells (exact on a linear field).
    """
    W, H = size
    x0, y0, x1, y1 = (0, 0, W, H) if box is None else box
    a = np.nan_to_num(np.asarray(cells, np.float64))
    k = min(_PAD, a.shape[0] - 1, a.shape[1] - 1)
    # point reflection about the edge cells: a linear field stays linear across the edges
    for axis in (0, 1):
        n = a.shape[axis]
        lo = 2 * np.take(a, [0], axis) - np.flip(np.take(a, range(1, k + 1), axis), axis)
        hi = 2 * np.take(a, [n - 1], axis) - np.flip(np.take(a, range(n - 1 - k, n - 1), axis), axis)
        a = np.concatenate([lo, a, hi], axis=axis)
    ys = (np.arange(y0, y1) - (factor - 1) / 2.0) / factor + k
    xs = (np.arange(x0, x1) - (factor - 1) / 2.0) / factor + k
    # cubic B-splines with their interpolating prefilter (OpenCV's cubic convolution is not
    # exact even on a linear field), as scipy's map_coordinates(order=3, mode="nearest")
    # makes them (the cells padded by their edge values before the prefilter), evaluated on
    # the pixels' tensor grid one axis at a time: 4 taps per axis
    rows, cols = _cubic_taps(ys + _SCIPY_PAD), _cubic_taps(xs + _SCIPY_PAD)
    out = np.empty((len(ys), len(xs), 2), np.float32)
    for i in range(2):
        coef = ndimage.spline_filter(np.pad(a[..., i], _SCIPY_PAD, mode="edge"), order=3, mode="nearest",
                                     output=np.float64)
        along = sum(w[:, None] * coef[j] for j, w in zip(*rows))
        out[..., i] = sum(w[None, :] * along[:, j] for j, w in zip(*cols))
    return out


def _cubic_taps(pos: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The four samples and cubic B-spline weights of each position: ``value(pos) =
    sum_t w_t coef[j_t]``."""
    j = np.floor(pos).astype(np.intp)
    t = pos - j
    t2, t3 = t * t, t * t * t
    weights = [(1.0 - t) ** 3 / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
               t3 / 6.0]
    return [j - 1, j, j + 1, j + 2], weights


def predicted_reference(reference, prediction: np.ndarray, *, presmooth: float, levels: int):
    """The reference resampled at ``q + p(q)`` (exact cubic B-splines) and prepared for the
    flow, what :func:`refined_deflection` measures a frame against: the same for every frame
    that shares the prediction, so made once for them.

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        The camera's background (grey levels; non-finite pixels read as its mean).
    prediction : ndarray, shape (H, W, 2)
        Predicted deflection at every pixel (pixels).
    presmooth : float
        The flow's pre-smoothing (pixels; a run's, resolved per camera).
    levels : int
        The flow's pyramid levels.

    Returns
    -------
    PreparedReference
    """
    return prepare_reference(_resampled(reference, prediction), presmooth=presmooth, levels=levels)


def _resampled(reference, prediction: np.ndarray) -> np.ndarray:
    """``reference`` sampled at ``q + prediction(q)`` (non-finite pixels read as its mean)."""
    img = reference.image if isinstance(reference, PreparedReference) else np.asarray(reference, np.float32)
    H, W = img.shape
    pred = np.asarray(prediction, np.float32)
    if pred.shape != (H, W, 2):
        raise ValueError(f"prediction shape {pred.shape} does not match the image ({H}, {W})")
    fill = float(np.nanmean(img))
    return warp_image(np.where(np.isfinite(img), img, np.float32(fill)).astype(np.float32), pred)


def refined_deflection(reference, frame: np.ndarray, prediction: np.ndarray, params: FlowParams = FlowParams(), *,
                       deflection: Callable | None = None, around=None, **kwargs) -> np.ndarray:
    """One camera-frame's deflection measured around a prediction of it.

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        The camera's background (grey levels).
    frame : ndarray, shape (H, W)
    prediction : ndarray, shape (H, W, 2)
        Predicted deflection at every pixel (pixels, ``[..., 0]`` = u), e.g.
        :func:`cells_to_pixels` of the tomography's predicted flows.
    params : FlowParams
    deflection : callable, optional
        ``deflection(reference, frame, params, **kwargs) -> (H // f, W // f, 2)``, the flow
        of the residual against the warped reference (:func:`predicted_reference`);
        default :func:`~.stage.deflection_stage` (a run passes its capture-corrected flow).
    around : PreparedReference, optional
        :func:`predicted_reference` of ``reference`` and ``prediction`` when already made
        (frames that share the prediction); without it the resampled reference is prepared
        by ``deflection``.

    Returns
    -------
    flow : ndarray, shape (H // f, W // f, 2), float32
        The residual's flow plus the prediction's mean over each flow cell (pixels).
    """
    moved = _resampled(reference, prediction) if around is None else around
    H, W = np.shape(frame)[:2]
    pred = np.asarray(prediction, np.float32)
    run = deflection if deflection is not None else deflection_stage
    residual = np.asarray(run(moved, frame, params, **kwargs), np.float32)
    rows, cols = FlowGrid((W, H), params.factor).shape
    back = np.stack([_block_mean(np.ascontiguousarray(pred[..., i]), params.factor, (rows, cols))
                     for i in range(2)], axis=-1)
    return residual + back
