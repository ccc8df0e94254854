"""The camera's motion against its reference: one robust global shift per frame.

A tripod that moved by a tenth of a pixel between the reference and the capture moves
every BOS deflection (a few tenths of a pixel, paper sec. 4) by that much. The shift is
found to the pixel by phase correlation (robust to the flow's regions), then refined by Lucas-Kanade steps whose update is the median over tiles of the
image (a plume covering less than half of the tiles does not move it); the spread of the
tiles' shifts tells a rotation or a non-rigid motion from a shift.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from schlieren.pipeline.flow.splines import spline_coefficients, warp_coefficients

__all__ = ["GlobalShift", "global_shift"]

_H = 0.05  # pixels: half the step of the derivative's central difference


@dataclass(frozen=True)
class GlobalShift:
    """The frame's shift against the reference, flow convention: ``frame(p) ~= reference(p + d)``.

    Attributes
    ----------
    du, dv : float
        Pixels along columns (x) and rows (y).
    spread : float
        Robust spread (``1.4826`` MAD, pixels, RMS of both axes) of the tiles' shifts
        about the median: noise, plus rotation or non-rigid motion where large.
    """

    du: float
    dv: float
    spread: float

    @property
    def magnitude(self) -> float:
        return float(np.hypot(self.du, self.dv))


def _shifted(coef: np.ndarray, shape: tuple[int, int], du: float, dv: float) -> np.ndarray:
    """``img(p + d)`` by exact cubic B-spline interpolation (``coef`` its coefficients):
    OpenCV's bicubic convolution would bias the sub-pixel shift."""
    flow = np.empty(shape + (2,), np.float32)
    flow[..., 0], flow[..., 1] = du, dv
    return warp_coefficients(coef, flow)


def _tile_sums(a: np.ndarray, tiles: tuple[int, int]) -> np.ndarray:
    ty, tx = tiles
    H, W = a.shape
    h, w = H // ty, W // tx
    return a[:h * ty, :w * tx].reshape(ty, h, tx, w).sum(axis=(1, 3))


def _jacobian(coef: np.ndarray, shape, du: float, dv: float, m: slice, tiles):
    """The tiles' structure tensors (``sxx, sxy, syy`` and their determinants) and the
    gradient of the shifted reference: the spline's own derivative, a central difference
    of 0.1 px (a Scharr gradient of a sharp texture undershoots each step)."""
    gx = ((_shifted(coef, shape, du + _H, dv) - _shifted(coef, shape, du - _H, dv))[m, m] / (2 * _H)).astype(np.float64)
    gy = ((_shifted(coef, shape, du, dv + _H) - _shifted(coef, shape, du, dv - _H))[m, m] / (2 * _H)).astype(np.float64)
    sxx, sxy, syy = (_tile_sums(a, tiles) for a in (gx * gx, gx * gy, gy * gy))
    return sxx, sxy, syy, np.maximum(sxx * syy - sxy * sxy, 1e-30), gx, gy


def _phase_correlation(ref: np.ndarray, frm: np.ndarray, search: int) -> tuple[float, float]:
    """The integer shift ``d`` (``frame(p) = reference(p + d)``) with ``|d| <= search`` at the
    peak of the phase correlation of the Hann-windowed images. The peak is searched near
    zero only: a background printed from a tiled pattern correlates with itself at the
    tile's period too."""
    win = cv2.createHanningWindow(ref.shape[::-1], cv2.CV_32F)
    a = np.fft.rfft2((ref - ref.mean()) * win)
    b = np.fft.rfft2((frm - frm.mean()) * win)
    cross = b * np.conj(a)
    corr = np.fft.irfft2(cross / np.maximum(np.abs(cross), 1e-12), s=ref.shape)
    r = int(search)
    near = np.roll(np.roll(corr, r, axis=0), r, axis=1)[:2 * r + 1, :2 * r + 1]
    iy, ix = np.unravel_index(int(np.argmax(near)), near.shape)
    return -float(ix - r), -float(iy - r)  # frame(p) = reference(p - s) at the peak s


def global_shift(reference: np.ndarray, frame: np.ndarray, *, tiles: tuple[int, int] = (6, 8), iterations: int = 4,
                 margin: int = 8, search: int = 8) -> GlobalShift:
    """The frame's global shift against the reference (:class:`GlobalShift`).

    Parameters
    ----------
    reference, frame : ndarray, shape (H, W)
        Grey images.
    tiles : (int, int)
        Rows and columns of tiles over which each refinement's update is the median.
    iterations : int
        Lucas-Kanade refinements after the phase correlation.
    margin : int
        Pixels at the border left out (interpolation at the edge).
    search : int
        The largest shift looked for, pixels per axis.
    """
    ref = np.ascontiguousarray(reference, dtype=np.float32)
    frm = np.ascontiguousarray(frame, dtype=np.float32)
    du, dv = _phase_correlation(ref, frm, search)
    m = slice(margin, -margin) if margin > 0 else slice(None)
    f_in = frm[m, m]
    coef = spline_coefficients(ref)
    tu = tv = np.zeros(1)
    for it in range(max(int(iterations), 1)):
        if it < 2:  # the Jacobian at the phase correlation's pixel, then once more near the shift
            sxx, sxy, syy, det, gx, gy = _jacobian(coef, ref.shape, du, dv, m, tiles)
        e = (f_in - _shifted(coef, ref.shape, du, dv)[m, m]).astype(np.float64)
        e -= e.mean()  # a uniform change of lighting is not a shift
        bx, by = _tile_sums(gx * e, tiles), _tile_sums(gy * e, tiles)
        tu = (syy * bx - sxy * by) / det
        tv = (sxx * by - sxy * bx) / det
        du += float(np.median(tu))
        dv += float(np.median(tv))
    mad = [1.4826 * float(np.median(np.abs(t - np.median(t)))) for t in (tu, tv)]
    return GlobalShift(du, dv, float(np.sqrt(0.5 * (mad[0] ** 2 + mad[1] ** 2))))
