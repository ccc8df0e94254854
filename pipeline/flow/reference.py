"""What depends only on a camera's background, prepared once for its many frames
(:class:`PreparedReference`: normalisation, pre-smoothed pyramid, B-spline coefficients,
invalid-pixel maps), and the check for pixels that cannot carry a deflection
(:func:`invalid_pixels`) with the per-level LK/HS weights it gives.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .focus import resolve_presmooth
from .images import _as_image, _fill_nonfinite, _normalisation, _pyramid, _standardise
from .params import FlowParams
from .splines import _spline_coefficients

__all__ = ["PreparedReference", "prepare_reference", "frame_pyramid", "invalid_pixels"]


@dataclass(frozen=True, eq=False)
class PreparedReference:
    """A reference background pre-processed once for many frames of the same camera.

    Holds the normalisation (mean, scale), the pre-smoothed pyramid and its cubic B-spline
    coefficients. Build it with :func:`prepare_reference`; pass it instead of the reference
    array to :func:`deflection_field` / :func:`deflection_stage` (cache one per camera in a
    worker process: it saves about a fifth of the per-frame cost at 1440x1080).
    """

    image: np.ndarray            # original reference, float32 (H, W)
    mean: float
    scale: float
    presmooth: float             # pixels (``"auto"`` resolved)
    levels: int
    pyramid: tuple               # standardised, pre-smoothed images per level (fine first)
    coefficients: tuple          # padded B-spline coefficients per level
    _invalid: dict = field(default_factory=dict, repr=False)   # texture_threshold -> invalid map

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape

    def invalid(self, texture_threshold: float) -> np.ndarray:
        """:func:`invalid_pixels` of the reference (computed once per threshold)."""
        key = float(texture_threshold)
        if key not in self._invalid:
            self._invalid[key] = invalid_pixels(self.image, texture_threshold=key)
        return self._invalid[key]


def prepare_reference(reference: np.ndarray, *, presmooth: float | str = FlowParams.presmooth,
                      levels: int = FlowParams.levels) -> PreparedReference:
    """Pre-process a reference background for :func:`deflection_field`.

    Parameters
    ----------
    reference : ndarray, shape (H, W)
        Background without flow, grey levels.
    presmooth : float or {"auto"}
        Gaussian sigma (pixels) applied before the flow (must match the flow parameters);
        ``"auto"``: chosen from the reference's sharpness (:func:`~.focus.auto_presmooth`).
    levels : int
        Pyramid levels (must match the flow parameters).
    """
    img = _as_image(reference, "reference")
    presmooth = resolve_presmooth(presmooth, img)
    mean, scale = _normalisation(img)
    pyr = _pyramid(_standardise(_fill_nonfinite(img, mean), mean, scale, presmooth), levels)
    coef = tuple(_spline_coefficients(p) for p in pyr)
    return PreparedReference(img, mean, scale, float(presmooth), int(levels), tuple(pyr), coef)


def frame_pyramid(reference: PreparedReference, frame: np.ndarray) -> list[np.ndarray]:
    """A frame's pyramid as LK and HS compare it with ``reference.pyramid``: non-finite
    pixels set to the reference's mean, standardised with the reference's normalisation,
    pre-smoothed like it (one per level, fine first; float32)."""
    img = _fill_nonfinite(_as_image(frame, "frame"), reference.mean)
    return _pyramid(_standardise(img, reference.mean, reference.scale, reference.presmooth), len(reference.pyramid))


def invalid_pixels(image: np.ndarray, *, texture_threshold: float = FlowParams.texture_threshold, size: int = 7,
                   clip_fraction: float = 0.6) -> np.ndarray:
    """Pixels of one image that cannot carry a BOS deflection.

    * non-finite values (NaN from a dead pixel map, inf);
    * clipped runs: where more than ``clip_fraction`` of a ``size`` x ``size`` window sits
      at the image's minimum or maximum grey level (a black or saturated region; isolated
      extreme pixels of a contrasty background stay valid);
    * textureless pixels: the local standard deviation (``size`` x ``size``) is below
      ``texture_threshold`` times its median over the image (a blank wall, a stuck
      region: optical flow there returns only noise or the regulariser's zero).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey levels.

    Returns
    -------
    invalid : ndarray, shape (H, W), bool
    """
    img = _as_image(image, "image")
    bad = ~np.isfinite(img)
    any_bad = bool(bad.any())
    fin = img[~bad] if any_bad else img.ravel()
    if fin.size == 0:
        return np.ones(img.shape, bool)
    x = _fill_nonfinite(img, float(np.median(fin[:: max(fin.size // 20000, 1)]))) if any_bad else img
    lo, hi = (float(fin.min()), float(fin.max())) if any_bad else cv2.minMaxLoc(img)[:2]
    # The clipped-run and texture statistics are regional: take them at half resolution
    # (a quarter of the pixels; 2x2 means), then back to full resolution, grown by a pixel.
    half = min(img.shape) >= 4 * size
    xs = cv2.resize(x, (x.shape[1] // 2, x.shape[0] // 2), interpolation=cv2.INTER_AREA) if half else x
    ks = ((size + 1) // 2, (size + 1) // 2) if half else (size, size)
    region = np.zeros(xs.shape, bool)
    if hi > lo:
        for value, how in ((lo, cv2.CMP_LE), (hi, cv2.CMP_GE)):
            if half:  # 0/4 per pixel -> the 2x2 area mean is the exact count (uint8: 4x cheaper)
                c4 = cv2.compare(x, value, how)
                np.bitwise_and(c4, np.uint8(4), out=c4)  # in place: OpenCV's and with a scalar is far slower
                cs = cv2.resize(c4, (xs.shape[1], xs.shape[0]), interpolation=cv2.INTER_AREA)
                frac = cv2.boxFilter(cs, cv2.CV_32F, ks, borderType=cv2.BORDER_REFLECT) * np.float32(0.25)
            else:
                frac = cv2.boxFilter((x <= lo if how == cv2.CMP_LE else x >= hi).astype(np.float32), -1, ks,
                                     borderType=cv2.BORDER_REFLECT)
            region |= frac > clip_fraction
    m = cv2.boxFilter(xs, -1, ks, borderType=cv2.BORDER_REFLECT)
    m2 = cv2.boxFilter(xs * xs, -1, ks, borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(np.maximum(m2 - m * m, 0.0))
    med = float(np.median(sd[::2, ::2]))
    if med <= 0:      # no texture in most of the image (a blank or black frame)
        return np.ones(img.shape, bool) if texture_threshold > 0 else bad
    if texture_threshold > 0:
        region |= sd < np.float32(texture_threshold * med)
    if region.any():
        if half:
            region = cv2.resize(region.astype(np.uint8), (img.shape[1], img.shape[0]),
                                interpolation=cv2.INTER_NEAREST)
            region = cv2.dilate(region, np.ones((3, 3), np.uint8)).astype(bool)
        bad |= region
    return bad


def _weight_pyramid(valid: np.ndarray, levels: int, dilate: int = 2) -> list[np.ndarray]:
    """Per-level LK/HS data weights: 1 on valid pixels, 0 within ``dilate`` px of invalid ones
    (the cubic warp of the reference reaches 2 px), a coarse pixel valid only if all of its
    fine pixels are."""
    inv = (~valid).astype(np.uint8)
    if dilate > 0:
        inv = cv2.dilate(inv, np.ones((2 * dilate + 1, 2 * dilate + 1), np.uint8))
    w = (1 - inv).astype(np.float32)
    out = [w]
    for _ in range(levels - 1):
        if min(out[-1].shape) < 16:
            break
        out.append((cv2.pyrDown(out[-1], borderType=cv2.BORDER_REFLECT) > 0.999).astype(np.float32))
    return out
