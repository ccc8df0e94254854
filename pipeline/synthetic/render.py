"""BOS image formation: the background seen through the flow (paper sec. 3, 6).

For every pixel the renderer needs the background point ``B'`` hit by the *curved* ray.
By the flow sign convention (SPEC, ``docs/design.md``) ``B'`` is the point seen along the
straight ray through ``p + delta(p)`` with ``delta(p) = camera.project(B') - p``, so an
image is rendered as ``frame(p) = area mean over the pixel of pattern(straight_hit(q + delta(q)))``.

* ``delta`` is traced exactly (:mod:`.tracer`, RK4 through the phantom at each ray's own
  time: rolling shutter) on a lattice of pixel positions every ``stride`` pixels,
  and interpolated between lattice nodes with interpolating cubic B-splines. The field is
  smooth on the voxel scale (several pixels), so the interpolation error is far below the
  flow's precision (measured in the tests). Only rays crossing the active part of the
  volume are marched; elsewhere ``delta = 0`` exactly and the frame equals the reference.
* The pattern is evaluated procedurally (:mod:`.background`), never by resampling an
  image; each pixel is the mean over ``supersample x supersample`` sub-positions
  (pixel-area integration).
* Sensor noise, a strobe flash band and quantisation to 8 or 16 bits are applied last.

Rolling shutter: every lattice row is traced with the phantom at that row's own exposure
time (no time binning; the phantom is linear in time between its knots, which is the
truth's own definition). Image rows between lattice rows take ``delta`` from the cubic
interpolation across lattice rows ``stride`` line times apart (46 us for stride 3 at
1.54e-5 s): a 1 m/s flow moves 0.05 mm, a fiftieth of a 2.5 mm voxel, in that time, so the
time part of that interpolation error is far below its spatial part. The spatial part,
measured against rays traced at every pixel of a 1440x1080 camera through the plume, is
a fraction of a percent of the signal, largest near the sharp plume base
(``benchmarks/render.py``; benchmarks/results/render.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy import ndimage

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid
from schlieren.pipeline.synthetic.background import Background, _noise_at
from schlieren.pipeline.synthetic.dots import _dots_at
from schlieren.pipeline.synthetic.tracer import trace_rays_timed

__all__ = [
    "RenderParams",
    "Lattice",
    "LatticeTrace",
    "make_lattice",
    "trace_lattice",
    "trace_cells",
    "render_image",
    "render_frame",
    "reference_image",
    "row_times",
    "flash_rows",
    "apply_flash",
    "sensor",
    "cell_average",
]

MARGIN = 3          # lattice nodes beyond the image on each side
DILATE = 8          # lattice nodes around marched rays that may carry spline ringing


@dataclass(frozen=True)
class RenderParams:
    """Parameters of the renderer.

    Attributes
    ----------
    supersample : int
        Sub-positions per pixel side for pixel-area integration.
    stride : int
        Pixels between traced lattice rays.
    step : float or None
        RK4 step (metres); default the phantom's voxel size.
    exposure : float
        Exposure time (seconds) used for the strobe flash band.
    flash_gain : float
        Grey levels (8-bit scale) added to the rows lit by the flash.
    noise : float
        Sensor noise standard deviation (8-bit grey levels).
    bit_depth : int
        8 or 16.
    """

    supersample: int = 3
    stride: int = 3
    step: float | None = None
    exposure: float = 1.0 / 120.0
    flash_gain: float = 100.0
    noise: float = 1.5
    bit_depth: int = 8


@dataclass(frozen=True)
class Lattice:
    """Pixel positions of traced rays: ``u = origin + stride * j``, ``v = origin + stride * i``."""

    stride: int
    origin: float
    nx: int
    ny: int

    def coords(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.origin + self.stride * np.arange(self.nx, dtype=np.float64),
                self.origin + self.stride * np.arange(self.ny, dtype=np.float64))


def make_lattice(image_size: tuple[int, int], stride: int) -> Lattice:
    """Lattice aligned with ``FlowGrid(image_size, stride)`` cell centres, with a margin."""
    W, H = image_size
    origin = (stride - 1) / 2.0 - MARGIN * stride
    nx = -(-W // stride) + 2 * MARGIN
    ny = -(-H // stride) + 2 * MARGIN
    return Lattice(int(stride), float(origin), int(nx), int(ny))


@dataclass(frozen=True)
class LatticeTrace:
    """Exact traced quantities on a lattice (or on flow-grid cell centres).

    Attributes
    ----------
    delta : ndarray, shape (ny, nx, 2)
        Image-plane deflection (pixels), ``project(B') - p``; exactly 0 where not marched.
    d_in, d_out : ndarray, shape (ny, nx, 3)
        Unit directions of the undeflected camera ray and of the ray after the volume.
    marched : ndarray, shape (ny, nx) bool
        The ray crossed the active part of the volume.
    hit : ndarray, shape (ny, nx) bool
        The ray crossed the volume box.
    """

    delta: np.ndarray
    d_in: np.ndarray
    d_out: np.ndarray
    marched: np.ndarray
    hit: np.ndarray


def row_times(camera: Camera, frame: int, v: np.ndarray, *, frame_rate: float) -> np.ndarray:
    """Session time of image row coordinate ``v`` in ``frame`` (SPEC section 1).

    ``time_offset + frame / frame_rate + v * line_time`` (``v`` may be fractional).
    """
    off = 0.0 if camera.time_offset is None else camera.time_offset
    return off + frame / frame_rate + np.asarray(v, dtype=np.float64) * camera.line_time


def _trace_points(camera: Camera, uv: np.ndarray, times: np.ndarray, fields, knot_times, grid: Grid,
                  *, step: float, n_ambient: float, clip_box) -> LatticeTrace:
    shp = uv.shape[:-1]
    C, d_in = camera.rays(uv.reshape(-1, 2))
    res = trace_rays_timed(fields, knot_times, grid, C, d_in, times.reshape(-1), step=step,
                           n_ambient=n_ambient, clip_box=clip_box)
    marched = res.hit & np.any(res.d_out != d_in, axis=1)
    delta = np.zeros((d_in.shape[0], 2))
    if np.any(marched):
        Bp = camera.intersect_background(res.exit_point[marched], res.d_out[marched])
        delta[marched] = camera.project(Bp) - uv.reshape(-1, 2)[marched]
    return LatticeTrace(delta=delta.reshape(*shp, 2), d_in=d_in.reshape(*shp, 3),
                        d_out=res.d_out.reshape(*shp, 3), marched=marched.reshape(shp),
                        hit=res.hit.reshape(shp))


def trace_lattice(camera: Camera, lattice: Lattice, fields: np.ndarray, knot_times: np.ndarray, grid: Grid, *,
                  frame: int | None, frame_rate: float, time: float | None = None, step: float | None = None,
                  n_ambient: float = 1.00029, clip_box=None) -> LatticeTrace:
    """Trace the lattice rays of one camera-frame.

    Parameters
    ----------
    camera : Camera
    lattice : Lattice
    fields, knot_times :
        :func:`~schlieren.pipeline.synthetic.tracer.field_stack` of the phantom's knots
        covering the frame, and their times (seconds).
    grid : Grid
        The phantom's grid.
    frame : int or None
        Raw frame index: each lattice row is traced at its rolling-shutter time
        :func:`row_times`. ``None`` with ``time`` given traces every ray at ``time``
        (global shutter).
    frame_rate : float
    time : float, optional
        Global-shutter instant (seconds), used when ``frame`` is None.
    step : float, optional
        RK4 step (metres); default ``grid.voxel_size``.
    """
    u, v = lattice.coords()
    uu, vv = np.meshgrid(u, v)
    uv = np.stack([uu, vv], axis=-1)
    if frame is None:
        if time is None:
            raise ValueError("give a frame index or a time")
        t = np.full(vv.shape, float(time))
    else:
        t = row_times(camera, frame, vv, frame_rate=frame_rate)
    return _trace_points(camera, uv, t, fields, knot_times, grid,
                         step=grid.voxel_size if step is None else step, n_ambient=n_ambient, clip_box=clip_box)


def trace_cells(camera: Camera, flow_grid: FlowGrid, fields: np.ndarray, knot_times: np.ndarray, grid: Grid, *,
                time: float, step: float | None = None, n_ambient: float = 1.00029, clip_box=None) -> LatticeTrace:
    """Exact ``d_in``, ``d_out`` and ``delta`` of the rays through the flow-grid cell centres at one instant."""
    uv = flow_grid.pixel_centres()
    t = np.full(uv.shape[:-1], float(time))
    return _trace_points(camera, uv, t, fields, knot_times, grid,
                         step=grid.voxel_size if step is None else step, n_ambient=n_ambient, clip_box=clip_box)


# --------------------------------------------------------------------------------------
# rendering kernel
# --------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _bs3(t):
    t2 = t * t
    t3 = t2 * t
    return ((1.0 - t) ** 3 / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
            (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0)


@njit(cache=True)
def _spline_eval(coef, x, y):
    """Cubic B-spline (prefiltered coefficients ``coef`` (ny, nx, 2)) at lattice coordinates."""
    ny = coef.shape[0]
    nx = coef.shape[1]
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    wx = _bs3(x - ix)
    wy = _bs3(y - iy)
    s0 = 0.0
    s1 = 0.0
    for a in range(4):
        yy = min(max(iy + a - 1, 0), ny - 1)
        for b in range(4):
            xx = min(max(ix + b - 1, 0), nx - 1)
            w = wy[a] * wx[b]
            s0 += w * coef[yy, xx, 0]
            s1 += w * coef[yy, xx, 1]
    return s0, s1


@njit(cache=True, parallel=True)
def _render_block(r0, r1, c0, c1, s, has_delta, dcoef, lat_o, lat_s, kinv, use_xy, xycoef, hom,
                  tile, inv_sp, oa, ob, wts, kind, dots, dot_par, mean, contrast, img, dmean):
    inv_s = 1.0 / s
    inv_ls = 1.0 / lat_s
    for r in prange(r0, r1):
        for c in range(c0, c1):
            acc = 0.0
            dx_acc = 0.0
            dy_acc = 0.0
            for i in range(s):
                v = r - 0.5 + (i + 0.5) * inv_s
                for j in range(s):
                    u = c - 0.5 + (j + 0.5) * inv_s
                    du = 0.0
                    dv = 0.0
                    if has_delta:
                        du, dv = _spline_eval(dcoef, (u - lat_o) * inv_ls, (v - lat_o) * inv_ls)
                    qu = u + du
                    qv = v + dv
                    if use_xy:
                        x, y = _spline_eval(xycoef, (qu - lat_o) * inv_ls, (qv - lat_o) * inv_ls)
                    else:
                        x = kinv[0, 0] * qu + kinv[0, 1] * qv + kinv[0, 2]
                        y = kinv[1, 0] * qu + kinv[1, 1] * qv + kinv[1, 2]
                    num_a = hom[3] * x + hom[4] * y + hom[5]
                    num_b = hom[6] * x + hom[7] * y + hom[8]
                    den = hom[9] * x + hom[10] * y + hom[11]
                    a = hom[0] + hom[2] * num_a / den
                    b = hom[1] + hom[2] * num_b / den
                    val = 0.0
                    if kind == 0:
                        for k in range(inv_sp.shape[0]):
                            val += wts[k] * _noise_at(tile, a * inv_sp[k] + oa[k], b * inv_sp[k] + ob[k])
                    else:
                        val = _dots_at(dots, a * inv_sp[0] + oa[0], b * inv_sp[0] + ob[0], dot_par)
                    acc += val
                    dx_acc += du
                    dy_acc += dv
            n = s * s
            img[r - r0, c - c0] = mean + contrast * acc / n
            dmean[r - r0, c - c0, 0] = dx_acc / n
            dmean[r - r0, c - c0, 1] = dy_acc / n


def _homography(camera: Camera, bg: Background) -> np.ndarray:
    """Plane coordinates of the straight ray with normalised direction (x, y, 1)."""
    C = camera.center
    nrm = np.cross(bg.e1, bg.e2)
    k = float((bg.point - C) @ nrm)
    u1 = camera.R @ bg.e1
    u2 = camera.R @ bg.e2
    un = camera.R @ nrm
    alpha = C - bg.point
    return np.concatenate([[alpha @ bg.e1, alpha @ bg.e2, k], u1, u2, un]).astype(np.float64)


def _xy_lattice(camera: Camera, lattice: Lattice) -> np.ndarray:
    u, v = lattice.coords()
    uu, vv = np.meshgrid(u, v)
    xy = camera.normalized(np.stack([uu, vv], axis=-1))
    return np.stack([ndimage.spline_filter(xy[..., k], order=3, mode="mirror") for k in range(2)], axis=-1)


class _CameraRenderer:
    """Per-camera constants of the kernel (homography, undistortion lattice)."""

    def __init__(self, camera: Camera, bg: Background, lattice: Lattice):
        self.camera = camera
        self.bg = bg
        self.lattice = lattice
        self.hom = _homography(camera, bg)
        self.kinv = np.linalg.inv(camera.K)[:2].copy()
        self.use_xy = camera.has_distortion
        self.xycoef = _xy_lattice(camera, lattice) if self.use_xy else np.zeros((1, 1, 2))

    def render(self, rows: slice, cols: slice, supersample: int, dcoef: np.ndarray | None):
        r0, r1 = rows.start, rows.stop
        c0, c1 = cols.start, cols.stop
        img = np.empty((r1 - r0, c1 - c0))
        dmean = np.zeros((r1 - r0, c1 - c0, 2))
        has = dcoef is not None
        tile, inv, oa, ob, w = self.bg.kernel_args()
        kind, dots, dot_par = self.bg.texture_args()
        _render_block(r0, r1, c0, c1, int(supersample), has, dcoef if has else np.zeros((1, 1, 2)),
                      self.lattice.origin, float(self.lattice.stride), self.kinv, self.use_xy, self.xycoef,
                      self.hom, tile, inv, oa, ob, w, kind, dots, dot_par, self.bg.mean, self.bg.contrast, img, dmean)
        return img, dmean


_RENDERERS: dict[tuple[int, int, int], _CameraRenderer] = {}


def _renderer(camera: Camera, bg: Background, lattice: Lattice) -> _CameraRenderer:
    key = (id(camera), id(bg), hash(lattice))
    r = _RENDERERS.get(key)
    if r is None or r.camera is not camera or r.bg is not bg:
        if len(_RENDERERS) > 64:
            _RENDERERS.clear()
        r = _CameraRenderer(camera, bg, lattice)
        _RENDERERS[key] = r
    return r


def reference_image(camera: Camera, bg: Background, *, supersample: int = 3, stride: int = 3) -> np.ndarray:
    """Noise-free reference (no flow): pixel-area mean of the pattern, shape (H, W) float64 grey levels."""
    lat = make_lattice(camera.image_size, stride)
    img, _ = _renderer(camera, bg, lat).render(slice(0, camera.height), slice(0, camera.width), supersample, None)
    return img


def render_image(camera: Camera, bg: Background, trace: LatticeTrace, lattice: Lattice, reference: np.ndarray, *,
                 supersample: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free frame through the flow, and the pixel-mean deflection.

    Parameters
    ----------
    camera, bg :
    trace : LatticeTrace
        :func:`trace_lattice` of this camera-frame.
    lattice : Lattice
    reference : ndarray, shape (H, W)
        :func:`reference_image` of the camera (used where the flow is zero).
    supersample : int

    Returns
    -------
    image : ndarray, shape (H, W) float64
        Grey levels (8-bit scale, not clipped).
    delta : ndarray, shape (H, W, 2) float32
        Mean deflection over each pixel's sub-positions (pixels).
    """
    H, W = camera.height, camera.width
    image = reference.copy()
    delta = np.zeros((H, W, 2), dtype=np.float32)
    if not np.any(trace.marched):
        return image, delta
    iy, ix = np.nonzero(trace.marched)
    y0 = max(iy.min() - DILATE, 0)
    y1 = min(iy.max() + DILATE, lattice.ny - 1)
    x0 = max(ix.min() - DILATE, 0)
    x1 = min(ix.max() + DILATE, lattice.nx - 1)
    u, v = lattice.coords()
    r0 = max(int(np.floor(v[y0])), 0)
    r1 = min(int(np.ceil(v[y1])) + 1, H)
    c0 = max(int(np.floor(u[x0])), 0)
    c1 = min(int(np.ceil(u[x1])) + 1, W)
    if r1 <= r0 or c1 <= c0:
        return image, delta
    dcoef = np.stack([ndimage.spline_filter(trace.delta[..., k], order=3, mode="mirror") for k in range(2)], axis=-1)
    img, dm = _renderer(camera, bg, lattice).render(slice(r0, r1), slice(c0, c1), supersample, dcoef)
    image[r0:r1, c0:c1] = img
    delta[r0:r1, c0:c1] = dm
    return image, delta


def render_frame(camera: Camera, bg: Background, trace: LatticeTrace, lattice: Lattice, *,
                 supersample: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free frame through the flow, every pixel rendered, and the pixel-mean deflection.

    As :func:`render_image`, for a camera whose pose differs from its reference's (a
    camera that moved: :mod:`.lab`), where no pixel equals the reference image.

    Returns
    -------
    image : ndarray, shape (H, W) float64
    delta : ndarray, shape (H, W, 2) float32
    """
    dcoef = None
    if np.any(trace.marched):
        dcoef = np.stack([ndimage.spline_filter(trace.delta[..., k], order=3, mode="mirror") for k in range(2)],
                         axis=-1)
    img, dm = _renderer(camera, bg, lattice).render(slice(0, camera.height), slice(0, camera.width), supersample,
                                                    dcoef)
    return img, dm.astype(np.float32)


def cell_average(delta: np.ndarray, flow_grid: FlowGrid) -> np.ndarray:
    """Area mean of a per-pixel field over the flow-grid cells, shape (rows, cols, C)."""
    h, w = flow_grid.shape
    f = flow_grid.factor
    d = delta[: h * f, : w * f]
    return d.reshape(h, f, w, f, -1).mean(axis=(1, 3))


def flash_rows(camera: Camera, frame: int, *, frame_rate: float, exposure: float) -> np.ndarray:
    """Rows lit by a flash at session time 0 (``docs/design.md`` strobe model).

    A row is lit when its exposure interval ``[start, start + exposure)`` contains 0,
    ``start = time_offset + frame / frame_rate + row * line_time``.

    Returns
    -------
    lit : ndarray, shape (H,) bool
    """
    start = row_times(camera, frame, np.arange(camera.height), frame_rate=frame_rate)
    return (start <= 0.0) & (start + exposure > 0.0)


def apply_flash(image: np.ndarray, lit: np.ndarray, gain: float) -> np.ndarray:
    """Add ``gain`` grey levels to the lit rows (returns a new array)."""
    out = image.copy()
    out[lit] += gain
    return out


def sensor(image: np.ndarray, *, noise: float, bit_depth: int, rng: np.random.Generator) -> np.ndarray:
    """Sensor noise and quantisation.

    Parameters
    ----------
    image : ndarray
        Grey levels on the 8-bit scale (0..255).
    noise : float
        Standard deviation of additive Gaussian noise, 8-bit grey levels (scaled by 257 for
        16-bit output).
    bit_depth : {8, 16}
    rng : numpy Generator

    Returns
    -------
    ndarray, uint8 or uint16
    """
    if bit_depth == 8:
        scale, dtype, top = 1.0, np.uint8, 255.0
    elif bit_depth == 16:
        scale, dtype, top = 257.0, np.uint16, 65535.0
    else:
        raise ValueError("bit_depth must be 8 or 16")
    x = image * scale
    if noise > 0:
        x = x + rng.normal(0.0, noise * scale, size=image.shape)
    return np.clip(np.rint(x), 0.0, top).astype(dtype)
