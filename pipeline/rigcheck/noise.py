"""Sensor noise and the flow noise it predicts, before any flow is computed.

Lucas-Kanade (paper sec. 4) solves, in each window, the normal equations
``T d = b`` with ``T = sum w g g^T`` (the structure tensor of the background's gradient
``g``, window weights ``w``) and ``b = sum w g e`` (``e`` the frame-reference difference).
Sensor noise of standard deviation ``s`` in ``e`` gives the deflection the covariance
``s^2 T^-1 M T^-1`` with ``M = sum w^2 g g^T`` (the Cramer-Rao bound of a window's shift for
white noise; :func:`~schlieren.pipeline.flow.lk._lk_ici` uses the same variance). So the
flow noise a run will have is known from the reference's texture and the sensor's noise:
:func:`predicted_flow_noise`. The noise itself is the temporal standard deviation of the
reference's frames (:func:`sensor_noise`), or, with one reference image, the robust
spread of the difference of capture frames where their rays miss the volume
(:func:`sensor_noise_from_pairs`).
"""

from __future__ import annotations

import cv2
import numpy as np

from schlieren.pipeline.flow.images import _gaussian_taps, _gradients
from schlieren.pipeline.flow.windows import _window_filter, _window_taps

__all__ = ["sensor_noise", "sensor_noise_from_pairs", "predicted_flow_noise", "MIN_NOISE_PIXELS"]

#: Samples :func:`sensor_noise_from_pairs` needs from the pixels it is given (a relative
#: standard error below 1 %).
MIN_NOISE_PIXELS = 10_000
#: :func:`sensor_noise_from_pairs` keeps differences within this many standard deviations.
CLIP_SIGMAS = 3.0
#: The standard deviation of a unit Gaussian truncated at +-CLIP_SIGMAS.
_TRUNCATED_STD = 0.98658


def _stack(frames) -> np.ndarray:
    a = np.asarray(frames, dtype=np.float64)
    if a.ndim != 3 or a.shape[0] < 2:
        raise ValueError(f"need a stack of at least 2 frames (frames, rows, columns), got shape {a.shape}")
    return a


def _without_flicker(a: np.ndarray) -> np.ndarray:
    """Each frame of ``a`` with its least-squares gain and offset against the mean frame
    removed, row by row (flicker, and the banding of a rolling shutter under mains light)."""
    m = a.mean(axis=0)
    mc = m - m.mean(axis=1, keepdims=True)
    mm = np.maximum((mc * mc).sum(axis=1, keepdims=True), 1e-30)
    out = np.empty_like(a)
    for k in range(len(a)):  # a few frames: each step is whole-image numpy
        ak = a[k] - a[k].mean(axis=1, keepdims=True)
        g = (ak * mc).sum(axis=1, keepdims=True) / mm
        out[k] = ak - g * mc + mc  # the frame on the mean frame's scale
    return out


def sensor_noise(frames, *, full_scale: float | None = None) -> float:
    """Sensor noise (grey levels) from frames of a static scene: the temporal standard
    deviation per pixel, its variance averaged over the pixels.

    Each frame's gain and offset against the frames' mean are removed first, row by row
    (lamp flicker and its row banding are not sensor noise; the two parameters a row's
    fit takes from its ``w`` pixels remove ``2 / w`` of the variance, which is put back),
    and pixels clipped at 0 or ``full_scale`` in any frame are left out (their spread is
    not the sensor's).

    Parameters
    ----------
    frames : array-like, shape (n, H, W)
        ``n >= 2`` frames of the same static view (e.g. a reference's frames).
    full_scale : float, optional
        The largest raw value (255, 65535); default: no clipping test at the top.
    """
    raw = np.asarray(frames)[:, ::2, ::2]  # every 4th pixel: plenty for one number, 4x faster
    a = _stack(raw)
    a = _without_flicker(a)
    var = a.var(axis=0, ddof=1) / (1.0 - 2.0 / max(a.shape[2], 3))
    ok = (raw > 0).all(axis=0)
    if full_scale is not None:
        ok &= (raw < full_scale).all(axis=0)
    return float(np.sqrt(var[ok].mean())) if ok.any() else float("nan")


