"""Exact cubic B-spline warping of images and fields, and flow prolongation between
pyramid levels; the LK and HS solvers and :mod:`schlieren.pipeline.sync` warp with them.

Why a custom warp: ``cv2.remap`` quantises sub-pixel positions to 1/32 pixel, which puts a
~0.01-0.02 px floor into any iterative flow that warps with it; BOS deflections are 0.05-1 px
and need better. The warps here use exact (float) cubic B-spline interpolation (with its
interpolating prefilter) in numba kernels, on images pre-smoothed with a Gaussian so that
the interpolant is accurate (pre-smoothing both images by the same kernel leaves a smooth
displacement field unchanged).
"""

from __future__ import annotations

import cv2
import numpy as np

from ._kernels import _PAD, _prolong_kernel, _warp_kernel, _warp_rows_kernel
from .images import _as_image

__all__ = ["prolong_flow", "spline_coefficients", "warp_coefficients", "warp_coefficient_rows", "warp_image"]


def prolong_flow(u: np.ndarray, v: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Prolong a coarse pyramid level's flow (or motion) to the next finer level (values doubled).

    ``cv2.pyrDown`` centres coarse pixel ``i`` on fine pixel ``2 i``, so fine pixel ``x``
    reads the coarse flow at ``x / 2`` (an affine map; bilinear, edges replicated).
    """
    H, W = shape
    if u.dtype == np.float32 and v.dtype == np.float32 and u.ndim == 2 and u.shape == v.shape:
        # float32 (the flow): one pass of :func:`_prolong_kernel`, the same numbers as below
        uu = np.empty((H, W), np.float32)
        vv = np.empty((H, W), np.float32)
        _prolong_kernel(np.ascontiguousarray(u), np.ascontiguousarray(v), uu, vv)
        return uu, vv
    M = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]], np.float64)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    uu = cv2.warpAffine(u, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    vv = cv2.warpAffine(v, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    return uu * np.float32(2.0), vv * np.float32(2.0)


_BSPLINE_POLE = np.sqrt(3.0) - 2.0
_PREFILTER_TAPS = (np.sqrt(3.0) * _BSPLINE_POLE ** np.abs(np.arange(-9, 10))).astype(np.float32)


def _spline_coefficients(img: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients of an image (interpolating prefilter), padded by 2.

    The exact prefilter is the inverse of the ``[1, 4, 1] / 6`` filter, whose impulse
    response is ``sqrt(3) (sqrt(3) - 2)^|k|``; truncated at |k| = 9 its error is below
    1e-5 relative. Applied separably with OpenCV (mirror borders).
    """
    k = _PREFILTER_TAPS
    coef = cv2.sepFilter2D(img, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT_101)
    return cv2.copyMakeBorder(coef, _PAD, _PAD, _PAD, _PAD, cv2.BORDER_REFLECT_101)


def spline_coefficients(image: np.ndarray) -> np.ndarray:
    """Padded cubic B-spline coefficients of a 2-D image, for :func:`warp_coefficients`
    (prefilter once, warp many times)."""
    return _spline_coefficients(_as_image(image, "image"))


def warp_coefficients(coefficients: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """:func:`warp_image` from precomputed :func:`spline_coefficients`.

    Parameters
    ----------
    coefficients : ndarray, shape (H + 4, W + 4)
    flow : ndarray, shape (H, W, 2)

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    flow = np.asarray(flow, dtype=np.float32)
    H, W = coefficients.shape[0] - 2 * _PAD, coefficients.shape[1] - 2 * _PAD
    if flow.shape != (H, W, 2):
        raise ValueError(f"flow shape {flow.shape} does not match the image ({H}, {W})")
    out = np.empty((H, W), np.float32)
    _warp_kernel(coefficients, np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1]), out)
    return out


def warp_coefficient_rows(coefficients: np.ndarray, rows: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """:func:`warp_coefficients` evaluated on the image rows ``rows`` only.

    Parameters
    ----------
    coefficients : ndarray, shape (H + 4, W + 4)
    rows : ndarray of int, shape (R,)
    flow : ndarray, shape (R, W, 2)
        Displacements of those rows.

    Returns
    -------
    ndarray, shape (R, W), float32: the same values as ``warp_coefficients(...)[rows]``.
    """
    flow = np.asarray(flow, dtype=np.float32)
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    H, W = coefficients.shape[0] - 2 * _PAD, coefficients.shape[1] - 2 * _PAD
    if flow.shape != (len(rows), W, 2):
        raise ValueError(f"flow shape {flow.shape} does not match {len(rows)} rows of width {W}")
    if len(rows) and (rows.min() < 0 or rows.max() >= H):
        raise ValueError(f"rows must lie in [0, {H})")
    out = np.empty((len(rows), W), np.float32)
    _warp_rows_kernel(coefficients, rows, np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1]),
                      out)
    return out


def warp_image(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Sample ``image`` at ``p + flow(p)`` with exact (unquantised) cubic B-spline interpolation.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey image.
    flow : ndarray, shape (H, W, 2)
        Displacement (u, v) in pixels.

    Returns
    -------
    warped : ndarray, shape (H, W), float32
        ``warped(p) = image(p + flow(p))`` (positions clamped to the image).
    """
    img = _as_image(image, "image")
    flow = np.asarray(flow, dtype=np.float32)
    if flow.shape != img.shape + (2,):
        raise ValueError(f"flow shape {flow.shape} does not match image {img.shape}")
    out = np.empty(img.shape, np.float32)
    _warp_kernel(_spline_coefficients(img), np.ascontiguousarray(flow[..., 0]),
                 np.ascontiguousarray(flow[..., 1]), out)
    return out
