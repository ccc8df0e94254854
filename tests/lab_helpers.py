"""Measurements the lab-effect tests judge the renders by, independent of the renderer."""

import numpy as np


def phase_shift(reference: np.ndarray, frame: np.ndarray, *, kmax: float = 0.12) -> np.ndarray:
    """Sub-pixel translation ``s`` (u, v pixels) with ``frame(x) ~ reference(x - s)``, by phase correlation.

    The normalised cross-power spectrum of a pure translation is ``exp(-2 pi i k . s)``;
    its phase is fitted by weighted least squares over the frequencies below ``kmax``
    cycles per pixel (no peak interpolation, so no sub-pixel bias). Both images are
    Hann-windowed; shifts must stay well below ``1 / (2 kmax)`` pixels (no phase wrapping).
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(frame, dtype=np.float64)
    H, W = a.shape
    win = np.outer(np.hanning(H), np.hanning(W))
    A = np.fft.fft2((a - a.mean()) * win)
    B = np.fft.fft2((b - b.mean()) * win)
    R = B * np.conj(A)
    ky = np.fft.fftfreq(H)[:, None] * np.ones((1, W))
    kx = np.fft.fftfreq(W)[None, :] * np.ones((H, 1))
    sel = (np.hypot(kx, ky) < kmax) & (np.hypot(kx, ky) > 0)
    w = np.abs(R[sel])
    phi = np.angle(R[sel])
    M = -2.0 * np.pi * np.stack([kx[sel], ky[sel]], axis=-1)
    sw = np.sqrt(w)[:, None]
    s, *_ = np.linalg.lstsq(M * sw, phi * sw[:, 0], rcond=None)
    return s


def radial_power(image: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Mean power spectrum (Hann-windowed) in the rings ``edges[i] <= |k| < edges[i+1]`` (cycles/pixel)."""
    a = np.asarray(image, dtype=np.float64)
    H, W = a.shape
    win = np.outer(np.hanning(H), np.hanning(W))
    P = np.abs(np.fft.fft2((a - a.mean()) * win)) ** 2
    k = np.hypot(np.fft.fftfreq(H)[:, None], np.fft.fftfreq(W)[None, :])
    return np.array([P[(k >= lo) & (k < hi)].mean() for lo, hi in zip(edges[:-1], edges[1:])])
