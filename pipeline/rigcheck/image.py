"""What one image tells about the camera: focus, exposure and hot or dead pixels.

* Focus (paper sec. 4: the cameras "must be focused on the background plane for the
  optical flow to work reliably"): the fraction of the background's texture energy in its
  finest scale, :func:`focus_energy`. Defocus removes the finest scale first.
* Exposure: the fractions of pixels clipped black or white, :func:`clipped_fractions`:
  a clipped pixel carries no deflection.
* Hot and dead pixels: single pixels far brighter (darker) than all their neighbours
  in the reference, :func:`hot_pixels`.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["focus_energy", "clipped_fractions", "hot_pixels"]


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def _noise_gain(sigma_fine: float, sigma_coarse: float) -> tuple[float, float]:
    """The fraction of white noise's variance passed by ``1 - G_fine`` and by ``1 - G_coarse``
    (measured on a white-noise image, so the result matches OpenCV's kernels exactly)."""
    rng = np.random.default_rng(0)
    n = rng.standard_normal((256, 256)).astype(np.float32)
    return (float(np.mean((n - _blur(n, sigma_fine)) ** 2) / np.mean(n ** 2)),
            float(np.mean((n - _blur(n, sigma_coarse)) ** 2) / np.mean(n ** 2)))


def focus_energy(image: np.ndarray, *, noise: float = 0.0, fine: float = 1.0, coarse: float = 4.0) -> float:
    """The fraction of the texture's energy at the finest scale, sensor noise removed.

    ``(E(I - G_fine I) - n_f) / (E(I - G_coarse I) - n_c)``: ``E`` the mean square, ``G_s``
    a Gaussian blur of sigma ``s`` pixels, ``n_f``, ``n_c`` the energy that white sensor
    noise ``noise`` alone puts in each band. Defocus lowers it (docs/check.md gives values
    on the benchmark family's background). Comparable between cameras of one rig (the
    same background), not between backgrounds.

    Parameters
    ----------
    image : ndarray, shape (H, W)
    noise : float
        Sensor noise of ``image``, grey levels (of one frame; the reference's averaged
        noise is smaller: pass ``noise / sqrt(n)``).
    """
    img = np.asarray(image, dtype=np.float32)
    gf, gc = _noise_gain(fine, coarse)
    ef = float(np.mean((img - _blur(img, fine)) ** 2)) - gf * noise ** 2
    ec = float(np.mean((img - _blur(img, coarse)) ** 2)) - gc * noise ** 2
    return max(ef, 0.0) / ec if ec > 0 else float("nan")


def clipped_fractions(image: np.ndarray, *, full_scale: float) -> tuple[float, float]:
    """Fractions of pixels at or below 0 and at or above ``full_scale`` (255, 65535)."""
    img = np.asarray(image)
    return float(np.mean(img <= 0)), float(np.mean(img >= full_scale))


def hot_pixels(image: np.ndarray, *, sigmas: float = 8.0, min_step: float = 20.0,
               full_scale: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Hot and dead pixels of a (reference) image: single pixels brighter (darker) than
    every one of their 8 neighbours by more than ``sigmas`` robust standard deviations of
    the image's Laplacian-like residual (the pixel minus its neighbours' mean), and by
    more than ``min_step`` grey levels. A band-limited background (the optics blur it) has
    no such isolated spikes; a sensor's hot pixel is one. A pixel clipped at
    ``full_scale`` (at 0) needs half that step only (and ``min_step``): a reference
    averaged over frames is clipped only where every frame was, and a hot pixel on a
    bright part of the texture stands out less.

    Returns
    -------
    hot, dead : ndarray, shape (n, 2), int
        ``(row, column)`` of each pixel.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0
    hi = cv2.dilate(img, ring, borderType=cv2.BORDER_REFLECT)
    lo = cv2.erode(img, ring, borderType=cv2.BORDER_REFLECT)
    mean8 = cv2.filter2D(img, cv2.CV_32F, ring.astype(np.float32) / 8.0, borderType=cv2.BORDER_REFLECT)
    r = (img - mean8)[::2, ::2]
    s = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    thr = max(sigmas * s, min_step)
    hot = img - hi > thr
    dead = lo - img > thr
    if full_scale is not None:
        low = max(sigmas * s / 2.0, min_step)
        hot |= (img >= full_scale) & (img - hi > low)
        dead |= (img <= 0) & (lo - img > low)
    return np.argwhere(hot), np.argwhere(dead)
