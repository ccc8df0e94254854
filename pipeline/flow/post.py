"""Post-processing of a flow field (paper sec. 4: "smoothed and filtered for outliers"):
the normalised median test with median replacement, Gaussian and structure-adaptive
smoothing, the area downsampling to the flow grid, and filling the cells without a
deflection from their nearest neighbour.
"""

from __future__ import annotations

import cv2
import numpy as np

from schlieren.pipeline.geometry import FlowGrid

__all__ = ["remove_outliers", "smooth_flow", "downsample_flow"]


def _median_test(u: np.ndarray, v: np.ndarray, threshold: float, epsilon: float):
    """Normalised median test on two (H, W) float32 components; returns (u, v, outliers)."""
    bad = None
    meds = []
    for comp in (u, v):
        m = cv2.medianBlur(comp, 3)
        res = cv2.absdiff(comp, m)
        rm = cv2.medianBlur(res, 3)
        b = res > np.float32(threshold) * (rm + np.float32(epsilon))
        bad = b if bad is None else (bad | b)
        meds.append(m)
    if bad.any():
        u = np.where(bad, meds[0], u)
        v = np.where(bad, meds[1], v)
    return u, v, bad


def remove_outliers(flow: np.ndarray, *, threshold: float = 3.0, epsilon: float = 0.01
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Normalised median test (after Westerweel & Scarano 2005) with median replacement.

    For each vector and component, the residual to the 3x3 median is divided by the 3x3
    median of those residuals plus ``epsilon``; vectors where either component exceeds
    ``threshold`` are replaced by the 3x3 median. (The 3x3 median includes the centre
    vector, unlike the original 8-neighbour test; it is computed with OpenCV's SIMD
    median filter. An isolated outlier cannot move a 9-point median, so it is caught the
    same way.)

    Parameters
    ----------
    flow : ndarray, shape (H, W, 2)
    threshold : float
        Normalised residual above which a vector is an outlier (2-3 typical).
    epsilon : float
        Expected noise level, pixels (keeps the test meaningful in uniform regions).

    Returns
    -------
    cleaned : ndarray, shape (H, W, 2), float32
    outliers : ndarray, shape (H, W), bool
    """
    flow = np.asarray(flow, dtype=np.float32)
    u, v, bad = _median_test(np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1]),
                             threshold, epsilon)
    return np.stack([u, v], axis=-1), bad


def smooth_flow(flow: np.ndarray, *, sigma: float) -> np.ndarray:
    """Gaussian smoothing of each flow component (sigma in pixels; 0 returns a copy)."""
    flow = np.asarray(flow, dtype=np.float32)
    if sigma <= 0:
        return flow.copy()
    return cv2.GaussianBlur(flow, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)


def downsample_flow(flow: np.ndarray, flow_grid: FlowGrid) -> np.ndarray:
    """Area-average full-resolution flow onto the flow grid (paper sec. 4).

    Cell ``(i, j)`` is the mean of image pixels ``[f*i : f*i+f, f*j : f*j+f]``; the
    remainder rows/columns beyond ``f * (H // f)`` are cropped. Values stay in pixels of
    the original image.

    Parameters
    ----------
    flow : ndarray, shape (H, W, 2)
    flow_grid : FlowGrid
        Its ``image_size`` must be ``(W, H)``.

    Returns
    -------
    ndarray, shape (H // f, W // f, 2), float32
    """
    flow = np.asarray(flow, dtype=np.float32)
    H, W = flow.shape[:2]
    if tuple(flow_grid.image_size) != (W, H):
        raise ValueError(f"flow is {W}x{H} but the flow grid is for {flow_grid.image_size}")
    f = flow_grid.factor
    rows, cols = flow_grid.shape
    crop = np.ascontiguousarray(flow[: rows * f, : cols * f])
    if f == 1:
        return crop.copy()
    # INTER_AREA with an integer factor is the exact block mean.
    return cv2.resize(crop, (cols, rows), interpolation=cv2.INTER_AREA)


def _block_mean(a: np.ndarray, f: int, shape: tuple[int, int]) -> np.ndarray:
    """Exact f x f block means of ``a`` on the flow grid ``shape`` = (rows, cols)
    (INTER_AREA with an integer factor)."""
    rows, cols = shape
    crop = a[: rows * f, : cols * f]
    return np.ascontiguousarray(crop) if f == 1 else cv2.resize(crop, (cols, rows),
                                                                interpolation=cv2.INTER_AREA)


def _smooth_cells(comps: list, sigma: float, adaptive_sigma: float, adaptive_threshold: float) -> np.ndarray:
    """The deflection stage's smoothing of (u, v) on the flow grid: each component
    Gaussian-smoothed with ``sigma`` (cells; 0 leaves it), then, with ``adaptive_sigma``
    (cells) > 0, :func:`_adaptive_smoothing`. Returns (rows, cols, 2) float32."""
    out = np.empty(comps[0].shape + (2,), np.float32)
    for k, comp in enumerate(comps):
        out[..., k] = comp if sigma <= 0 else cv2.GaussianBlur(
            comp, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    if adaptive_sigma > 0:
        out = _adaptive_smoothing(out, np.dstack(comps), adaptive_sigma, adaptive_threshold)
    return out


def _adaptive_smoothing(small: np.ndarray, flow: np.ndarray, sigma: float, threshold: float
                        ) -> np.ndarray:
    """Blend a strongly smoothed flow into ``small`` where both agree within the noise.

    Two-scale structure-adaptive smoothing (in the spirit of Lepski's scale selection):
    ``large`` = ``flow`` Gaussian-smoothed with ``sigma`` (grid cells). Where the flow is
    smooth, ``large`` differs from ``small`` only by noise; across structure it differs by
    the bias of the large scale. With ``D = |large - small|`` (vector norm) and the robust
    noise scale ``tau`` = lower quartile of ``D`` over the image (assumes at least a
    quarter of the image is flow-free or smooth; BOS images mostly are), the result is
    ``w large + (1 - w) small``, ``w = exp(-(D / (threshold tau))^2)``.
    """
    large = cv2.GaussianBlur(flow, (0, 0), sigmaX=sigma, sigmaY=sigma,
                             borderType=cv2.BORDER_REFLECT)
    diff = large - small
    d2 = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]
    tau2 = float(np.quantile(d2[::2, ::2], 0.25))  # lower quartile of D^2 = of D, squared
    if not np.isfinite(tau2) or tau2 <= 0:
        return small
    w = np.exp(d2 * np.float32(-1.0 / (threshold * threshold * tau2)))
    return (small + w[..., None] * diff).astype(np.float32)


def _nearest_fill(a: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """``a`` (h, w, ...) with the ``bad`` cells replaced by their nearest good cell."""
    if not bad.any() or bad.all():
        return a
    idx = _nearest_index(bad)
    return a[idx[0], idx[1]]


def _nearest_index(bad: np.ndarray) -> np.ndarray:
    """For each cell, the (row, column) of its nearest cell outside ``bad`` (Euclidean
    distance transform), shape (2, h, w)."""
    from scipy import ndimage

    return ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
