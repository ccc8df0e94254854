"""Hot, dead and stuck sensor pixels, found from a camera's frames.

A defective pixel does not follow the background: a hot or stuck pixel keeps its value
whatever the deflection, so Lucas-Kanade's window around it sees a strong feature that
does not move and pulls the flow there towards zero (paper sec. 4 assumes every pixel
samples the displaced background). The flow gives such pixels no weight
(``invalid`` of :func:`~schlieren.pipeline.flow.deflection_stage`), like clipped or
textureless ones.

Two tests, over the reference frames and a sample of the capture frames:

* **hot / dead**: the pixel departs from the quadratic prediction of its 8 neighbours
  (``(2 (N + S + E + W) - (NE + NW + SE + SW)) / 4``, exact for any quadratic surface,
  so a smooth, defocused or band-limited background predicts itself well) by more than
  ``threshold`` robust standard deviations of that residual over the image, with the
  same sign in every frame, and is the largest departure (either sign) of its 3 x 3
  neighbourhood in every frame (its neighbours' residuals carry half of its own, with
  the other sign);
* **stuck**: its standard deviation over the frames is below ``stuck_ratio`` times the
  smallest of its 8 neighbours', which do vary (each at least by the sensor noise,
  whatever the motion or the lighting add: a pixel on a texture extremum barely follows
  a sub-pixel motion while its neighbours on the slopes do, so a neighbourhood median
  would flag it), and it is not at the frame's clipping level in half of the frames or
  more (a pixel of a saturated or black patch of the background also stays constant, but
  so do its neighbours, or it carries no texture the flow could use anyway), and a normal
  pixel could not have kept its values that close together by chance: few frames of a
  quantised sensor repeat one value often (at 1.5 grey levels of noise, 9 frames all equal
  about once in 10^5 pixels), so the spread over the frames is compared with the chance
  that a pixel varying like its least varying neighbour keeps its ``n`` values within the
  range it shows (:func:`range_chance`), and a pixel is flagged only when that chance,
  times the pixels of the image, is below :data:`STUCK_FALSE_ALARMS`. The false alarms
  per image are so bounded whatever the number of frames; with too few frames for the
  noise the test flags nothing (:func:`stuck_decidable` says so beforehand).
"""

from __future__ import annotations

from typing import Iterable

import cv2
import numpy as np
from scipy.special import ndtr

from ._defects_kernels import abs_median_every_second
from .params import CaptureParams

__all__ = ["HOT", "DEAD", "STUCK", "DEFECT_NAMES", "find_defective_pixels", "defect_counts", "valid_pixels",
           "STUCK_FALSE_ALARMS", "range_chance", "stuck_decidable"]

HOT, DEAD, STUCK = 1, 2, 4
#: Names of the codes (bits) of :func:`find_defective_pixels`'s map.
DEFECT_NAMES = {HOT: "hot", DEAD: "dead", STUCK: "stuck"}
#: Normal pixels the stuck test may flag by chance per image (the expected number): a
#: pixel is stuck only if the chance that a normal one shows so little spread, times the
#: image's pixels, is below this.
STUCK_FALSE_ALARMS = 0.01

_PREDICT = (np.array([[-1.0, 2.0, -1.0], [2.0, 0.0, 2.0], [-1.0, 2.0, -1.0]]) / 4.0).astype(np.float32)


def _standard_residual(img: np.ndarray) -> np.ndarray:
    """The residual against the neighbours' quadratic prediction, in robust standard
    deviations (1.4826 x the median absolute residual, every second pixel)."""
    r = cv2.filter2D(img, cv2.CV_32F, _PREDICT, borderType=cv2.BORDER_REPLICATE)
    np.subtract(img, r, out=r)
    scale = 1.4826 * abs_median_every_second(r)
    if scale <= 0:
        return np.zeros_like(r)
    np.divide(r, np.float32(scale), out=r)
    return r


