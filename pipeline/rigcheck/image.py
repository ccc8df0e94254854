"""What one image tells about the camera: focus and exposure.

* Focus (paper sec. 4: the cameras "must be focused on the background plane for the
  optical flow to work reliably"): the fraction of the background's texture energy in its
  finest scale, :func:`focus_energy`. Defocus removes the finest scale first.
* Exposure: the fractions of pixels clipped black or white, :func:`clipped_fractions`:
  a clipped pixel carries no deflection.

Hot, dead and stuck pixels are the run's own test
(:func:`schlieren.pipeline.capture.find_defective_pixels`).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

__all__ = ["focus_energy", "clipped_fractions"]


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


@functools.lru_cache(maxsize=8)
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