def sensor_noise_from_pairs(frames, *, where: np.ndarray | None = None) -> float:
    """Sensor noise (grey levels) from frames of one view that may carry flow: the standard
    deviation of ``(f_k - f_k+1) / sqrt 2`` over every 4th pixel and every pair of
    successive frames (each frame's mean level removed), from the differences within
    :data:`CLIP_SIGMAS` standard deviations of the median (iterated from the median
    absolute deviation to a fixed point, and corrected for the truncation).

    Where the flow changes between frames the difference holds more than noise, so the
    pixels ``where`` (those whose rays miss the volume: no flow there) are used when they
    hold at least :data:`MIN_NOISE_PIXELS` samples; else every pixel, the clipping
    dropping the flow's largest differences. Not the median absolute deviation alone: the
    differences of integer samples are integers, and its value jumps between multiples of
    ``1.4826 / sqrt 2`` grey levels. Every 4th pixel is plenty: the standard deviation of
    ``n`` values has a relative standard error of ``1 / sqrt(2 n)``, 0.2 % for 10^5 of them.
    """
    a = _stack(np.asarray(frames)[:, ::2, ::2])
    a = a - a.mean(axis=(1, 2), keepdims=True)
    d = (a[1:] - a[:-1]) / np.sqrt(2.0)
    if where is not None:
        m = np.asarray(where, bool)[::2, ::2]
        if np.count_nonzero(m) * len(d) >= MIN_NOISE_PIXELS:
            d = d[:, m]
    d = d.ravel()
    d = d - np.median(d)
    s = 1.4826 * float(np.median(np.abs(d))) or float(d.std())  # a robust start
    for _ in range(8):  # the standard deviation of what lies within CLIP_SIGMAS of it, to a fixed point
        if s == 0:
            break
        new = float(d[np.abs(d) <= CLIP_SIGMAS * s].std()) / _TRUNCATED_STD
        if abs(new - s) <= 1e-3 * s:
            return new
        s = new
    return s


def predicted_flow_noise(reference: np.ndarray, *, noise: float, n_reference: int = 1, window: int = 9,
                         window_type: str = "gaussian", presmooth: float = 0.6,
                         regularisation: float = 1e-3) -> np.ndarray:
    """Per-pixel standard deviation (pixels, per component) of the LK deflection that
    sensor noise ``noise`` gives against this reference.

    ``sqrt(trace(C) / 2)`` with ``C = s^2 (T + lam)^-1 M (T + lam)^-1``: ``T`` and ``M``
    the structure tensor of the pre-smoothed reference filtered with the window weights
    and their squares (the run's ``FlowParams.window``, ``window_type``, ``presmooth``,
    ``regularisation``), ``s^2 = noise^2 (1 + 1 / n_reference)`` the variance of the
    frame-reference difference. Pre-smoothing by a kernel ``k`` correlates the noise:
    ``M`` is then built from the gradient smoothed once more by ``k`` (the noise term
    ``sum_q n_q (k * (w g))_q`` with ``k * (w g) ~ w (k * g)``, the window being smooth
    against the kernel).

    Parameters
    ----------
    reference : ndarray, shape (H, W)
        The reference (grey levels), averaged over ``n_reference`` frames.
    noise : float
        Sensor noise of one frame, grey levels (:func:`sensor_noise`).

    Returns
    -------
    sigma : ndarray, shape (H, W), float32
    """
    img = np.ascontiguousarray(reference, dtype=np.float32)
    k = _gaussian_taps(presmooth) if presmooth > 0 else None
    if k is not None:
        img = cv2.sepFilter2D(img, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT)
    gx, gy = _gradients(img)
    # the pre-smoothed noise is correlated: sum_p w g (k * n) = sum_q n (k * (w g)), and
    # k * (w g) ~ w (k * g) where the window is smooth against the kernel
    hx, hy = (gx, gy) if k is None else \
        (cv2.sepFilter2D(a, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT) for a in (gx, gy))
    taps = _window_taps(int(window), window_type)
    t2 = (taps * taps).astype(np.float32)
    txx, txy, tyy = (_window_filter(p, taps).astype(np.float64) for p in (gx * gx, gx * gy, gy * gy))
    mxx, mxy, myy = (_window_filter(p, t2).astype(np.float64) for p in (hx * hx, hx * hy, hy * hy))
    lam = regularisation * 0.5 * (txx.mean() + tyy.mean())
    txx, tyy = txx + lam, tyy + lam
    det = np.maximum(txx * tyy - txy * txy, 1e-30)
    ixx, ixy, iyy = tyy / det, -txy / det, txx / det  # (T + lam)^-1
    # C = I M I for symmetric 2x2 matrices: the diagonal entries
    cxx = ixx * (ixx * mxx + ixy * mxy) + ixy * (ixx * mxy + ixy * myy)
    cyy = ixy * (ixy * mxx + iyy * mxy) + iyy * (ixy * mxy + iyy * myy)
    s2 = float(noise) ** 2 * (1.0 + 1.0 / max(int(n_reference), 1))
    return np.sqrt(s2 * 0.5 * np.maximum(cxx + cyy, 0.0)).astype(np.float32)
