"""The LK integration window: its taps (box or Gaussian), the separable window filter,
the window as a line inside each f x f flow cell (the per-cell solve's form), and the RMS
width of the image averaging behind one flow cell (:func:`measurement_sigma`, which the
tomography's data term models).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .params import FlowParams, uses_cell_solve

__all__ = ["measurement_sigma"]


def _window_taps(window: int, window_type: str) -> np.ndarray:
    if window_type == "box":
        return np.full(window, 1.0 / window, np.float32)
    if window_type == "gaussian":
        x = np.arange(window) - (window - 1) / 2.0
        k = np.exp(-0.5 * (x / (window / 4.0)) ** 2)
        return (k / k.sum()).astype(np.float32)
    raise ValueError(f"window_type must be 'box' or 'gaussian', got {window_type!r}")


def _block_window_taps(window: int, window_type: str, f: int) -> np.ndarray:
    """LK window weights per f x f block: ``w~_k`` = mean of the window over the pixel
    offsets ``f k + r - (f - 1) / 2`` of block ``k`` (box: half-open extent window / 2);
    the constant part ``A`` of :func:`_block_window_linear_taps`."""
    return _block_window_linear_taps(window, window_type, f)[0]


@functools.lru_cache(maxsize=64)
def _block_window_linear_taps(window: int, window_type: str, f: int):
    """The LK window per f x f block as a line in the pixel's offset inside the block.

    For block offset ``k`` (blocks from the cell) and a pixel's offset ``rho`` from its
    block's centre (pixel offset ``f k + rho`` from the cell centre), the least-squares
    line over the block's ``f`` offsets: ``w(f k + rho) ~ A_k + B_k rho`` per axis.
    ``A`` alone is :func:`_block_window_taps` (the window constant over each block).
    Returns ``(A, B)``, both divided by ``sum(A)``; read-only, cached per window (a
    deflection task asks five times)."""
    half = (window - 1) // 2
    K = (half + f // 2 + f - 1) // f
    rho = np.arange(f) - (f - 1) / 2.0
    d = (np.arange(-K, K + 1)[:, None] * f + rho[None, :]).astype(np.float64)
    if window_type == "box":
        w = (np.abs(d) <= half + 1e-9).astype(np.float64)
    else:
        w = np.where(np.abs(d) <= half + 1e-9, np.exp(-0.5 * (d / (window / 4.0)) ** 2), 0.0)
    A = w.mean(axis=1)
    r2 = float(np.sum(rho ** 2))
    B = (w * rho[None, :]).sum(axis=1) / r2 if r2 > 0 else np.zeros_like(A)
    norm = A.sum()
    A, B = (A / norm).astype(np.float32), (B / norm).astype(np.float32)
    A.flags.writeable = B.flags.writeable = False
    return A, B


def _cell_window_sums(m: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The LK window sums on the cell grid from per-cell sums ``m[0]`` and first moments
    ``m[1]`` (x), ``m[2]`` (y), shape (3, rows, cols, k), with the window linear inside each
    cell (:func:`_block_window_linear_taps`: ``A (x) A`` on the sums, ``B (x) A`` on the
    x-moments, ``A (x) B`` on the y-moments)."""
    bt = cv2.BORDER_REFLECT
    return (cv2.sepFilter2D(m[0], cv2.CV_32F, A, A, borderType=bt)
            + cv2.sepFilter2D(m[1], cv2.CV_32F, B, A, borderType=bt)
            + cv2.sepFilter2D(m[2], cv2.CV_32F, A, B, borderType=bt))


def _window_filter(a: np.ndarray, taps: np.ndarray) -> np.ndarray:
    # separable FIR (OpenCV's SIMD path is faster than boxFilter for float32)
    return cv2.sepFilter2D(a, cv2.CV_32F, taps, taps, borderType=cv2.BORDER_REFLECT)


def measurement_sigma(params: FlowParams) -> float:
    """RMS width (pixels, per axis) of the image averaging behind one flow-grid cell.

    A deflection on the flow grid is not the deflection of the ray through the cell centre:
    it is the LK window's weighted mean of the per-pixel deflections (``window`` taps),
    smoothed (``smoothing_sigma``) and block-averaged to the grid (``factor``). Their
    variances add: ``var(window taps) + smoothing_sigma^2 + (factor^2 - 1) / 12``. The
    tomography models this averaging (``TomoParams.model_flow_window``). Methods other
    than LK get the smoothing and block mean only.

    With the per-cell solve (:func:`uses_cell_solve`) a cell's deflection is the window
    mean around the cell's centre (the window linear over each cell's pixels,
    :func:`_block_window_linear_taps`), with no block mean after it: the variance is that
    of the piecewise-linear window plus ``smoothing_sigma^2`` (sigma 5.52 px at a 25 px
    window and factor 3, against 5.58 per pixel).
    """
    var = float(params.smoothing_sigma) ** 2
    if params.method == "lk" and uses_cell_solve(params):
        f = int(params.factor)
        A, B = (t.astype(np.float64) for t in _block_window_linear_taps(int(params.window), params.window_type, f))
        rho = np.arange(f) - (f - 1) / 2.0
        k = np.arange(len(A)) - (len(A) - 1) / 2.0
        w = A[:, None] + B[:, None] * rho[None, :]  # per pixel: block k, offset rho
        d = f * k[:, None] + rho[None, :]
        return float(np.sqrt(var + np.sum(w * d * d) / np.sum(w)))
    var += (params.factor ** 2 - 1) / 12.0
    if params.method == "lk":
        taps = _window_taps(int(params.window), params.window_type).astype(np.float64)
        x = np.arange(len(taps)) - (len(taps) - 1) / 2.0
        var += float(np.sum(taps * x * x) / np.sum(taps))
    return float(np.sqrt(var))
