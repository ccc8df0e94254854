"""Image conditioning shared by the flow methods: the grey-image check, normalisation
(mean, 1/std of the finite pixels), filling non-finite pixels, Gaussian pre-smoothing
(paper sec. 4: both images by the same kernel), the image pyramid and Scharr gradients.
"""

from __future__ import annotations

import cv2
import numpy as np


def _as_image(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey image (rows, columns), got shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _normalisation(img: np.ndarray) -> tuple[float, float]:
    """Mean and 1/std of the finite pixels (every 4th row and column)."""
    sub = img[::4, ::4]
    fin = sub[np.isfinite(sub)]
    if fin.size == 0:
        return 0.0, 1.0
    std = float(fin.std())
    return float(fin.mean()), (1.0 / std if std > 0 else 1.0)


def _fill_nonfinite(img: np.ndarray, value: float) -> np.ndarray:
    """``img`` with NaN / inf pixels set to ``value`` (the same array when all are finite)."""
    bad = ~np.isfinite(img)
    if bad.any():
        img = np.where(bad, np.float32(value), img)
    return img


def nonfinite_cells(field) -> np.ndarray:
    """True where any component (last axis) of ``field`` is NaN or infinite: the same as
    ``~np.isfinite(field).all(axis=-1)``, one component at a time (NumPy reduces over a
    short trailing axis element by element, some 30x slower on a flow field)."""
    field = np.asarray(field)
    ok = np.isfinite(field[..., 0])
    for k in range(1, field.shape[-1]):
        ok &= np.isfinite(field[..., k])
    return ~ok


def _gaussian_taps(sigma: float) -> np.ndarray:
    r = max(1, int(np.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def _standardise(img: np.ndarray, mean: float, scale: float, presmooth: float) -> np.ndarray:
    """``(img - mean) * scale``, Gaussian pre-smoothed with ``presmooth`` (one OpenCV pass)."""
    if presmooth > 0:
        k = _gaussian_taps(presmooth)
        return cv2.sepFilter2D(img, cv2.CV_32F, k * np.float32(scale), k,
                               delta=-mean * scale, borderType=cv2.BORDER_REFLECT)
    return (img - np.float32(mean)) * np.float32(scale)


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    pyr = [img]
    for _ in range(levels - 1):
        if min(pyr[-1].shape) < 16:
            break
        pyr.append(cv2.pyrDown(pyr[-1], borderType=cv2.BORDER_REFLECT))
    return pyr


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Scharr derivative (rotationally accurate 3x3), scaled to units of grey / pixel.
    gx = cv2.Scharr(img, cv2.CV_32F, 1, 0, scale=1.0 / 32.0, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Scharr(img, cv2.CV_32F, 0, 1, scale=1.0 / 32.0, borderType=cv2.BORDER_REFLECT)
    return gx, gy
