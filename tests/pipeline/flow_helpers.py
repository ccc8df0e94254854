"""Synthetic BOS images with known deflections, rendered cleaner than the flow judged.

The background is band-limited noise defined on a fine grid (``oversample`` samples per
image pixel) and interpolated with cubic B-splines (scipy ``map_coordinates``, order 3,
prefiltered), so it is a smooth continuous function. A camera pixel integrates that
function over its area (``supersample`` x ``supersample`` points) displaced by the known
deflection: ``frame(p) = mean_{q in pixel p} B(q + delta(q))``. No bilinear resampling
anywhere (STYLE.md "Numbers that bite").
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


class NoiseBackground:
    """Band-limited noise pattern, a continuous function of image coordinates (u, v)."""

    def __init__(self, shape, *, rng, feature_px: float = 0.8, oversample: int = 4,
                 margin: int = 8, contrast: float = 40.0, mean: float = 128.0):
        H, W = shape
        self.oversample = oversample
        self.margin = margin
        hf, wf = (H + 2 * margin) * oversample, (W + 2 * margin) * oversample
        white = rng.standard_normal((hf, wf))
        fine = ndimage.gaussian_filter(white, feature_px * oversample, mode="wrap")
        fine *= contrast / fine.std()
        fine += mean
        self.coeffs = ndimage.spline_filter(fine, order=3)

    def sample(self, u, v) -> np.ndarray:
        """Pattern value at image coordinates (u = column, v = row), any shape."""
        s = self.oversample
        # image pixel centre u maps to fine coordinate (u + margin + 0.5) * s - 0.5
        fu = (np.asarray(u) + self.margin + 0.5) * s - 0.5
        fv = (np.asarray(v) + self.margin + 0.5) * s - 0.5
        out = ndimage.map_coordinates(self.coeffs, [fv.ravel(), fu.ravel()], order=3,
                                      prefilter=False, mode="nearest")
        return out.reshape(np.shape(u))


def render(background: NoiseBackground, shape, deflection=None, *, supersample: int = 3,
           noise: float = 0.0, rng=None, rows=None) -> np.ndarray:
    """Camera image of ``background`` seen through ``deflection``.

    Parameters
    ----------
    deflection : callable (u, v) -> (du, dv) or None
        Deflection in pixels at image coordinates; None = reference image.
    noise : float
        Std of additive Gaussian sensor noise (grey levels).
    rows : slice or None
        Render only these image rows (the full-size coordinates are kept).

    Returns
    -------
    ndarray, shape (H, W) float32
    """
    H, W = shape
    r = np.arange(H)[rows] if rows is not None else np.arange(H)
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    acc = np.zeros((len(r), W))
    vv, uu = np.meshgrid(r.astype(float), np.arange(W, dtype=float), indexing="ij")
    for oy in offs:
        for ox in offs:
            u = uu + ox
            v = vv + oy
            if deflection is not None:
                du, dv = deflection(u, v)
                u = u + du
                v = v + dv
            acc += background.sample(u, v)
    img = acc / supersample**2
    if noise > 0:
        img = img + rng.normal(0.0, noise, img.shape)
    return img.astype(np.float32)


def pixel_truth(deflection, shape, *, supersample: int = 3) -> np.ndarray:
    """Pixel-averaged true deflection, shape (H, W, 2)."""
    H, W = shape
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    vv, uu = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    acc = np.zeros((H, W, 2))
    for oy in offs:
        for ox in offs:
            du, dv = deflection(uu + ox, vv + oy)
            acc[..., 0] += du
            acc[..., 1] += dv
    return acc / supersample**2


def plume_deflection(shape, *, peak: float = 1.0, width: float | None = None, centre=None):
    """Deflection of a hot vertical plume: rays bent away from its axis.

    phi = g(v) exp(-(u - cu)^2 / (2 s(v)^2)) is the projected refractivity deficit
    (positive in the plume, widening upwards, fading in above the source row ``cv``);
    ``delta = -c grad(phi)`` points away from the axis, max |delta| about ``peak`` pixels.
    """
    H, W = shape
    width = width if width is not None else W / 10.0
    cu = centre[0] if centre is not None else W / 2.0
    cv = centre[1] if centre is not None else H * 0.9
    # phi(u, v) = A * g(v) * exp(-(u - cu)^2 / (2 s(v)^2)), plume widening upwards
    def field(u, v):
        h = np.clip((cv - v) / H, 0.0, None)           # height above the source
        s = width * (0.6 + 0.8 * h)
        g = np.where(v < cv, 1.0 - np.exp(-((cv - v) / (0.1 * H)) ** 2), 0.0)
        e = np.exp(-((u - cu) ** 2) / (2 * s**2))
        # grad phi / A (the s(v) and g(v) dependence gives a smaller vertical component)
        dphi_du = -g * e * (u - cu) / s**2
        ds_dv = -0.8 * width / H * (v < cv)
        dg_dv = np.where(v < cv, -2 * (cv - v) / (0.1 * H) ** 2
                         * np.exp(-((cv - v) / (0.1 * H)) ** 2), 0.0)
        dphi_dv = e * dg_dv + g * e * ((u - cu) ** 2 / s**3) * ds_dv
        scale = peak / (np.exp(-0.5) / (width * 0.6))   # max |dphi_du| at the base ~ 1/s
        return -scale * dphi_du, -scale * dphi_dv

    return field
