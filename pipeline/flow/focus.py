"""The pre-smoothing a background asks for, from its own reference (``flow.presmooth: auto``).

Paper sec. 4 smooths both images by the same Gaussian before the flow. The right width
depends on how sharp the background's image already is: an in-focus texture carries
energy up to the pixel's Nyquist frequency, which the linearised, interpolating flow
handles worst (and a rendered or real sensor partly aliases), and a small Gaussian helps;
an out-of-focus background has lost that band already, and the same Gaussian then only
removes the texture the flow measures with.

:func:`reference_blur` measures the image's softness in a way the texture's contrast does
not change: the fraction of the reference's gradient energy that a Gaussian of
:data:`PROBE_SIGMA` keeps (the sensor noise's share removed), expressed as the blur of
Gaussian-filtered white noise that keeps the same fraction (an exact lookup through the
same discrete filters). :func:`auto_presmooth` then tops the image's own blur up to the
total an in-focus background gets: ``sqrt(max(PRESMOOTH_IN_FOCUS^2 - excess^2, 0))``
with ``excess^2 = blur^2 - FOCUS_BLUR^2`` (none for a background at most as soft as
:data:`FOCUS_BLUR`). The constants were chosen on the realistic family's tune case and
are measured, with the estimators tried and rejected, in
benchmarks/results/realistic_focus.md.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .images import _as_image, _fill_nonfinite, _gaussian_taps
from .params import FlowParams

__all__ = ["AUTO", "AUTO_METHODS", "PRESMOOTH_IN_FOCUS", "FOCUS_BLUR", "PROBE_SIGMA", "reference_blur",
           "auto_presmooth", "resolve_presmooth"]

#: The ``flow.presmooth`` keyword for a per-camera width from the camera's reference.
AUTO = "auto"
#: The flow methods whose ``auto`` width follows the reference (measured with Lucas-Kanade);
#: the others keep :data:`PRESMOOTH_IN_FOCUS`.
AUTO_METHODS = ("lk",)
#: Pre-smoothing (Gaussian sigma, pixels) of an in-focus background.
PRESMOOTH_IN_FOCUS = 0.6
#: Blur (white-noise equivalent, pixels; :func:`reference_blur`) up to which a background
#: counts as in focus and keeps :data:`PRESMOOTH_IN_FOCUS`.
FOCUS_BLUR = 1.05
#: Gaussian sigma (pixels) whose kept share of the gradient energy measures the blur.
PROBE_SIGMA = 0.6
#: Pixels left out at each image edge (the filters' reach).
_EDGE = 8


def _gradient_energy(img: np.ndarray, sigma: float) -> float:
    """Mean squared Sobel gradient of ``img`` after a Gaussian of ``sigma`` (0: none)."""
    x = img
    if sigma > 0:
        k = _gaussian_taps(sigma)
        x = cv2.sepFilter2D(img, cv2.CV_64F, k, k, borderType=cv2.BORDER_REFLECT)
    gx = cv2.Sobel(x, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(x, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    np.multiply(gx, gx, out=gx)  # gx^2 + gy^2 in place (a frame is 1-2 million float64 pixels)
    np.multiply(gy, gy, out=gy)
    np.add(gx, gy, out=gx)
    return float(gx[_EDGE:-_EDGE, _EDGE:-_EDGE].mean())


def _noise_energy(sigma: float, blur: float = 0.0) -> float:
    """:func:`_gradient_energy` per unit variance of white noise blurred by ``blur`` then
    ``sigma``: the squared impulse response of the filter chain, summed (exact)."""
    n = 2 * (int(np.ceil(3.0 * (sigma + blur))) + 4) + 1
    d = np.zeros((n, n))
    d[n // 2, n // 2] = 1.0
    for s in (blur, sigma):
        if s > 0:
            k = _gaussian_taps(s).astype(np.float64)
            d = cv2.sepFilter2D(d, cv2.CV_64F, k, k, borderType=cv2.BORDER_CONSTANT)
    gx = cv2.Sobel(d, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_CONSTANT)
    gy = cv2.Sobel(d, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_CONSTANT)
    return float((gx * gx + gy * gy).sum())


@functools.lru_cache(maxsize=4)
def _blur_table(probe: float) -> tuple[np.ndarray, np.ndarray]:
    """(kept fractions, blurs): white noise blurred by ``blur`` keeps ``kept`` of its
    gradient energy under a Gaussian of ``probe`` (increasing in the blur)."""
    blurs = np.arange(0.0, 4.0001, 0.02)
    kept = np.array([_noise_energy(probe, b) / _noise_energy(0.0, b) for b in blurs])
    return kept, blurs


def reference_blur(reference: np.ndarray, *, noise: float = 0.0, n_frames: int = 1,
                   probe: float = PROBE_SIGMA) -> float:
    """How soft a background's image is, as the blur (pixels) of white noise as soft.

    Parameters
    ----------
    reference : ndarray, shape (H, W)
        The reference image, grey levels (the mean of ``n_frames`` frames).
    noise : float
        Sensor noise of one frame, grey levels (:func:`~schlieren.pipeline.rigcheck.sensor_noise`);
        its share of the gradient energy (``noise^2 / n_frames`` white) is removed first. 0:
        none removed.
    n_frames : int
        Frames averaged into ``reference``.
    probe : float
        The Gaussian (sigma, pixels) whose kept share of the gradient energy is measured.

    Returns
    -------
    blur : float
        The Gaussian sigma (pixels) that makes white noise keep the same share; 0 for an
        image as sharp as white noise, larger for softer ones; NaN for an image without
        texture.
    """
    img = _as_image(reference, "reference")
    if min(img.shape) <= 2 * _EDGE + 4:
        raise ValueError(f"reference {img.shape} too small to measure its blur")
    if not cv2.checkRange(img)[0]:  # NaN or inf: the finite pixels' mean instead
        fin = img[np.isfinite(img)]
        img = _fill_nonfinite(img, float(fin.mean()) if fin.size else 0.0)
    img = img.astype(np.float64)
    var = float(noise) ** 2 / max(int(n_frames), 1)
    e0 = _gradient_energy(img, 0.0) - var * _noise_energy(0.0)
    e1 = _gradient_energy(img, probe) - var * _noise_energy(probe)
    if not e0 > 0:
        return float("nan")
    kept, blurs = _blur_table(float(probe))
    return float(np.interp(min(max(e1 / e0, 0.0), 1.0), kept, blurs))


def auto_presmooth(reference: np.ndarray, *, noise: float = 0.0, n_frames: int = 1) -> float:
    """The pre-smoothing (Gaussian sigma, pixels) for a camera's reference.

    :data:`PRESMOOTH_IN_FOCUS` for a background at most :data:`FOCUS_BLUR` soft
    (:func:`reference_blur`); less for a softer one, so that its blur beyond an in-focus
    background's and the pre-smoothing add up (in quadrature) to :data:`PRESMOOTH_IN_FOCUS`;
    0 once the background alone is that soft. A textureless reference keeps
    :data:`PRESMOOTH_IN_FOCUS`.

    Parameters
    ----------
    reference : ndarray, shape (H, W)
    noise, n_frames : float, int
        As :func:`reference_blur`.
    """
    blur = reference_blur(reference, noise=noise, n_frames=n_frames)
    if not np.isfinite(blur) or blur <= FOCUS_BLUR:
        return PRESMOOTH_IN_FOCUS
    excess2 = blur * blur - FOCUS_BLUR * FOCUS_BLUR
    return float(np.sqrt(max(PRESMOOTH_IN_FOCUS * PRESMOOTH_IN_FOCUS - excess2, 0.0)))


def resolve_presmooth(presmooth, reference: np.ndarray, *, method: str = FlowParams.method, noise: float = 0.0,
                      n_frames: int = 1) -> float:
    """``presmooth`` as a number: itself, or for :data:`AUTO` :func:`auto_presmooth` of
    ``reference`` (``noise``, ``n_frames`` as there; noise 0 leaves its share in) with a
    method of :data:`AUTO_METHODS`, else :data:`PRESMOOTH_IN_FOCUS`."""
    if isinstance(presmooth, str):
        if presmooth != AUTO:
            raise ValueError(f"presmooth must be a number of pixels or {AUTO!r}, got {presmooth!r}")
        if method not in AUTO_METHODS:
            return PRESMOOTH_IN_FOCUS
        return auto_presmooth(reference, noise=noise, n_frames=n_frames)
    return float(presmooth)