def find_defective_pixels(frames: Iterable[np.ndarray], *, threshold: float = 10.0,
                          stuck_ratio: float = CaptureParams.stuck_ratio) -> np.ndarray:
    """Map of a camera's defective pixels from its frames.

    Parameters
    ----------
    frames : iterable of ndarray, shape (H, W)
        Grey images of the camera: its reference frames (each one, not their mean) and a
        few capture frames. Read once, one at a time.
    threshold : float
        Hot and dead: robust standard deviations of the neighbour-prediction residual.
    stuck_ratio : float
        Stuck: standard deviation over the frames below this fraction of the smallest of
        its 8 neighbours' (0 disables the test); and a spread no normal pixel shows by
        chance (:data:`STUCK_FALSE_ALARMS` per image).

    Returns
    -------
    defects : ndarray, shape (H, W), uint8
        Bit sum of :data:`HOT`, :data:`DEAD` and :data:`STUCK` (0 = a good pixel).
    """
    st = _FrameStats()
    for frame in frames:
        st.add(frame)
    if st.n == 0:
        raise ValueError("no frames to find defective pixels in")
    out = np.zeros(st.zmin.shape, np.uint8)
    out[(st.zmin > threshold) & st.peak] |= HOT
    out[(st.zmax < -threshold) & st.peak] |= DEAD
    if stuck_ratio > 0 and st.n >= 2:
        out[_stuck(st, stuck_ratio)] |= STUCK
    return out


_BOX = np.ones((3, 3), np.uint8)  # a pixel's 3x3 neighbourhood


class _FrameStats:
    """What the tests need of the frames, accumulated one frame at a time: the extreme
    standardised residuals, whether the pixel is its neighbourhood's largest residual in
    every frame, the per-pixel sums, extremes and clipping counts over the frames, and
    whether every value is an integer (a quantised sensor)."""

    def __init__(self):
        self.n = 0
        self.integer = True

    def add(self, frame) -> None:
        img = np.ascontiguousarray(frame, dtype=np.float32)
        if not cv2.checkRange(img)[0]:  # NaN or inf
            img = np.where(np.isfinite(img), img, np.float32(np.nanmedian(img)))
        z = _standard_residual(img)
        a = np.abs(z)
        is_peak = a >= cv2.dilate(a, _BOX)
        lo, hi = cv2.minMaxLoc(img)[:2]
        at_clip = cv2.bitwise_or(cv2.compare(img, lo, cv2.CMP_LE), cv2.compare(img, hi, cv2.CMP_GE))  # 0 or 255
        self.integer = self.integer and bool(np.array_equal(img, np.round(img)))
        if self.n == 0:  # in place from here on: a frame is 1-2 million pixels
            self.zmin, self.zmax, self.peak = z.copy(), z, is_peak
            self.s1, self.s2, self.clip = np.zeros(img.shape), np.zeros(img.shape), np.zeros(img.shape, np.int32)
            self.lo, self.hi = img.copy(), img.copy()
        else:
            if z.shape != self.zmin.shape:
                raise ValueError(f"frame {self.n} has shape {z.shape}, frame 0 has {self.zmin.shape}")
            np.minimum(self.zmin, z, out=self.zmin)
            np.maximum(self.zmax, z, out=self.zmax)
            self.peak &= is_peak
            np.minimum(self.lo, img, out=self.lo)
            np.maximum(self.hi, img, out=self.hi)
        cv2.accumulate(img, self.s1)  # float64 sums of the frames and of their squares
        cv2.accumulateSquare(img, self.s2)
        np.add(self.clip, at_clip, out=self.clip)  # 255 per clipped frame
        self.n += 1


