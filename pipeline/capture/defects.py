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
  so do its neighbours, or it carries no texture the flow could use anyway).
"""

from __future__ import annotations

from typing import Iterable

import cv2
import numpy as np

from .params import CaptureParams

__all__ = ["HOT", "DEAD", "STUCK", "DEFECT_NAMES", "find_defective_pixels", "defect_counts", "valid_pixels",
           "MIN_STUCK_FRAMES"]

HOT, DEAD, STUCK = 1, 2, 4
#: Names of the codes (bits) of :func:`find_defective_pixels`'s map.
DEFECT_NAMES = {HOT: "hot", DEAD: "dead", STUCK: "stuck"}
#: Frames the stuck test needs (with fewer, quantised noise repeats by chance).
MIN_STUCK_FRAMES = 8

_PREDICT = (np.array([[-1.0, 2.0, -1.0], [2.0, 0.0, 2.0], [-1.0, 2.0, -1.0]]) / 4.0).astype(np.float32)


def _standard_residual(img: np.ndarray) -> np.ndarray:
    """The residual against the neighbours' quadratic prediction, in robust standard
    deviations (1.4826 x the median absolute residual, every second pixel)."""
    r = cv2.filter2D(img, cv2.CV_32F, _PREDICT, borderType=cv2.BORDER_REPLICATE)
    np.subtract(img, r, out=r)
    scale = 1.4826 * float(np.median(np.abs(r[::2, ::2]), overwrite_input=True))
    if scale <= 0:
        return np.zeros_like(r)
    np.divide(r, np.float32(scale), out=r)
    return r


def find_defective_pixels(frames: Iterable[np.ndarray], *, threshold: float = 10.0,
                          stuck_ratio: float = CaptureParams.stuck_ratio,
                          min_stuck_frames: int = MIN_STUCK_FRAMES) -> np.ndarray:
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
        its 8 neighbours' (0 disables the test).
    min_stuck_frames : int
        The stuck test runs only with at least this many frames.

    Returns
    -------
    defects : ndarray, shape (H, W), uint8
        Bit sum of :data:`HOT`, :data:`DEAD` and :data:`STUCK` (0 = a good pixel).
    """
    n = 0
    zmin = zmax = peak = s1 = s2 = clip = None
    box = np.ones((3, 3), np.uint8)
    for frame in frames:  # in place where it can be: a frame is 1-2 million pixels
        img = np.ascontiguousarray(frame, dtype=np.float32)
        if not cv2.checkRange(img)[0]:  # NaN or inf
            img = np.where(np.isfinite(img), img, np.float32(np.nanmedian(img)))
        z = _standard_residual(img)
        a = np.abs(z)
        is_peak = a >= cv2.dilate(a, box)
        lo, hi = cv2.minMaxLoc(img)[:2]
        at_clip = cv2.bitwise_or(cv2.compare(img, lo, cv2.CMP_LE), cv2.compare(img, hi, cv2.CMP_GE))  # 0 or 255
        if n == 0:
            zmin, zmax, peak = z.copy(), z, is_peak
            s1, s2, clip = np.zeros(img.shape), np.zeros(img.shape), np.zeros(img.shape, np.int32)
        else:
            if z.shape != zmin.shape:
                raise ValueError(f"frame {n} has shape {z.shape}, frame 0 has {zmin.shape}")
            np.minimum(zmin, z, out=zmin)
            np.maximum(zmax, z, out=zmax)
            peak &= is_peak
        cv2.accumulate(img, s1)  # float64 sums of the frames and of their squares
        cv2.accumulateSquare(img, s2)
        np.add(clip, at_clip, out=clip)
        n += 1
    if n == 0:
        raise ValueError("no frames to find defective pixels in")
    clip //= 255
    out = np.zeros(zmin.shape, np.uint8)
    out[(zmin > threshold) & peak] |= HOT
    out[(zmax < -threshold) & peak] |= DEAD
    if stuck_ratio > 0 and n >= min_stuck_frames:
        mean = s1 / n
        sd = np.sqrt(np.maximum(s2 / n - mean * mean, 0.0)).astype(np.float32)
        ring = np.ones((3, 3), np.uint8)
        ring[1, 1] = 0
        around = cv2.erode(sd, ring, borderType=cv2.BORDER_REFLECT_101)
        clipped = 2 * clip >= n  # at the frame's darkest or brightest level in half of the frames
        out[(sd < stuck_ratio * around) & (around > 0) & ~clipped] |= STUCK
    return out


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
