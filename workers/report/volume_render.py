"""Emission-absorption volume rendering of the refractivity (the paper's Figures 1 and 8).

An orthographic camera orbits the box (z up), samples are trilinear, the transfer function
acts on the refractivity deficit ``r_ambient - r`` so hot (less dense) gas glows,
compositing is front to back with early ray termination. Arrays in, RGB ``uint8`` arrays
out; the ray marching itself is the numba kernel in :mod:`._kernels`.

* :class:`TransferFunction`: refractivity -> colour and extinction.
* :func:`view_basis`, :func:`fit_image_size`: the camera of a view.
* :func:`render_volume`: one rendering (with the box edges and an axis triad).
* :func:`animation_frames`: a time series with one transfer function, time-stamped.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import matplotlib
import numpy as np

from schlieren.pipeline.geometry import Grid
from schlieren.workers.report._kernels import march

__all__ = [
    "TransferFunction",
    "view_basis",
    "render_volume",
    "fit_image_size",
    "animation_frames",
]


@dataclass(frozen=True)
class TransferFunction:
    """Maps refractivity to emitted colour and extinction (paper Figures 1 and 8).

    The signal is ``s = clip((r_ambient - r) / scale, 0, 1)``: 0 for ambient air, 1 for
    the hottest gas shown. Colour is ``cmap(s)``; extinction per metre is
    ``optical_depth / L * s**gamma`` with ``L`` the longest edge of the box, so a ray
    crossing the whole box through gas at full signal accumulates ``optical_depth``.

    Parameters
    ----------
    r_ambient : float
        Refractivity ``n - 1`` of the surrounding air.
    scale : float
        Refractivity deficit shown at full signal (same units as refractivity). A negative
        scale shows excesses instead (``r - r_ambient``), e.g. cold gas or a 0/1 mask.
    optical_depth : float
        Dimensionless, see above.
    cmap : str
        A matplotlib colour map name.
    gamma : float
        Opacity ramp exponent (> 1 hides faint gas).
    """

    r_ambient: float
    scale: float
    optical_depth: float = 16.0
    cmap: str = "inferno"
    gamma: float = 1.0

    def tables(self, n: int = 1024) -> tuple[np.ndarray, np.ndarray]:
        """Colour (n, 3) in 0..1 and extinction-per-metre factor (n,) at ``s = k / (n - 1)``."""
        s = np.linspace(0.0, 1.0, n)
        rgb = np.asarray(matplotlib.colormaps[self.cmap](s))[:, :3]
        return rgb.astype(np.float64), s ** self.gamma


def view_basis(azimuth_deg: float, elevation_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Viewing direction, image right and image up (world unit vectors), z up.

    The eye sits at azimuth ``azimuth_deg`` (from +x towards +y) and elevation
    ``elevation_deg`` above the x-y plane and looks at the box centre.
    """
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    eye = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    d = -eye
    right = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: keep x to the right
        right = np.array([-np.sin(az), np.cos(az), 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, d)
    return d, right, up / np.linalg.norm(up)


def _box_edges() -> list[tuple[int, int]]:
    edges = []
    for a in range(8):
        for b in range(a + 1, 8):
            if bin(a ^ b).count("1") == 1:
                edges.append((a, b))
    return edges


def _view_extent(lo, hi, right, up):
    """Centre, bounding radius and projected width/height (metres) of the box in the view."""
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rel = corners - centre
    ext_w = 2.0 * float(np.max(np.abs(rel @ right)))
    ext_h = 2.0 * float(np.max(np.abs(rel @ up)))
    return centre, radius, (ext_w, ext_h)


def fit_image_size(grid: Grid, *, azimuth_deg: float = 30.0, elevation_deg: float = 15.0,
                   long_side: int = 480) -> tuple[int, int]:
    """``(width, height)`` in pixels whose aspect matches the box as seen from the view.

    Parameters
    ----------
    grid : Grid
    azimuth_deg, elevation_deg : float
        The view of :func:`render_volume`.
    long_side : int
        Pixels along the longer image side.
    """
    h = grid.voxel_size
    lo = np.asarray(grid.vmin, dtype=np.float64)
    hi = lo + h * np.asarray(grid.shape_xyz, dtype=np.float64)
    _, right, up = view_basis(azimuth_deg, elevation_deg)
    _, _, (ext_w, ext_h) = _view_extent(lo, hi, right, up)
    if ext_w >= ext_h:
        return int(long_side), max(16, int(round(long_side * ext_h / ext_w)))
    return max(16, int(round(long_side * ext_w / ext_h))), int(long_side)


def render_volume(refractivity: np.ndarray, grid: Grid, *, azimuth_deg: float = 30.0,
                  elevation_deg: float = 15.0, image_size: tuple[int, int] | None = None,
                  transfer: TransferFunction | None = None, step: float = 0.5,
                  background: tuple[int, int, int] = (0, 0, 0), draw_box: bool = True,
                  min_transmittance: float = 1e-3) -> np.ndarray:
    """Emission-absorption volume rendering of a refractivity field (paper Figures 1, 8).

    An orthographic camera looks at the box centre from ``(azimuth, elevation)`` with
    world z up; the projected box fills the image (a margin of 4 % on each side). Each
    pixel's ray is clipped to the box, sampled every ``step`` voxels with trilinear interpolation of the
    refractivity, and composited front to back
    ``C += T * alpha(s) * rgb(s); T *= 1 - alpha(s)``, with
    ``alpha(s) = 1 - exp(-sigma(s) * step * h)`` from the :class:`TransferFunction`;
    rays stop once ``T < min_transmittance``.

    Parameters
    ----------
    refractivity : ndarray, shape (nz, ny, nx)
        ``n - 1`` on ``grid`` (any scalar works with a suitable transfer function).
    grid : Grid
    azimuth_deg, elevation_deg : float
        Eye direction, degrees (azimuth from +x towards +y, elevation above x-y).
    image_size : (width, height), optional
        Pixels of the result (default: :func:`fit_image_size`, 480 on the long side).
    transfer : TransferFunction, optional
        Default: ambient = the volume's median, scale = its largest deficit.
    step : float
        Sampling step in voxels.
    background : (r, g, b)
        Colour behind the volume, 0..255.
    draw_box : bool
        Draw the box edges (grey) and an x/y/z axis triad at the lower-left corner.
    min_transmittance : float
        Early ray termination threshold.

    Returns
    -------
    rgb : ndarray, shape (height, width, 3), uint8
    """
    vol = np.ascontiguousarray(refractivity, dtype=np.float64)
    if vol.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {vol.shape} does not match grid {grid.shape}")
    if transfer is None:
        amb = float(np.median(vol))
        deficit = float(np.max(amb - vol))
        transfer = TransferFunction(r_ambient=amb, scale=deficit if deficit > 0 else 1.0)
    if transfer.scale == 0:
        raise ValueError("transfer.scale must be non-zero")
    h = grid.voxel_size
    nx, ny, nz = grid.shape_xyz
    lo = np.asarray(grid.vmin, dtype=np.float64)
    hi = lo + h * np.array([nx, ny, nz], dtype=np.float64)
    d, right, up = view_basis(azimuth_deg, elevation_deg)
    centre, radius, (ext_w, ext_h) = _view_extent(lo, hi, right, up)
    if image_size is None:
        image_size = fit_image_size(grid, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg)
    W, H = int(image_size[0]), int(image_size[1])
    pix = 1.08 * max(ext_w / W, ext_h / H)  # metres per pixel: the projected box fills the image
    jj, ii = np.meshgrid(np.arange(W) - (W - 1) / 2.0, np.arange(H) - (H - 1) / 2.0)
    plane = (centre + jj[..., None] * pix * right - ii[..., None] * pix * up).reshape(-1, 3)
    origins = plane - 1.05 * radius * d
    ro, rd, t0, t1 = _clip_to_box(origins, d, grid)
    rgb_lut, s_gamma = transfer.tables()
    box_len = float(np.max(hi - lo))
    sigma = transfer.optical_depth / box_len * s_gamma  # 1/m
    ds = step * h
    alpha_lut = 1.0 - np.exp(-sigma * ds)
    bg = np.asarray(background, dtype=np.float64) / 255.0
    # march in world arc length: index point = ro + t * rd, step of ds metres
    out = march(vol, np.ascontiguousarray(ro), np.ascontiguousarray(rd), ds, t0, t1,
                float(transfer.r_ambient), 1.0 / float(transfer.scale), rgb_lut, alpha_lut, bg,
                 float(min_transmittance))
    img = np.clip(np.round(255.0 * out), 0, 255).astype(np.uint8).reshape(H, W, 3)
    if draw_box:
        img = _draw_box(img, lo, hi, centre, right, up, pix)
    return img


def _clip_to_box(origins, d, grid: Grid):
    """Rays in voxel-index space and the arc lengths (metres) where they enter and leave the box.

    Index space: voxel centres at integers, box faces at -0.5 and n - 0.5; the index point
    is ``ro + t * rd`` at ``t`` metres along the ray (slab method, rays parallel to a face
    inside or outside its slab).
    """
    h = grid.voxel_size
    nx, ny, nz = grid.shape_xyz
    # index space: voxel centres at integers, box faces at -0.5 and n - 0.5
    ro = (origins - np.asarray(grid.origin)) / h
    rd = d / h  # index units per metre of arc length
    box_lo = np.full(3, -0.5)
    box_hi = np.array([nx, ny, nz], dtype=np.float64) - 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(rd != 0, 1.0 / np.where(rd != 0, rd, 1.0), np.inf)
        ta = (box_lo - ro) * inv
        tb = (box_hi - ro) * inv
    par = rd == 0
    inside = (ro >= box_lo) & (ro <= box_hi)
    tmin = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    tmax = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    t0 = np.maximum(tmin.max(axis=1), 0.0)  # metres along the ray
    t1 = tmax.min(axis=1)
    return ro, rd, t0, t1


def _to_image(X, centre, right, up, pix, W, H):
    rel = np.asarray(X) - centre
    return np.stack([rel @ right / pix + (W - 1) / 2.0, -(rel @ up) / pix + (H - 1) / 2.0], axis=-1)


def _draw_box(img, lo, hi, centre, right, up, pix):
    H, W = img.shape[:2]
    img = np.ascontiguousarray(img.copy())
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv = _to_image(corners, centre, right, up, pix, W, H)
    sh = 4  # fixed-point sub-pixel bits of cv2.line
    for a, b in _box_edges():
        p = tuple(int(round(c * (1 << sh))) for c in uv[a])
        q = tuple(int(round(c * (1 << sh))) for c in uv[b])
        cv2.line(img, p, q, (110, 110, 110), 1, cv2.LINE_AA, sh)
    # axis triad in the lower-left corner
    L = 0.08 * min(W, H)
    o = np.array([0.12 * min(W, H), H - 0.12 * min(W, H)])
    for k, (name, col) in enumerate((("x", (230, 80, 80)), ("y", (80, 200, 80)), ("z", (90, 140, 255)))):
        e = np.zeros(3)
        e[k] = 1.0
        v2 = np.array([e @ right, -(e @ up)])
        tip = o + L * v2
        cv2.line(img, tuple(int(round(c)) for c in o), tuple(int(round(c)) for c in tip), col, 2, cv2.LINE_AA)
        cv2.putText(img, name, tuple(int(round(c)) for c in tip + 4 * v2 + np.array([-4, 4])),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1, cv2.LINE_AA)
    return img


def animation_frames(volumes: np.ndarray, grid: Grid, *, r_ambient: float, times: np.ndarray | None = None,
                     azimuth_deg: float = 30.0, elevation_deg: float = 15.0,
                     image_size: tuple[int, int] | None = None, scale: float | None = None,
                     transfer: TransferFunction | None = None) -> list[np.ndarray]:
    """Volume renderings of a time series with one transfer function, time-stamped.

    Parameters
    ----------
    volumes : ndarray, shape (F, nz, ny, nx) or a sequence of (nz, ny, nx)
        Refractivity per frame.
    grid : Grid
    r_ambient : float
        Ambient refractivity.
    times : ndarray, shape (F,), optional
        Seconds, stamped on each frame.
    azimuth_deg, elevation_deg, image_size
        As in :func:`render_volume`.
    scale : float, optional
        Full-signal deficit (default: the largest deficit over all frames, so brightness is
        comparable between frames).
    transfer : TransferFunction, optional
        Overrides ``r_ambient`` / ``scale``.

    Returns
    -------
    list of ndarray, each (H, W, 3) uint8
    """
    if transfer is None:
        if scale is None:
            scale = max(float(np.nanmax(r_ambient - np.asarray(v, dtype=np.float64))) for v in volumes)
            if not scale > 0:
                scale = 1.0
        transfer = TransferFunction(r_ambient=r_ambient, scale=scale)
    frames = []
    for k, vol in enumerate(volumes):
        img = render_volume(vol, grid, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg,
                            image_size=image_size, transfer=transfer)
        if times is not None:
            img = np.ascontiguousarray(img)
            cv2.putText(img, f"t = {float(times[k]):.4f} s", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                        (230, 230, 230), 1, cv2.LINE_AA)
        frames.append(img)
    return frames