def _stuck(st: _FrameStats, stuck_ratio: float) -> np.ndarray:
    """The stuck pixels (see the module docstring): little spread against the least varying
    neighbour, not clipped, and a spread no normal pixel keeps by chance."""
    n = st.n
    mean = st.s1 / n
    var = st.s2 / n  # the variance over the frames, in place (a frame is 1-2 million pixels)
    np.multiply(mean, mean, out=mean)
    np.subtract(var, mean, out=var)
    np.maximum(var, 0.0, out=var)
    sd = np.sqrt(var, out=var).astype(np.float32)
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0
    around = cv2.erode(sd, ring, borderType=cv2.BORDER_REFLECT_101)
    clipped = 2 * (st.clip // 255) >= n  # at the frame's darkest or brightest level in half of the frames
    cand = (sd < stuck_ratio * around) & (around > 0) & ~clipped
    rows, cols = np.nonzero(cand)
    if len(rows) == 0:
        return cand
    quantum = 1.0 if st.integer else 0.0
    chance = range_chance((st.hi - st.lo)[rows, cols], _normal_sigma(around[rows, cols], quantum), n,
                          quantum=quantum)
    keep = chance * cand.size <= STUCK_FALSE_ALARMS
    out = np.zeros_like(cand)
    out[rows[keep], cols[keep]] = True
    return out


def _normal_sigma(sd: np.ndarray, quantum: float) -> np.ndarray:
    """The noise (before quantisation) of a pixel whose quantised values have standard
    deviation ``sd`` (quantisation adds ``quantum^2 / 12`` to the variance)."""
    return np.sqrt(np.maximum(np.asarray(sd, np.float64) ** 2 - quantum * quantum / 12.0, 0.0))


def range_chance(spread, sigma, n: int, *, quantum: float = 1.0) -> np.ndarray:
    """The chance that ``n`` independent values of a normal pixel (noise ``sigma``) span no
    more than ``spread`` (their largest minus their smallest), elementwise.

    With ``quantum > 0`` the values are rounded to multiples of it (a sensor's grey levels):
    the chance that all fall within ``spread / quantum + 1`` consecutive levels, summed over
    where the lowest one lies, ``sum_j P(all in j..j+R) - P(all in j+1..j+R)``, for the
    pixel's mean at the worst place (on a level, or half way between two). Without it the
    range of ``n`` normal values, ``n int phi(x) (Phi(x + spread / sigma) - Phi(x))^(n-1) dx``.

    Parameters
    ----------
    spread : array-like
        Observed range of the pixel's values (grey levels).
    sigma : array-like
        Standard deviation of a normal pixel's values there, before quantisation.
    n : int
        Number of values.
    quantum : float
        The quantisation step (0: values not quantised).

    Returns
    -------
    chance : ndarray, float64
    """
    spread, sigma = np.broadcast_arrays(np.asarray(spread, np.float64), np.asarray(sigma, np.float64))
    shape = spread.shape
    spread, sigma = spread.ravel(), sigma.ravel()
    out = np.ones(spread.shape)
    idx = np.flatnonzero(sigma > 0)
    idx = idx[np.argsort(sigma[idx], kind="stable")]  # blocks of similar noise: similar reach
    for k in range(0, len(idx), 4096):  # bounded memory: a block of pixels times the levels
        i = idx[k:k + 4096]
        out[i] = _range_chance(spread[i][:, None], sigma[i][:, None], int(n), float(quantum))
    return out.reshape(shape)


def _range_chance(w: np.ndarray, s: np.ndarray, n: int, q: float) -> np.ndarray:
    """:func:`range_chance` of columns ``w`` (spread) and ``s`` (noise > 0)."""
    if q > 0:
        r = np.round(w / q)
        reach = int(np.ceil(8.0 * float(s.max()) / q + float(r.max()))) + 2
        j = np.arange(-reach, reach + 1, dtype=np.float64)[None, :]
        best = np.zeros(len(s))
        for mu in (0.0, 0.5):  # the pixel's mean on a level, or half way between two
            top = ndtr((j + r + 0.5 - mu) * q / s)
            inside = top - ndtr((j - 0.5 - mu) * q / s)
            above_low = top - ndtr((j + 0.5 - mu) * q / s)
            p = (np.clip(inside, 0, 1) ** n - np.clip(above_low, 0, 1) ** n).sum(axis=1)
            best = np.maximum(best, p)
    else:
        x = np.linspace(-9.0, 9.0, 1801)[None, :]
        phi = np.exp(-0.5 * x * x) / np.sqrt(2.0 * np.pi)
        inner = np.clip(ndtr(x + w / s) - ndtr(x), 0.0, 1.0)
        best = n * np.trapezoid(phi * inner ** (n - 1), x, axis=1)
    return np.clip(best, 0.0, 1.0)


def stuck_decidable(n: int, noise: float, pixels: int, *, quantum: float = 1.0) -> bool:
    """Whether ``n`` frames can tell a stuck pixel (one constant value) from a normal one of
    sensor noise ``noise`` (grey levels, its quantisation included) in an image of
    ``pixels`` pixels, at :data:`STUCK_FALSE_ALARMS` per image: with fewer, the stuck test
    finds stuck pixels only where the neighbours vary more than the noise (a flow)."""
    if n < 2:
        return False
    sigma = _normal_sigma(np.array([noise]), quantum)
    return bool(range_chance(np.zeros(1), sigma, n, quantum=quantum)[0] * pixels <= STUCK_FALSE_ALARMS)


def defect_counts(defects: np.ndarray) -> dict[str, int]:
    """Pixels of each kind in a map of :func:`find_defective_pixels` (a pixel may count twice)."""
    d = np.asarray(defects)
    return {name: int(np.count_nonzero(d & bit)) for bit, name in DEFECT_NAMES.items()}


def valid_pixels(defects: np.ndarray | None) -> np.ndarray | None:
    """The pixels a registration may use: none within 2 pixels of a defective one (the
    pre-smoothing and the gradient spread a defect over its neighbours); None when
    ``defects`` (a map of :func:`find_defective_pixels`, or None) holds none."""
    if defects is None or not np.any(defects):
        return None
    bad = np.asarray(defects) != 0
    return ~cv2.dilate(bad.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
