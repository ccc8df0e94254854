"""BOS deflection fields: dense optical flow between a reference background and a frame.

Paper section 4 ("Computing BOS deflections"): gradient-based optical flow (Lucas-Kanade,
Horn-Schunck) beats window cross-correlation on BOS data; the flow is smoothed and filtered
for outliers, computed at *full* resolution and only then downsampled to the flow grid.

Conventions (SPEC "Flow sign convention", docs/design.md):

* ``frame(p) ~= reference(p + delta)``; ``delta`` in pixels of the original image.
* Component 0 = u (x, columns), component 1 = v (y, rows).
* Images are float32 grey levels (8- or 16-bit range), indexed ``[row, column]``.

The public entry points are :func:`deflection_field` (full-resolution flow, one of several
methods behind one pyramid driver) and :func:`deflection_stage` (the per camera-frame stage
kernel: flow + outlier removal + smoothing + area downsampling to the
:class:`~schlieren.pipeline.geometry.FlowGrid`).

Why a custom warp: ``cv2.remap`` quantises sub-pixel positions to 1/32 pixel, which puts a
~0.01-0.02 px floor into any iterative flow that warps with it; BOS deflections are 0.05-1 px
and need better. The warps here use exact (float) cubic B-spline interpolation (with its
interpolating prefilter) in numba kernels, on images pre-smoothed with a Gaussian so that
the interpolant is accurate (pre-smoothing both images by the same kernel leaves a smooth
displacement field unchanged).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import asdict, dataclass, field

import cv2
import numba as nb
import numpy as np

from schlieren.pipeline.geometry import FlowGrid
from schlieren.pipeline.params import param

__all__ = [
    "FlowParams",
    "METHODS",
    "PreparedReference",
    "prepare_reference",
    "deflection_field",
    "deflection_stage",
    "remove_outliers",
    "smooth_flow",
    "downsample_flow",
    "warp_image",
    "spline_coefficients",
    "warp_coefficients",
    "warp_coefficient_rows",
    "endpoint_error",
    "invalid_pixels",
    "window_for_voxel",
]

log = logging.getLogger(__name__)

METHODS = ("lk", "hs", "dis", "correlation")


# ----------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FlowParams:
    """Parameters of the deflection stage (field names = keyword names of the kernels).

    Attributes
    ----------
    method : {"lk", "hs", "dis", "correlation"}
        Flow method (paper sec. 4 uses Lucas-Kanade).
    window : int
        LK integration window edge (full-resolution pixels, odd).
    window_type : {"box", "gaussian"}
        LK window weights: uniform box of size ``window`` or a Gaussian with
        sigma = ``window / 4`` truncated at the same size.
    levels : int
        Pyramid levels (1 = full resolution only). Each level halves the image.
    iterations : int
        Warping iterations on each coarser pyramid level (LK and HS).
    fine_iterations : int
        Warping iterations on the full-resolution level (LK and HS). Each LK step
        re-linearises every pixel around its own warp, so with a converged coarse level
        one full-resolution step reaches the accuracy of several (and costs the most); on
        the buoyant-plume phantom a second one even raised the error (0.015 -> 0.018 px).
    presmooth : float
        Gaussian sigma (pixels) applied to both images before the flow; 0 disables.
    regularisation : float
        LK Tikhonov weight ``lambda = regularisation * mean(trace T) / 2`` added to the
        structure tensor ``T``: pulls the flow of textureless windows towards zero.
    gradient : {"frame", "symmetric", "reference"}
        LK image gradient ``g``: the frame's (Scharr; structure tensor filtered once per
        level), the mean of the frame's and the warped reference's, or the warped
        reference's alone (exact B-spline derivative at ``q + d_q``; structure tensor
        re-filtered every iteration). Sensor noise in ``g`` biases LK towards zero
        (errors in variables: ``T`` gains the noise energy); a reference averaged over
        many frames has almost none.
    alpha : float
        Horn-Schunck smoothness weight (in units of the normalised image gradient).
    inner_iterations : int
        Horn-Schunck Jacobi iterations per warp.
    dis_preset : {"ultrafast", "fast", "medium"}
        OpenCV DIS preset.
    corr_window : int
        Cross-correlation interrogation window edge (pixels, even).
    corr_step : int
        Spacing of the interrogation windows (pixels); 16 with 32-pixel windows is the
        classic 50 % overlap.
    corr_taper : bool
        Hann-taper the interrogation windows (reduces edge effects; the classic top-hat
        window is ``False``).
    outlier_threshold : float
        Normalised median test threshold (Westerweel & Scarano 2005), applied on the
        flow grid (see :func:`deflection_stage`); 0 disables.
    outlier_epsilon : float
        Noise floor of the normalised median test, pixels.
    smoothing_sigma : float
        Gaussian smoothing of the flow, in full-resolution pixels (applied on the flow
        grid as ``smoothing_sigma / factor``); 0 disables.
    adaptive_sigma : float
        Structure-adaptive smoothing (see :func:`deflection_stage`): the larger Gaussian
        sigma, full-resolution pixels, used where the flow is smooth; 0 disables (the
        default: on the realistic family it cost 1.2 dB at 640x480 and its lower flow
        noise made the tomography weight chosen from the noise less reliable; the
        former default 9 px suits strong, smooth flows).
    adaptive_threshold : float
        Deviation between the large- and the ``smoothing_sigma``-smoothed flow, in units
        of its lower quartile over the image (a robust noise scale), at which the large
        scale is ``1 / e``-weighted.
    texture_correction : bool
        LK only, in :func:`deflection_stage`: remove the first-order bias of the
        texture-weighted window average where the deflection varies inside the window
        (see :func:`deflection_stage`).
    factor : int
        Area-downsampling factor to the flow grid (rows = H // factor, cols = W // factor);
        with ``auto_factor`` (the default) the largest factor a run may take.
    auto_factor : bool
        In a run: the flow grid's factor is the largest up to ``factor`` that leaves at least
        :data:`~schlieren.pipeline.tomography.binning.MIN_CELLS_PER_VOXEL` (1) flow cell per
        voxel edge at the volume (:func:`~schlieren.pipeline.tomography.binning.
        auto_flow_factor`: one sample per edge is the Nyquist rate of the linear basis).
        Rigs whose voxels span few pixels then get a finer flow grid: the realistic family
        (0.7-0.9 cells per voxel at factor 3, 2.0-2.6 pixels per voxel) takes 2, the paper's
        scale (2.7 cells at 3) keeps 3. Measured on the family (whole box / in plume, factor 3
        -> auto): tune plume1 16 cameras 43.43 / 28.72 -> 44.12 / 29.32, 8 cameras 41.77 /
        27.00 -> 42.48 / 27.61; see docs/realistic.md for every case. False: ``factor`` as
        given. The run logs and stores the factor it took (``run.flow_factor``).
    invalid_check : bool
        In :func:`deflection_stage`: find pixels that cannot carry a deflection
        (:func:`invalid_pixels`: non-finite, clipped black/white runs, textureless), give
        them zero weight in the flow (LK, HS) and return NaN on the flow-grid cells they
        dominate, instead of garbage that spreads over the window.
    texture_threshold : float
        A pixel is textureless where the local standard deviation of the image (7x7) is
        below this fraction of its median over the image.
    window_per_voxel : float
        When > 0, the pipeline sets each camera's LK window (and the support of its
        invalid-pixel check) to this many times the reconstruction voxel's footprint in
        that camera's pixels (:func:`window_for_voxel`: odd, 5 to 25 px), overriding
        ``window``: the flow then resolves what the voxels can hold, at any image size and
        voxel. Chosen on the realistic family's tune cases: 9 px at 640x480 and 11 px at
        960x720 (2.0 and 2.6 px voxels) beat 13 and 17 px; at the paper's 9 px voxels it
        gives 25 px. 0 uses ``window``.
    ici_gamma : float
        LK only (frame gradient): > 0 chooses the window per pixel by the intersection
        of confidence intervals (:func:`_lk_ici`), among odd windows from
        ``ici_min_window`` to ``window`` growing by about 1.4x; the interval half-width
        is ``ici_gamma`` predicted standard deviations (from the measured image noise).
        0 uses ``window`` everywhere. The texture correction is not applied to ICI flow.
    ici_min_window : int
        Smallest window of the ICI ladder, pixels.
    cell_solve : {"auto", "on", "off"}
        LK (frame gradient, no ICI), ``factor`` > 1, in :func:`deflection_stage`: solve
        the full-resolution level once per flow cell (window sums over the cell's pixels,
        :func:`_lk_cells`) instead of at every pixel and then averaging the cell: LK at
        the cell's centre with the window linear inside each cell, at a fraction of the
        cost (the finest level's window filtering was most of the stage; at paper scale
        deflection tasks 21 % faster, flow error in the plume 3 % lower, the phantom
        -0.07 dB). ``auto``: where the window spans at least
        :data:`CELL_SOLVE_MIN_CELLS` cells (``window >= 5 factor``: paper-scale images),
        where the cell steps are fine against the window; ``on`` / ``off``: always / never.
    """

    method: str = param("lk", unit="", choices=METHODS)
    window: int = param(17, unit="px", ge=3, le=255, odd=True)
    window_type: str = param("gaussian", choices=("box", "gaussian"))
    levels: int = param(3, unit="1", ge=1, le=8)
    iterations: int = param(2, unit="1", ge=1, le=50)
    fine_iterations: int = param(1, unit="1", ge=1, le=50)
    presmooth: float = param(0.6, unit="px", ge=0, le=20)
    regularisation: float = param(1e-3, unit="1", ge=0, le=1e3)
    gradient: str = param("frame", choices=("frame", "symmetric", "reference"))
    alpha: float = param(0.3, unit="1", gt=0, le=1e3)
    inner_iterations: int = param(30, unit="1", ge=1, le=1000)
    dis_preset: str = param("medium", choices=("ultrafast", "fast", "medium"))
    corr_window: int = param(32, unit="px", ge=8, le=512, even=True)
    corr_step: int = param(16, unit="px", ge=1, le=512)
    corr_taper: bool = param(False)
    outlier_threshold: float = param(3.0, unit="1", ge=0, le=100)
    outlier_epsilon: float = param(0.01, unit="px", ge=0, le=10)
    smoothing_sigma: float = param(0.5, unit="px", ge=0, le=100)
    adaptive_sigma: float = param(0.0, unit="px", ge=0, le=200)
    adaptive_threshold: float = param(3.0, unit="1", gt=0, le=100)
    texture_correction: bool = param(True)
    factor: int = param(3, unit="px per flow cell", ge=1, le=32)
    auto_factor: bool = param(True)
    invalid_check: bool = param(True)
    texture_threshold: float = param(0.1, unit="1", ge=0, le=1)
    window_per_voxel: float = param(3.8, unit="1", ge=0, le=50)
    ici_gamma: float = param(0.0, unit="1", ge=0, le=10)
    ici_min_window: int = param(5, unit="px", ge=3, le=255, odd=True)
    cell_solve: str = param("auto", choices=("auto", "on", "off"))

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"FlowParams.method must be one of {METHODS}, got {self.method!r}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"FlowParams.window must be odd and >= 3, got {self.window}")
        if self.levels < 1 or self.iterations < 1 or self.fine_iterations < 1:
            raise ValueError("FlowParams.levels, iterations and fine_iterations must be >= 1")
        if self.gradient not in ("frame", "symmetric", "reference"):
            raise ValueError("FlowParams.gradient must be 'frame', 'symmetric' or 'reference', "
                             f"got {self.gradient!r}")
        if self.factor < 1:
            raise ValueError(f"FlowParams.factor must be >= 1, got {self.factor}")

    def reference_kwargs(self) -> dict:
        """Keyword arguments of :func:`prepare_reference` taken from these parameters."""
        return {"presmooth": self.presmooth, "levels": self.levels}

    def field_kwargs(self) -> dict:
        """Keyword arguments of :func:`deflection_field` taken from these parameters."""
        d = asdict(self)
        for k in ("outlier_threshold", "outlier_epsilon", "smoothing_sigma", "adaptive_sigma",
                  "adaptive_threshold", "texture_correction", "factor", "auto_factor", "invalid_check",
                  "texture_threshold", "window_per_voxel", "cell_solve"):
            d.pop(k)
        return d


# ----------------------------------------------------------------------------------------
# numba kernels
# ----------------------------------------------------------------------------------------
_F32 = np.float32
_PAD = 2  # border of the padded spline-coefficient arrays


@nb.njit(inline="always", fastmath=True)
def _bspline_weights(t):
    # cubic B-spline weights for offsets -1, 0, 1, 2 at fractional t (float32)
    s = _F32(1.0) - t
    t2 = t * t
    t3 = t2 * t
    w0 = s * s * s * _F32(1.0 / 6.0)
    w3 = t3 * _F32(1.0 / 6.0)
    w1 = _F32(2.0 / 3.0) - t2 + _F32(0.5) * t3
    w2 = _F32(1.0) - w0 - w1 - w3
    return w0, w1, w2, w3


@nb.njit(inline="always", fastmath=True)
def _bspline_at(cp, x, y, Wm, Hm):
    # Cubic B-spline interpolation at image coordinate (x, y) from coefficients ``cp``
    # padded by _PAD on every side (see _spline_coefficients); the position is clamped
    # to [0, Wm] x [0, Hm] (Wm = W - 1, Hm = H - 1).
    x = min(max(x, _F32(0.0)), Wm)
    y = min(max(y, _F32(0.0)), Hm)
    x0 = int(x)
    y0 = int(y)
    ax0, ax1, ax2, ax3 = _bspline_weights(x - _F32(x0))
    ay0, ay1, ay2, ay3 = _bspline_weights(y - _F32(y0))
    k = x0 + 1  # padded column of image column x0 - 1
    r0 = cp[y0 + 1]
    r1 = cp[y0 + 2]
    r2 = cp[y0 + 3]
    r3 = cp[y0 + 4]
    return (ay0 * (ax0 * r0[k] + ax1 * r0[k + 1] + ax2 * r0[k + 2] + ax3 * r0[k + 3])
            + ay1 * (ax0 * r1[k] + ax1 * r1[k + 1] + ax2 * r1[k + 2] + ax3 * r1[k + 3])
            + ay2 * (ax0 * r2[k] + ax1 * r2[k + 1] + ax2 * r2[k + 2] + ax3 * r2[k + 3])
            + ay3 * (ax0 * r3[k] + ax1 * r3[k + 1] + ax2 * r3[k + 2] + ax3 * r3[k + 3]))


@nb.njit(fastmath=True, cache=True, nogil=True)
def _warp_kernel(cp, u, v, out):
    H, W = out.shape
    Wm = _F32(W - 1)
    Hm = _F32(H - 1)
    for r in range(H):
        fr = _F32(r)
        for c in range(W):
            out[r, c] = _bspline_at(cp, _F32(c) + u[r, c], fr + v[r, c], Wm, Hm)


@nb.njit(fastmath=True, cache=True, nogil=True)
def _warp_rows_kernel(cp, rows, u, v, out):
    """:func:`_warp_kernel` for the image rows ``rows`` only (``u``, ``v``, ``out``: one row each)."""
    W = out.shape[1]
    Wm = _F32(W - 1)
    Hm = _F32(cp.shape[0] - 2 * _PAD - 1)
    for q in range(rows.shape[0]):
        fr = _F32(rows[q])
        for c in range(W):
            out[q, c] = _bspline_at(cp, _F32(c) + u[q, c], fr + v[q, c], Wm, Hm)


@nb.njit(fastmath=True, cache=True, nogil=True)
def _lk_residual_kernel(cp, frame, gx, gy, u, v, ex, ey):
    # e = frame - ref(q + d(q)) + g . d(q); returns gx * e, gy * e.
    # Per row: first the B-spline indices and weights (a loop LLVM vectorises), then the
    # 4x4 gathers; ~30 % faster than evaluating _bspline_at pixel by pixel.
    H, W = frame.shape
    Wm = _F32(W - 1)
    Hm = _F32(H - 1)
    ix = np.empty(W, np.int64)
    iy = np.empty(W, np.int64)
    wx = np.empty((4, W), np.float32)
    wy = np.empty((4, W), np.float32)
    sixth = _F32(1.0 / 6.0)
    for r in range(H):
        fr = _F32(r)
        for c in range(W):
            x = min(max(_F32(c) + u[r, c], _F32(0.0)), Wm)
            y = min(max(fr + v[r, c], _F32(0.0)), Hm)
            x0 = np.floor(x)
            y0 = np.floor(y)
            tx = x - x0
            ty = y - y0
            ix[c] = int(x0) + 1  # padded column of image column x0 - 1
            iy[c] = int(y0) + 1
            s = _F32(1.0) - tx
            t2 = tx * tx
            t3 = t2 * tx
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + _F32(0.5) * t3
            wx[0, c] = a0
            wx[1, c] = a1
            wx[2, c] = _F32(1.0) - a0 - a1 - a3
            wx[3, c] = a3
            s = _F32(1.0) - ty
            t2 = ty * ty
            t3 = t2 * ty
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + _F32(0.5) * t3
            wy[0, c] = a0
            wy[1, c] = a1
            wy[2, c] = _F32(1.0) - a0 - a1 - a3
            wy[3, c] = a3
        for c in range(W):
            k = ix[c]
            rr = iy[c]
            acc = _F32(0.0)
            for j in range(4):
                row = cp[rr + j]
                acc += wy[j, c] * (wx[0, c] * row[k] + wx[1, c] * row[k + 1]
                                   + wx[2, c] * row[k + 2] + wx[3, c] * row[k + 3])
            uu = u[r, c]
            vv = v[r, c]
            g1 = gx[r, c]
            g2 = gy[r, c]
            e = frame[r, c] - acc + g1 * uu + g2 * vv
            ex[r, c] = g1 * e
            ey[r, c] = g2 * e


@nb.njit(fastmath=True, cache=True, nogil=True)
def _lk_residual_grad_kernel(cp, frame, fgx, fgy, u, v, mix, gx, gy, ex, ey):
    # As _lk_residual_kernel, with the gradient g = mix * grad ref(q + d_q) + (1 - mix) *
    # frame gradient (fgx, fgy), the reference gradient being the exact derivative of the
    # cubic B-spline at the warped position; writes g to (gx, gy) and g * e to (ex, ey).
    H, W = frame.shape
    Wm = _F32(W - 1)
    Hm = _F32(H - 1)
    ix = np.empty(W, np.int64)
    iy = np.empty(W, np.int64)
    wx = np.empty((4, W), np.float32)
    wy = np.empty((4, W), np.float32)
    dx = np.empty((4, W), np.float32)
    dy = np.empty((4, W), np.float32)
    sixth = _F32(1.0 / 6.0)
    half = _F32(0.5)
    m1 = _F32(1.0) - mix
    for r in range(H):
        fr = _F32(r)
        for c in range(W):
            x = min(max(_F32(c) + u[r, c], _F32(0.0)), Wm)
            y = min(max(fr + v[r, c], _F32(0.0)), Hm)
            x0 = np.floor(x)
            y0 = np.floor(y)
            tx = x - x0
            ty = y - y0
            ix[c] = int(x0) + 1
            iy[c] = int(y0) + 1
            s = _F32(1.0) - tx
            t2 = tx * tx
            t3 = t2 * tx
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + half * t3
            wx[0, c] = a0
            wx[1, c] = a1
            wx[2, c] = _F32(1.0) - a0 - a1 - a3
            wx[3, c] = a3
            d0 = -half * s * s
            d3 = half * t2
            d1 = _F32(1.5) * t2 - _F32(2.0) * tx
            dx[0, c] = d0
            dx[1, c] = d1
            dx[2, c] = -d0 - d1 - d3
            dx[3, c] = d3
            s = _F32(1.0) - ty
            t2 = ty * ty
            t3 = t2 * ty
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + half * t3
            wy[0, c] = a0
            wy[1, c] = a1
            wy[2, c] = _F32(1.0) - a0 - a1 - a3
            wy[3, c] = a3
            d0 = -half * s * s
            d3 = half * t2
            d1 = _F32(1.5) * t2 - _F32(2.0) * ty
            dy[0, c] = d0
            dy[1, c] = d1
            dy[2, c] = -d0 - d1 - d3
            dy[3, c] = d3
        for c in range(W):
            k = ix[c]
            rr = iy[c]
            acc = _F32(0.0)
            accx = _F32(0.0)
            accy = _F32(0.0)
            for j in range(4):
                row = cp[rr + j]
                h = (wx[0, c] * row[k] + wx[1, c] * row[k + 1]
                     + wx[2, c] * row[k + 2] + wx[3, c] * row[k + 3])
                hd = (dx[0, c] * row[k] + dx[1, c] * row[k + 1]
                      + dx[2, c] * row[k + 2] + dx[3, c] * row[k + 3])
                acc += wy[j, c] * h
                accx += wy[j, c] * hd
                accy += dy[j, c] * h
            g1 = mix * accx + m1 * fgx[r, c]
            g2 = mix * accy + m1 * fgy[r, c]
            e = frame[r, c] - acc + g1 * u[r, c] + g2 * v[r, c]
            gx[r, c] = g1
            gy[r, c] = g2
            ex[r, c] = g1 * e
            ey[r, c] = g2 * e


@nb.njit(fastmath=True, cache=True, nogil=True)
def _lk_solve_kernel(sxx, sxy, syy, lam, bx, by, u, v):
    # d = (T + lam I)^-1 b per pixel (2x2 closed form); singular windows give d = 0
    H, W = u.shape
    for r in range(H):
        for c in range(W):
            p = sxx[r, c] + lam
            q = sxy[r, c]
            s = syy[r, c] + lam
            det = p * s - q * q
            inv = _F32(1.0) / det if det > _F32(0.0) else _F32(0.0)
            b1 = bx[r, c]
            b2 = by[r, c]
            u[r, c] = (s * b1 - q * b2) * inv
            v[r, c] = (p * b2 - q * b1) * inv


@nb.njit(fastmath=True, cache=True, nogil=True)
def _ici_kernel(sxx, sxy, syy, lam, bx, by, mxx, mxy, myy, s2, gamma, code, lo, hi, alive, u, v, chosen, sd):
    # One window of the ICI rule: d_w = (T + lam I)^-1 b, Var(d_w) = s2 (T+lam)^-1 M (T+lam)^-1.
    # A pixel keeps d_w while its interval [d_w - gamma sd, d_w + gamma sd] still meets the
    # intersection of every smaller window's interval (per component); once it does not,
    # the pixel keeps its last estimate (Katkovnik's intersection of confidence intervals).
    H, W = u.shape
    for r in range(H):
        for c in range(W):
            if not alive[r, c]:
                continue
            p = sxx[r, c] + lam
            q = sxy[r, c]
            s = syy[r, c] + lam
            det = p * s - q * q
            if det <= _F32(0.0):
                continue
            inv = _F32(1.0) / det
            a = s * inv          # (T + lam)^-1 = [[a, b], [b, d]]
            b = -q * inv
            d = p * inv
            du = a * bx[r, c] + b * by[r, c]
            dv = b * bx[r, c] + d * by[r, c]
            m1 = mxx[r, c]
            m2 = mxy[r, c]
            m3 = myy[r, c]
            vu = a * (a * m1 + b * m2) + b * (a * m2 + b * m3)
            vv = b * (b * m1 + d * m2) + d * (b * m2 + d * m3)
            su = gamma * np.sqrt(max(vu * s2, _F32(0.0)))
            sv = gamma * np.sqrt(max(vv * s2, _F32(0.0)))
            l0 = max(lo[r, c, 0], du - su)
            h0 = min(hi[r, c, 0], du + su)
            l1 = max(lo[r, c, 1], dv - sv)
            h1 = min(hi[r, c, 1], dv + sv)
            if l0 <= h0 and l1 <= h1:
                lo[r, c, 0] = l0
                hi[r, c, 0] = h0
                lo[r, c, 1] = l1
                hi[r, c, 1] = h1
                u[r, c] = du
                v[r, c] = dv
                chosen[r, c] = code
                sd[r, c] = np.sqrt(max((vu + vv) * s2, _F32(0.0)))
            else:
                alive[r, c] = False


@nb.njit(fastmath=True, cache=True, nogil=True)
def _block_moments_kernel(ga, gb, f, out):
    # Per f x f block (i, j) of the flow grid and channel q: the block sum of q, of q * xl
    # and of q * yl, where (xl, yl) is the pixel offset from the block centre. out: (3,
    # rows, cols, k): out[0] = sums, out[1] = x-moments, out[2] = y-moments. k = 3: the
    # channels are the products (a a, a b, b b) of the inputs (the structure tensor from
    # gx, gy); k = 2: the inputs themselves (a, b).
    _, rows, cols, k = out.shape
    c0 = _F32(0.5) * _F32(f - 1)
    products = k == 3
    for i in range(rows):
        for j in range(cols):
            s0 = s1 = s2 = x0 = x1 = x2 = y0 = y1 = y2 = _F32(0.0)
            for dr in range(f):
                yl = _F32(dr) - c0
                ra = ga[i * f + dr]
                rb = gb[i * f + dr]
                for dc in range(f):
                    xl = _F32(dc) - c0
                    a = ra[j * f + dc]
                    b = rb[j * f + dc]
                    if products:
                        p0 = a * a
                        p1 = a * b
                        p2 = b * b
                    else:
                        p0 = a
                        p1 = b
                        p2 = _F32(0.0)
                    s0 += p0
                    s1 += p1
                    s2 += p2
                    x0 += p0 * xl
                    x1 += p1 * xl
                    x2 += p2 * xl
                    y0 += p0 * yl
                    y1 += p1 * yl
                    y2 += p2 * yl
            out[0, i, j, 0] = s0
            out[0, i, j, 1] = s1
            out[1, i, j, 0] = x0
            out[1, i, j, 1] = x1
            out[2, i, j, 0] = y0
            out[2, i, j, 1] = y1
            if products:
                out[0, i, j, 2] = s2
                out[1, i, j, 2] = x2
                out[2, i, j, 2] = y2


@nb.njit(fastmath=True, cache=True, nogil=True)
def _texture_bias_kernel(T, Sx, Sy, flow, inv_f, bu, bv):
    # b = T^-1 (Sx J[:, 0] + Sy J[:, 1]); J = central differences of the smoothed flow
    # (one-sided at the edges), divided by the factor f (grid cells -> image pixels).
    rows, cols = bu.shape
    for i in range(rows):
        i0 = max(i - 1, 0)
        i1 = min(i + 1, rows - 1)
        for j in range(cols):
            j0 = max(j - 1, 0)
            j1 = min(j + 1, cols - 1)
            sx = inv_f / _F32(max(j1 - j0, 1))
            sy = inv_f / _F32(max(i1 - i0, 1))
            ux = (flow[i, j1, 0] - flow[i, j0, 0]) * sx
            vx = (flow[i, j1, 1] - flow[i, j0, 1]) * sx
            uy = (flow[i1, j, 0] - flow[i0, j, 0]) * sy
            vy = (flow[i1, j, 1] - flow[i0, j, 1]) * sy
            r1 = Sx[i, j, 0] * ux + Sx[i, j, 1] * vx + Sy[i, j, 0] * uy + Sy[i, j, 1] * vy
            r2 = Sx[i, j, 1] * ux + Sx[i, j, 2] * vx + Sy[i, j, 1] * uy + Sy[i, j, 2] * vy
            p = T[i, j, 0]
            q = T[i, j, 1]
            s = T[i, j, 2]
            det = p * s - q * q
            if det > _F32(1e-6) * (p + s) * (p + s):
                inv = _F32(1.0) / det
                bu[i, j] = (s * r1 - q * r2) * inv
                bv[i, j] = (p * r2 - q * r1) * inv
            else:
                bu[i, j] = _F32(0.0)
                bv[i, j] = _F32(0.0)


@nb.njit(cache=True, nogil=True)  # no fastmath: the operations in this order, bit for bit
def _prolong_row(s0, s1, b, out):
    # One row of _prolong_kernel from the coarse rows s0 (y0) and s1 (y1): output column c
    # reads coarse columns x0 = c // 2 and x0 + 1 (clamped) at a = 0 (even c) or 1/2.
    w = s0.shape[0]
    W = out.shape[0]
    half = _F32(0.5)
    zero = _F32(0.0)
    two = _F32(2.0)
    n = min(w - 1, W // 2)
    for k in range(n):  # interior: columns 2k (a = 0) and 2k + 1 (a = 1/2), no clamping
        p0 = s0[k]
        p1 = s1[k]
        d0 = s0[k + 1] - p0
        d1 = s1[k + 1] - p1
        i0 = p0 + zero * d0
        i1 = p1 + zero * d1
        out[2 * k] = (i0 + b * (i1 - i0)) * two
        i0 = p0 + half * d0
        i1 = p1 + half * d1
        out[2 * k + 1] = (i0 + b * (i1 - i0)) * two
    for c in range(2 * n, W):  # the right edge (BORDER_REPLICATE)
        x0 = min(c // 2, w - 1)
        x1 = min(c // 2 + 1, w - 1)
        a = half if c % 2 else zero
        p0 = s0[x0]
        p1 = s1[x0]
        i0 = p0 + a * (s0[x1] - p0)
        i1 = p1 + a * (s1[x1] - p1)
        out[c] = (i0 + b * (i1 - i0)) * two


@nb.njit(cache=True, nogil=True)
def _prolong_kernel(u, v, uo, vo):
    # prolong_flow of float32 (u, v): cv2.warpAffine (INTER_LINEAR, BORDER_REPLICATE) at the
    # source position (c / 2, r / 2), times 2, in one pass (the two warps and the two
    # products took 7 ms of a paper-scale deflection task, this 0.3 ms). OpenCV
    # interpolates as a lerp along x, then along y: i0 = p00 + a (p01 - p00),
    # i1 = p10 + a (p11 - p10), i0 + b (i1 - i0); with a, b in {0, 1/2} every product is
    # exact, so this is OpenCV's result bit for bit (tests/pipeline/test_flow.py checks it
    # against cv2 on odd and even sizes).
    h = u.shape[0]
    H = uo.shape[0]
    half = _F32(0.5)
    for r in range(H):
        y0 = min(r // 2, h - 1)
        y1 = min(r // 2 + 1, h - 1)
        b = half if r % 2 else _F32(0.0)
        _prolong_row(u[y0], u[y1], b, uo[r])
        _prolong_row(v[y0], v[y1], b, vo[r])


# ----------------------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------------------
def _as_image(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey image (rows, columns), got shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _normalisation(img: np.ndarray) -> tuple[float, float]:
    """Mean and 1/std of the finite pixels (every 4th row and column)."""
    sub = img[::4, ::4]
    fin = sub[np.isfinite(sub)]
    if fin.size == 0:
        return 0.0, 1.0
    std = float(fin.std())
    return float(fin.mean()), (1.0 / std if std > 0 else 1.0)


def _fill_nonfinite(img: np.ndarray, value: float) -> np.ndarray:
    """``img`` with NaN / inf pixels set to ``value`` (the same array when all are finite)."""
    bad = ~np.isfinite(img)
    if bad.any():
        img = np.where(bad, np.float32(value), img)
    return img


def invalid_pixels(image: np.ndarray, *, texture_threshold: float = 0.1, size: int = 7,
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
                c4 = cv2.bitwise_and(cv2.compare(x, value, how), 4)
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


def _nearest_fill(a: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """``a`` (h, w, ...) with the ``bad`` cells replaced by their nearest good cell."""
    if not bad.any() or bad.all():
        return a
    from scipy import ndimage

    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return a[idx[0], idx[1]]


def _gaussian_taps(sigma: float) -> np.ndarray:
    r = max(1, int(np.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def _standardise(img: np.ndarray, mean: float, scale: float, presmooth: float) -> np.ndarray:
    """``(img - mean) * scale``, Gaussian pre-smoothed with ``presmooth`` (one OpenCV pass)."""
    if presmooth > 0:
        k = _gaussian_taps(presmooth)
        return cv2.sepFilter2D(img, cv2.CV_32F, k * np.float32(scale), k,
                               delta=-mean * scale, borderType=cv2.BORDER_REFLECT)
    return (img - np.float32(mean)) * np.float32(scale)


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    pyr = [img]
    for _ in range(levels - 1):
        if min(pyr[-1].shape) < 16:
            break
        pyr.append(cv2.pyrDown(pyr[-1], borderType=cv2.BORDER_REFLECT))
    return pyr


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Scharr derivative (rotationally accurate 3x3), scaled to units of grey / pixel.
    gx = cv2.Scharr(img, cv2.CV_32F, 1, 0, scale=1.0 / 32.0, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Scharr(img, cv2.CV_32F, 0, 1, scale=1.0 / 32.0, borderType=cv2.BORDER_REFLECT)
    return gx, gy


def _window_taps(window: int, window_type: str) -> np.ndarray:
    if window_type == "box":
        return np.full(window, 1.0 / window, np.float32)
    if window_type == "gaussian":
        x = np.arange(window) - (window - 1) / 2.0
        k = np.exp(-0.5 * (x / (window / 4.0)) ** 2)
        return (k / k.sum()).astype(np.float32)
    raise ValueError(f"window_type must be 'box' or 'gaussian', got {window_type!r}")


def _block_window_taps(window: int, window_type: str, f: int) -> np.ndarray:
    """LK window weights per f x f block: ``w~_k`` = mean of the window over the pixel
    offsets ``f k + r - (f - 1) / 2`` of block ``k`` (box: half-open extent window / 2);
    the constant part ``A`` of :func:`_block_window_linear_taps`."""
    return _block_window_linear_taps(window, window_type, f)[0]


@functools.lru_cache(maxsize=64)
def _block_window_linear_taps(window: int, window_type: str, f: int):
    """The LK window per f x f block as a line in the pixel's offset inside the block.

    For block offset ``k`` (blocks from the cell) and a pixel's offset ``rho`` from its
    block's centre (pixel offset ``f k + rho`` from the cell centre), the least-squares
    line over the block's ``f`` offsets: ``w(f k + rho) ~ A_k + B_k rho`` per axis.
    ``A`` alone is :func:`_block_window_taps` (the window constant over each block).
    Returns ``(A, B)``, both divided by ``sum(A)``; read-only, made once per window (five
    calls per deflection task took 0.4 ms)."""
    half = (window - 1) // 2
    K = (half + f // 2 + f - 1) // f
    rho = np.arange(f) - (f - 1) / 2.0
    d = (np.arange(-K, K + 1)[:, None] * f + rho[None, :]).astype(np.float64)
    if window_type == "box":
        w = (np.abs(d) <= half + 1e-9).astype(np.float64)
    else:
        w = np.where(np.abs(d) <= half + 1e-9, np.exp(-0.5 * (d / (window / 4.0)) ** 2), 0.0)
    A = w.mean(axis=1)
    r2 = float(np.sum(rho ** 2))
    B = (w * rho[None, :]).sum(axis=1) / r2 if r2 > 0 else np.zeros_like(A)
    norm = A.sum()
    A, B = (A / norm).astype(np.float32), (B / norm).astype(np.float32)
    A.flags.writeable = B.flags.writeable = False
    return A, B


def _cell_window_sums(m: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The LK window sums on the cell grid from per-cell sums ``m[0]`` and first moments
    ``m[1]`` (x), ``m[2]`` (y), shape (3, rows, cols, k), with the window linear inside each
    cell (:func:`_block_window_linear_taps`: ``A (x) A`` on the sums, ``B (x) A`` on the
    x-moments, ``A (x) B`` on the y-moments)."""
    bt = cv2.BORDER_REFLECT
    return (cv2.sepFilter2D(m[0], cv2.CV_32F, A, A, borderType=bt)
            + cv2.sepFilter2D(m[1], cv2.CV_32F, B, A, borderType=bt)
            + cv2.sepFilter2D(m[2], cv2.CV_32F, A, B, borderType=bt))


def _texture_bias(gx: np.ndarray, gy: np.ndarray, u: np.ndarray, v: np.ndarray, *,
                  window: int, window_type: str, factor: int, mom: np.ndarray | None = None,
                  linear: bool = False, T: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First-order bias of the LK window mean on the flow grid, to subtract from ``(u, v)``.

    The LK displacement of pixel ``p`` is ``T_p^-1 sum_q w(q - p) g_q g_q^T d(q)`` (see
    :func:`_lk_level`). With ``d(q) ~= d(p) + J (q - p)`` this is
    ``d(p) + T_p^-1 (S_x J[:, 0] + S_y J[:, 1])``, ``S_k = sum_q w(q - p) (q - p)_k g_q g_q^T``:
    the texture's weighted centroid is not the window centre, so wherever the deflection
    varies (``J != 0``) the window mean is shifted by a random, texture-dependent amount.
    ``T`` and ``S_k`` are evaluated at the flow-grid cell centres from per-block gradient
    moments (exact block sums; the window is taken constant inside a block, or with
    ``linear`` as the line :func:`_lk_cells` uses), ``J`` from the flow grid smoothed
    with ``sigma = window / 4`` full-resolution pixels.

    Parameters
    ----------
    gx, gy : ndarray, shape (H, W)
        Frame gradients of the finest LK level.
    u, v : ndarray, shape (rows, cols)
        LK flow on the flow grid (pixels).
    mom : ndarray, shape (3, rows, cols, 3), optional
        The block moments of ``g g^T`` (computed here when not given).
    linear : bool
        The flow comes from :func:`_lk_cells` (its window, linear inside each cell: at
        paper scale the flow's RMS error in the plume 0.02182 -> 0.02170 px against the
        constant-per-block model).
    T : ndarray, shape (rows, cols, 3), optional
        With ``linear``: the window sums of ``g g^T`` that :func:`_lk_cells` solved with
        (computed here when not given).

    Returns
    -------
    bu, bv : ndarray, shape (rows, cols), float32
        Bias in pixels.
    """
    f = int(factor)
    rows, cols = u.shape
    if mom is None:  # (:func:`_lk_cells` hands over the moments it computed)
        mom = np.empty((3, rows, cols, 3), np.float32)
        _block_moments_kernel(gx, gy, f, mom)
    kt = _block_window_taps(window, window_type, f)
    K = (len(kt) - 1) // 2
    km = kt * (f * np.arange(-K, K + 1)).astype(np.float32)

    def filt(a, kx, ky):  # correlation: out(p) = sum_k kx[k] ky[l] a(p + (k - K, l - K))
        return cv2.sepFilter2D(a, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REFLECT)

    if linear:
        # the window of :func:`_lk_cells`: w(f k + rho) ~ A_k + B_k rho per axis. With the
        # pixel offset f k + rho, sum w (q - p)_x g g^T ~ (f k A_k + B_k (f^2 - 1) / 12) (x) A
        # on the block sums + (A_k + f k B_k) (x) A on the x-moments + f k A_k (x) B on the
        # y-moments (the texture taken even inside a block for the second moment)
        A, B = _block_window_linear_taps(window, window_type, f)
        fk = (f * np.arange(-K, K + 1)).astype(np.float32)
        k1 = fk * A + B * np.float32((f * f - 1) / 12.0)
        k2 = A + fk * B
        if T is None:
            T = _cell_window_sums(mom, A, B)
        Sx = filt(mom[0], k1, A) + filt(mom[1], k2, A) + filt(mom[2], fk * A, B)
        Sy = filt(mom[0], A, k1) + filt(mom[2], A, k2) + filt(mom[1], B, fk * A)
    else:
        T = filt(mom[0], kt, kt)  # (rows, cols, 3): xx, xy, yy
        Sx = filt(mom[0], km, kt) + filt(mom[1], kt, kt)
        Sy = filt(mom[0], kt, km) + filt(mom[2], kt, kt)
    sig = window / 4.0 / f
    flow = cv2.GaussianBlur(np.dstack([u, v]), (0, 0), sig, borderType=cv2.BORDER_REFLECT)
    bu = np.empty((rows, cols), np.float32)
    bv = np.empty((rows, cols), np.float32)
    _texture_bias_kernel(T, Sx, Sy, flow, np.float32(1.0 / f), bu, bv)
    return bu, bv


def _window_filter(a: np.ndarray, taps: np.ndarray) -> np.ndarray:
    # separable FIR (OpenCV's SIMD path is faster than boxFilter for float32)
    return cv2.sepFilter2D(a, cv2.CV_32F, taps, taps, borderType=cv2.BORDER_REFLECT)


def prolong_flow(u: np.ndarray, v: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Prolong a coarse pyramid level's flow (or motion) to the next finer level (values doubled).

    ``cv2.pyrDown`` centres coarse pixel ``i`` on fine pixel ``2 i``, so fine pixel ``x``
    reads the coarse flow at ``x / 2`` (an affine map; bilinear, edges replicated).
    """
    H, W = shape
    if u.dtype == np.float32 and v.dtype == np.float32 and u.ndim == 2 and u.shape == v.shape:
        # float32 (the flow): one pass of :func:`_prolong_kernel`, the same numbers as below
        uu = np.empty((H, W), np.float32)
        vv = np.empty((H, W), np.float32)
        _prolong_kernel(np.ascontiguousarray(u), np.ascontiguousarray(v), uu, vv)
        return uu, vv
    M = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]], np.float64)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    uu = cv2.warpAffine(u, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    vv = cv2.warpAffine(v, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    return uu * np.float32(2.0), vv * np.float32(2.0)


_BSPLINE_POLE = np.sqrt(3.0) - 2.0
_PREFILTER_TAPS = (np.sqrt(3.0) * _BSPLINE_POLE ** np.abs(np.arange(-9, 10))).astype(np.float32)


def _spline_coefficients(img: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients of an image (interpolating prefilter), padded by 2.

    The exact prefilter is the inverse of the ``[1, 4, 1] / 6`` filter, whose impulse
    response is ``sqrt(3) (sqrt(3) - 2)^|k|``; truncated at |k| = 9 its error is below
    1e-5 relative. Applied separably with OpenCV (mirror borders).
    """
    k = _PREFILTER_TAPS
    coef = cv2.sepFilter2D(img, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT_101)
    return cv2.copyMakeBorder(coef, _PAD, _PAD, _PAD, _PAD, cv2.BORDER_REFLECT_101)


def spline_coefficients(image: np.ndarray) -> np.ndarray:
    """Padded cubic B-spline coefficients of a 2-D image, for :func:`warp_coefficients`
    (prefilter once, warp many times)."""
    return _spline_coefficients(_as_image(image, "image"))


def warp_coefficients(coefficients: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """:func:`warp_image` from precomputed :func:`spline_coefficients`.

    Parameters
    ----------
    coefficients : ndarray, shape (H + 4, W + 4)
    flow : ndarray, shape (H, W, 2)

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    flow = np.asarray(flow, dtype=np.float32)
    H, W = coefficients.shape[0] - 2 * _PAD, coefficients.shape[1] - 2 * _PAD
    if flow.shape != (H, W, 2):
        raise ValueError(f"flow shape {flow.shape} does not match the image ({H}, {W})")
    out = np.empty((H, W), np.float32)
    _warp_kernel(coefficients, np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1]), out)
    return out


def warp_coefficient_rows(coefficients: np.ndarray, rows: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """:func:`warp_coefficients` evaluated on the image rows ``rows`` only.

    Parameters
    ----------
    coefficients : ndarray, shape (H + 4, W + 4)
    rows : ndarray of int, shape (R,)
    flow : ndarray, shape (R, W, 2)
        Displacements of those rows.

    Returns
    -------
    ndarray, shape (R, W), float32: the same values as ``warp_coefficients(...)[rows]``.
    """
    flow = np.asarray(flow, dtype=np.float32)
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    H, W = coefficients.shape[0] - 2 * _PAD, coefficients.shape[1] - 2 * _PAD
    if flow.shape != (len(rows), W, 2):
        raise ValueError(f"flow shape {flow.shape} does not match {len(rows)} rows of width {W}")
    if len(rows) and (rows.min() < 0 or rows.max() >= H):
        raise ValueError(f"rows must lie in [0, {H})")
    out = np.empty((len(rows), W), np.float32)
    _warp_rows_kernel(coefficients, rows, np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1]),
                      out)
    return out


def warp_image(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Sample ``image`` at ``p + flow(p)`` with exact (unquantised) cubic B-spline interpolation.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey image.
    flow : ndarray, shape (H, W, 2)
        Displacement (u, v) in pixels.

    Returns
    -------
    warped : ndarray, shape (H, W), float32
        ``warped(p) = image(p + flow(p))`` (positions clamped to the image).
    """
    img = _as_image(image, "image")
    flow = np.asarray(flow, dtype=np.float32)
    if flow.shape != img.shape + (2,):
        raise ValueError(f"flow shape {flow.shape} does not match image {img.shape}")
    out = np.empty(img.shape, np.float32)
    _warp_kernel(_spline_coefficients(img), np.ascontiguousarray(flow[..., 0]),
                 np.ascontiguousarray(flow[..., 1]), out)
    return out


# ----------------------------------------------------------------------------------------
# Prepared reference: everything that depends only on the background image
# ----------------------------------------------------------------------------------------
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
    presmooth: float
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


def prepare_reference(reference: np.ndarray, *, presmooth: float = 0.6, levels: int = 3
                      ) -> PreparedReference:
    """Pre-process a reference background for :func:`deflection_field`.

    Parameters
    ----------
    reference : ndarray, shape (H, W)
        Background without flow, grey levels.
    presmooth : float
        Gaussian sigma (pixels) applied before the flow (must match the flow parameters).
    levels : int
        Pyramid levels (must match the flow parameters).
    """
    img = _as_image(reference, "reference")
    mean, scale = _normalisation(img)
    pyr = _pyramid(_standardise(_fill_nonfinite(img, mean), mean, scale, presmooth), levels)
    coef = tuple(_spline_coefficients(p) for p in pyr)
    return PreparedReference(img, mean, scale, float(presmooth), int(levels), tuple(pyr), coef)


# ----------------------------------------------------------------------------------------
# Solvers (one pyramid level each); all share the driver in _pyramid_flow
# ----------------------------------------------------------------------------------------
def _lk_level(coef, frame, u, v, *, window, window_type, iterations, regularisation,
              gradient="frame", keep=None, weight=None, ici=None, cells=0, **_):
    """Dense Lucas-Kanade on one level, warping the reference at every iteration.

    Each pixel ``q`` of the window of ``p`` is linearised around its own current warp:
    ``ref(q + d_p) ~= ref(q + d_q) + g_q . (d_p - d_q)``, so the window normal equations
    give ``d_p = T_p^-1 sum_q w g_q (frame_q - ref(q + d_q) + g_q . d_q)``. In the linear
    regime one step returns the window-weighted true displacement (no oscillation between
    neighbouring pixels, unlike the naive incremental dense update); the iterations
    remove the linearisation error. ``g`` is the frame gradient (fixed, so the structure
    tensor is filtered once per level); the fixed point does not depend on it.
    The fixed point is the structure-tensor weighted window mean
    ``T_p^-1 sum_q w g_q g_q^T d_q`` of the true displacement (corrected to first order by
    :func:`_texture_bias`). ``keep`` (a dict) receives the level's gradients. ``weight``
    (0/1 per pixel) removes invalid pixels from every window sum (their gradient is
    zeroed, so they add neither to the structure tensor nor to the mismatch).
    ``cells`` = f > 1 (frame gradient, no ICI): solve on the f x f flow cells instead of
    every pixel and return the flow on the cell grid (:func:`_lk_cells`).
    """
    taps = _window_taps(window, window_type)
    gx, gy = _gradients(frame)
    if weight is not None:
        gx *= weight
        gy *= weight
    if cells > 1 and gradient == "frame" and ici is None:
        return _lk_cells(coef, frame, gx, gy, u, v, window=window, window_type=window_type,
                         iterations=iterations, regularisation=regularisation, f=int(cells), keep=keep)
    if gradient != "frame":
        mix = np.float32(0.5 if gradient == "symmetric" else 1.0)
        g = (np.empty_like(frame), np.empty_like(frame))
        ex = np.empty_like(frame)
        ey = np.empty_like(frame)
        for _ in range(iterations):
            _lk_residual_grad_kernel(coef, frame, gx, gy, u, v, mix, g[0], g[1], ex, ey)
            if weight is not None:
                for a in (g[0], g[1], ex, ey):
                    a *= weight
            sxx = _window_filter(g[0] * g[0], taps)
            sxy = _window_filter(g[0] * g[1], taps)
            syy = _window_filter(g[1] * g[1], taps)
            lam = np.float32(regularisation * 0.5 * (float(sxx[::4, ::4].mean())
                                                     + float(syy[::4, ::4].mean())))
            _lk_solve_kernel(sxx, sxy, syy, lam, _window_filter(ex, taps),
                             _window_filter(ey, taps), u, v)
        if keep is not None:
            keep["gx"], keep["gy"] = g
        return u, v
    if keep is not None:
        keep["gx"], keep["gy"] = gx, gy
    sxx = _window_filter(gx * gx, taps)
    sxy = _window_filter(gx * gy, taps)
    syy = _window_filter(gy * gy, taps)
    lam = np.float32(regularisation * 0.5 * (float(sxx[::4, ::4].mean()) + float(syy[::4, ::4].mean())))
    ex = np.empty_like(frame)
    ey = np.empty_like(frame)
    for _ in range(iterations):
        _lk_residual_kernel(coef, frame, gx, gy, u, v, ex, ey)
        bx = _window_filter(ex, taps)
        by = _window_filter(ey, taps)
        _lk_solve_kernel(sxx, sxy, syy, lam, bx, by, u, v)
    if ici is not None:
        u, v = _lk_ici(coef, frame, gx, gy, u, v, window_type=window_type, regularisation=regularisation, **ici)
    return u, v


def measurement_sigma(params: FlowParams) -> float:
    """RMS width (pixels, per axis) of the image averaging behind one flow-grid cell.

    A deflection on the flow grid is not the deflection of the ray through the cell centre:
    it is the LK window's weighted mean of the per-pixel deflections (``window`` taps),
    smoothed (``smoothing_sigma``) and block-averaged to the grid (``factor``). Their
    variances add: ``var(window taps) + smoothing_sigma^2 + (factor^2 - 1) / 12``. The
    tomography models this averaging (``TomoParams.model_flow_window``). Methods other
    than LK get the smoothing and block mean only.

    With the per-cell solve (:func:`uses_cell_solve`) a cell's deflection is the window
    mean around the cell's centre (the window linear over each cell's pixels,
    :func:`_block_window_linear_taps`), with no block mean after it: the variance is that
    of the piecewise-linear window plus ``smoothing_sigma^2`` (sigma 5.52 px at a 25 px
    window and factor 3, against 5.58 per pixel).
    """
    var = float(params.smoothing_sigma) ** 2
    if params.method == "lk" and uses_cell_solve(params):
        f = int(params.factor)
        A, B = (t.astype(np.float64) for t in _block_window_linear_taps(int(params.window), params.window_type, f))
        rho = np.arange(f) - (f - 1) / 2.0
        k = np.arange(len(A)) - (len(A) - 1) / 2.0
        w = A[:, None] + B[:, None] * rho[None, :]  # per pixel: block k, offset rho
        d = f * k[:, None] + rho[None, :]
        return float(np.sqrt(var + np.sum(w * d * d) / np.sum(w)))
    var += (params.factor ** 2 - 1) / 12.0
    if params.method == "lk":
        taps = _window_taps(int(params.window), params.window_type).astype(np.float64)
        x = np.arange(len(taps)) - (len(taps) - 1) / 2.0
        var += float(np.sum(taps * x * x) / np.sum(taps))
    return float(np.sqrt(var))


#: ``FlowParams.cell_solve = "auto"`` solves per cell when the LK window spans at least this
#: many flow cells (``window >= CELL_SOLVE_MIN_CELLS * factor``).
CELL_SOLVE_MIN_CELLS = 5


def uses_cell_solve(params: FlowParams) -> bool:
    """Whether :func:`deflection_stage` solves the finest LK level per flow cell (:func:`_lk_cells`)."""
    if params.cell_solve == "off" or params.method != "lk" or params.gradient != "frame" \
            or params.ici_gamma > 0 or params.factor <= 1:
        return False
    return params.cell_solve == "on" or params.window >= CELL_SOLVE_MIN_CELLS * params.factor


def window_for_voxel(px_per_voxel: float, window_per_voxel: float, *, smallest: int = 5,
                     largest: int = 25) -> int:
    """The odd LK window (pixels) spanning ``window_per_voxel`` voxel footprints."""
    w = int(round(window_per_voxel * px_per_voxel))
    w = min(max(w, smallest), largest)
    return w if w % 2 else w + 1


def ici_windows(smallest: int, largest: int, ratio: float = 1.4) -> tuple[int, ...]:
    """Odd window edges from ``smallest`` to ``largest``, growing by about ``ratio``."""
    out = [int(smallest) | 1]
    while out[-1] < largest:
        nxt = max(int(round(out[-1] * ratio)) | 1, out[-1] + 2)
        out.append(min(nxt, int(largest) | 1))
    return tuple(out)


def _lk_ici(coef, frame, gx, gy, u, v, *, windows, window_type, regularisation, gamma, info=None):
    """Per-pixel LK window by the intersection of confidence intervals (ICI).

    Around the converged pilot estimate ``(u, v)``, one more LK step is taken with every
    window of ``windows`` (small to large, sharing the linearisation), each with its
    variance ``sigma^2 (T + lam)^-1 M (T + lam)^-1`` (``M`` the structure tensor filtered
    with the squared window weights, ``sigma`` the image noise: a robust scale of the
    warped residual ``frame - ref(q + d)``). A pixel takes the largest window whose
    confidence interval (``gamma`` standard deviations) still meets those of all smaller
    windows: large windows where the deflection is smooth (less noise), small ones where
    it has fine structure (less bias). Katkovnik, Egiazarian & Astola, *Local Approximation
    Techniques in Signal and Image Processing* (2006), applied to LK's window.

    ``info`` (a dict) receives ``noise`` (image noise, standardised units), the median
    chosen window and the median predicted flow noise (pixels of this level).
    """
    H, W = frame.shape
    ex = np.empty_like(frame)
    ey = np.empty_like(frame)
    _lk_residual_kernel(coef, frame, gx, gy, u, v, ex, ey)
    warped = np.empty_like(frame)
    _warp_kernel(coef, u, v, warped)
    res = (frame - warped)[::2, ::2]
    keep_px = (gx[::2, ::2] != 0) | (gy[::2, ::2] != 0)   # invalid pixels have zeroed gradients
    res = res[keep_px] if keep_px.any() else res.ravel()
    noise = float(1.4826 * np.median(np.abs(res - np.median(res))))
    s2 = np.float32(max(noise, 1e-6) ** 2)
    gxx, gxy, gyy = gx * gx, gx * gy, gy * gy
    lo = np.full((H, W, 2), -np.inf, np.float32)
    hi = np.full((H, W, 2), np.inf, np.float32)
    alive = np.ones((H, W), np.bool_)
    chosen = np.zeros((H, W), np.int16)
    sd = np.zeros((H, W), np.float32)
    uu = u.copy()
    vv = v.copy()
    for code, w in enumerate(windows):
        taps = _window_taps(w, window_type)
        t2 = (taps * taps).astype(np.float32)
        sxx = _window_filter(gxx, taps)
        sxy = _window_filter(gxy, taps)
        syy = _window_filter(gyy, taps)
        lam = np.float32(regularisation * 0.5 * (float(sxx[::4, ::4].mean()) + float(syy[::4, ::4].mean())))
        _ici_kernel(sxx, sxy, syy, lam, _window_filter(ex, taps), _window_filter(ey, taps),
                    _window_filter(gxx, t2), _window_filter(gxy, t2), _window_filter(gyy, t2), s2,
                    np.float32(gamma), code, lo, hi, alive, uu, vv, chosen, sd)
    if info is not None:
        info["noise"] = noise
        info["window_median"] = int(np.asarray(windows)[int(np.median(chosen[::2, ::2]))])
        info["window_fraction"] = {int(w): float(np.mean(chosen[::2, ::2] == i)) for i, w in enumerate(windows)}
        info["flow_noise_px"] = float(np.median(sd[::2, ::2]))
    return uu, vv


_HS_KERNEL = np.array([[1, 2, 1], [2, 0, 2], [1, 2, 1]], np.float32) / 12.0


def _hs_level(coef, frame, u, v, *, iterations, alpha, inner_iterations, weight=None, **_):
    """Horn-Schunck (1981) with warping: Jacobi iterations on the linearised problem
    ``min sum (e - g . (d - d0))^2 + alpha^2 |grad d|^2`` around the current warp ``d0``
    (``weight`` zeroes the data term of invalid pixels; the smoothness term fills them)."""
    gx, gy = _gradients(frame)
    if weight is not None:
        gx *= weight
        gy *= weight
    a2 = np.float32(alpha * alpha)
    denom = a2 + gx * gx + gy * gy
    warped = np.empty_like(frame)
    for _ in range(iterations):
        _warp_kernel(coef, u, v, warped)
        e = frame - warped
        u0 = u.copy()
        v0 = v.copy()
        for _ in range(inner_iterations):
            ub = cv2.filter2D(u, -1, _HS_KERNEL, borderType=cv2.BORDER_REFLECT)
            vb = cv2.filter2D(v, -1, _HS_KERNEL, borderType=cv2.BORDER_REFLECT)
            r = (e - gx * (ub - u0) - gy * (vb - v0)) / denom
            u = ub + gx * r
            v = vb + gy * r
        u = np.ascontiguousarray(u, dtype=np.float32)
        v = np.ascontiguousarray(v, dtype=np.float32)
    return u, v


def _lk_cells(coef, frame, gx, gy, u, v, *, window, window_type, iterations, regularisation, f, keep=None):
    """The finest LK level solved once per f x f flow cell (the flow grid of sec. 4).

    :func:`_lk_level` solves ``d_p = T_p^-1 b_p`` at every pixel (window sums of
    ``g g^T`` and of ``g (frame - ref(q + d_q) + g . d_q)``), and the deflection stage then
    averages the f x f pixels of each flow cell. Here the window sums are taken once per
    cell, around its centre: the per-pixel products are summed over each cell with their
    first moments (offsets from the cell's centre; exact), and the window is applied on
    the cell grid as a line in the pixel's offset inside each cell
    (:func:`_block_window_linear_taps`: ``sum_q w g e ~ sum_k A_k S_k + B_k (X_k + Y_k)``,
    separably), then ``d_cell = T_cell^-1 b_cell``: LK at the cell's centre with the
    window to first order inside each cell. The full-resolution work drops from five
    window filters and a solve to one pass of block moments: the window filtering runs on
    f^2 times fewer points with f times fewer taps. With the window constant over each
    cell (the block mean of the weights alone, a staircase) the flow was 1.6 % worse in the
    plume at paper scale (RMS error 0.02266 against 0.02231 per pixel; the line: 0.02182)
    and the phantom 0.2 dB. ``u``, ``v`` (H, W) are the per-pixel warps of the residual
    (the coarser level's flow); the result is (rows, cols) = (H // f, W // f). ``keep``
    receives ``gx``, ``gy``, the block moments ``mom`` and the window sums ``T`` of
    ``g g^T`` (reused by :func:`_texture_bias`).

    The coarser pyramid levels, which only initialise the finest, are solved on f x f
    cells of their own pixels too (:func:`_pyramid_flow`; their cell flow is interpolated
    back to their pixels before it is prolonged). Measured with the staircase window, at
    1440x1080 with a 25 px window: the stage 69 instead of 79 ms, the flow's in-plume
    end-point error against the rendered truth 0.01784 px (per-pixel coarse levels
    0.01804, the per-pixel solve 0.01778; with the line window now 0.01722). With a 9 px
    window at 640x480 (which ``cell_solve: auto`` leaves per pixel) it rose from 0.0187
    to 0.0190 px.
    """
    H, W = frame.shape
    rows, cols = H // f, W // f
    mom = np.empty((3, rows, cols, 3), np.float32)
    _block_moments_kernel(gx, gy, f, mom)
    if keep is not None:
        keep["gx"], keep["gy"], keep["mom"] = gx, gy, mom
    A, B = _block_window_linear_taps(window, window_type, f)
    T = _cell_window_sums(mom, A, B)
    if keep is not None:
        keep["T"] = T
    sxx = np.ascontiguousarray(T[..., 0])
    sxy = np.ascontiguousarray(T[..., 1])
    syy = np.ascontiguousarray(T[..., 2])
    lam = np.float32(regularisation * 0.5 * (float(sxx.mean()) + float(syy.mean())))
    ex = np.empty_like(frame)
    ey = np.empty_like(frame)
    uc = np.empty((rows, cols), np.float32)
    vc = np.empty((rows, cols), np.float32)
    e2 = np.empty((3, rows, cols, 2), np.float32)
    for it in range(iterations):
        if it:  # later iterations warp every pixel by its cell's flow (bilinear)
            u, v = _upsample_cells(uc, vc, f, (H, W))
        _lk_residual_kernel(coef, frame, gx, gy, u, v, ex, ey)
        _block_moments_kernel(ex, ey, f, e2)
        b = _cell_window_sums(e2, A, B)
        _lk_solve_kernel(sxx, sxy, syy, lam, np.ascontiguousarray(b[..., 0]),
                         np.ascontiguousarray(b[..., 1]), uc, vc)
    return uc, vc


def _upsample_cells(uc: np.ndarray, vc: np.ndarray, f: int, shape: tuple[int, int]):
    """Per-pixel flow from the cell grid: cell (i, j) is centred on pixel
    ``(f i + (f - 1) / 2, f j + (f - 1) / 2)``; bilinear, edges replicated."""
    H, W = shape
    c = (f - 1) / 2.0
    M = np.array([[1.0 / f, 0.0, -c / f], [0.0, 1.0 / f, -c / f]], np.float64)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return (cv2.warpAffine(uc, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE),
            cv2.warpAffine(vc, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE))


def _pyramid_flow(level_solver, prep: PreparedReference, frame_pyr, *, iterations,
                  fine_iterations, keep=None, weights=None, cells=0, **kw):
    kw0 = kw
    h, w = prep.pyramid[-1].shape
    u = np.zeros((h, w), np.float32)
    v = np.zeros((h, w), np.float32)
    for lev in range(len(prep.pyramid) - 1, -1, -1):
        if "gradient" in kw0:  # coarse levels only initialise: frame gradient (cheapest)
            kw = dict(kw0, gradient=kw0["gradient"] if lev == 0 else "frame")
        if u.shape != prep.pyramid[lev].shape:
            u, v = prolong_flow(u, v, prep.pyramid[lev].shape)
        it = fine_iterations if lev == 0 else iterations
        w = weights[lev] if weights is not None and lev < len(weights) else None
        extra = {} if lev == 0 or "ici" not in kw else {"ici": None}
        if cells > 1:  # every level on f x f cells of its pixels; the finest returns the cell grid
            extra["cells"] = cells
        u, v = level_solver(prep.coefficients[lev], frame_pyr[lev], u, v, iterations=it,
                            keep=keep if lev == 0 else None, weight=w, **{**kw, **extra})
        if lev > 0 and cells > 1:  # a coarse level's cells -> its pixels, for the prolongation
            u, v = _upsample_cells(u, v, cells, prep.pyramid[lev].shape)
    return u, v


_DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def _dis_flow(ref, frame, *, dis_preset):
    """OpenCV DIS (Kroeger et al. 2016). DIS needs 8-bit input: both images are scaled
    with one common linear map to 0..255 and rounded, which quantises the signal."""
    lo, hi = np.percentile(ref[::2, ::2], [0.1, 99.9])
    scale = 255.0 / max(float(hi - lo), 1e-12)
    r8 = np.clip((ref - lo) * scale, 0, 255).round().astype(np.uint8)
    f8 = np.clip((frame - lo) * scale, 0, 255).round().astype(np.uint8)
    dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[dis_preset])
    # calc(I0, I1) gives I0(x) ~= I1(x + flow): I0 = frame, I1 = reference.
    flow = dis.calc(f8, r8, None)
    return np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1])


def _correlation_flow(ref, frame, *, corr_window, corr_step, corr_taper):
    """Window cross-correlation with 3-point Gaussian sub-pixel peak fit (classic BOS).

    Interrogation windows of ``corr_window`` pixels every ``corr_step`` pixels (mean
    removed, optionally Hann tapered); the displacement of each window is the peak of the circular
    cross-correlation, refined by a 3-point Gaussian fit along each axis; the window
    displacements are interpolated bilinearly to every pixel.
    """
    H, W = ref.shape
    n = int(corr_window)
    s = int(corr_step)
    if H < n or W < n:
        raise ValueError(f"image {W}x{H} smaller than the correlation window {n}")
    r0 = np.arange(0, H - n + 1, s)
    c0 = np.arange(0, W - n + 1, s)
    sw_r = np.lib.stride_tricks.sliding_window_view(ref, (n, n))[::s, ::s]
    sw_f = np.lib.stride_tricks.sliding_window_view(frame, (n, n))[::s, ::s]
    hann = np.hanning(n + 2)[1:-1] if corr_taper else np.ones(n)
    taper = np.outer(hann, hann).astype(np.float32)
    nr, nc = sw_r.shape[:2]
    U = np.zeros((nr, nc), np.float32)
    V = np.zeros((nr, nc), np.float32)
    k = np.arange(nc)
    for i in range(nr):  # one batched FFT per row of windows
        a = sw_f[i] - sw_f[i].mean(axis=(1, 2), keepdims=True)
        b = sw_r[i] - sw_r[i].mean(axis=(1, 2), keepdims=True)
        A = np.fft.rfft2(a * taper)
        B = np.fft.rfft2(b * taper)
        # c(s) = sum_p f(p) r(p + s): peak at s = delta (frame(p) = ref(p + delta))
        c = np.fft.fftshift(np.fft.irfft2(np.conj(A) * B, s=(n, n)), axes=(1, 2))
        flat = c.reshape(nc, -1).argmax(axis=1)
        pr, pc = np.unravel_index(flat, (n, n))
        pr = np.clip(pr, 1, n - 2)
        pc = np.clip(pc, 1, n - 2)
        cmax = c[k, pr, pc]
        # a window without a positive peak (textureless, or all anti-correlated) gets no
        # sub-pixel fit: the log of a non-positive floor was NaN
        peak = cmax > 0
        floor = np.where(peak, cmax * 1e-3, 1.0)

        def lg(x):
            return np.log(np.maximum(x, floor))

        def fit(lm, l0, lp):
            den = 2.0 * (lm - 2.0 * l0 + lp)
            ok = peak & (den < -1e-12)
            return np.where(ok, (lm - lp) / np.where(ok, den, -1.0), 0.0)

        l0 = lg(cmax)
        dv = fit(lg(c[k, pr - 1, pc]), l0, lg(c[k, pr + 1, pc]))
        du = fit(lg(c[k, pr, pc - 1]), l0, lg(c[k, pr, pc + 1]))
        V[i] = pr - n // 2 + np.clip(dv, -1, 1)
        U[i] = pc - n // 2 + np.clip(du, -1, 1)
    # window centres at r0 + (n - 1) / 2; interpolate to every pixel
    rc = r0 + (n - 1) / 2.0
    cc = c0 + (n - 1) / 2.0
    ir = np.interp(np.arange(H), rc, np.arange(nr)).astype(np.float32)
    ic = np.interp(np.arange(W), cc, np.arange(nc)).astype(np.float32)
    mapx, mapy = np.meshgrid(ic, ir)
    u = cv2.remap(U, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    v = cv2.remap(V, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return u, v


# ----------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------
def deflection_field(
    reference,
    frame: np.ndarray,
    *,
    method: str = "lk",
    window: int = 17,
    window_type: str = "gaussian",
    levels: int = 3,
    iterations: int = 2,
    fine_iterations: int = 1,
    presmooth: float = 0.6,
    regularisation: float = 1e-3,
    gradient: str = "frame",
    alpha: float = 0.3,
    inner_iterations: int = 30,
    dis_preset: str = "medium",
    corr_window: int = 32,
    corr_step: int = 16,
    corr_taper: bool = False,
    ici_gamma: float = 0.0,
    ici_min_window: int = 5,
) -> np.ndarray:
    """Full-resolution BOS deflection field between a reference background and a frame.

    Paper sec. 4 ("Computing BOS deflections"): dense pyramidal Lucas-Kanade (default),
    Horn-Schunck, OpenCV DIS, or window cross-correlation. Keyword parameters are those of
    :class:`FlowParams` (see there for units); each method uses its own subset.

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        Background without flow, grey levels (any range; float32 internally).
    frame : ndarray, shape (H, W)
        Image through the flow.

    Returns
    -------
    flow : ndarray, shape (H, W, 2), float32
        ``delta`` in pixels such that ``frame(p) ~= reference(p + delta)``;
        ``[..., 0]`` = u (columns), ``[..., 1]`` = v (rows).
    """
    kw = {k: val for k, val in locals().items() if k not in ("reference", "frame")}
    u, v = _flow_components(reference, frame, **kw)
    out = np.empty(u.shape + (2,), np.float32)
    out[..., 0] = u
    out[..., 1] = v
    return out


def _flow_components(reference, frame, *, method, window, window_type, levels, iterations,
                     fine_iterations, presmooth, regularisation, gradient, alpha,
                     inner_iterations, dis_preset, corr_window, corr_step, corr_taper,
                     ici_gamma=0.0, ici_min_window=5, keep=None, valid=None, info=None, cells=0):
    """:func:`deflection_field` as two (H, W) float32 arrays (u, v); for LK, ``keep``
    (a dict) receives the full-resolution frame gradients ``gx``, ``gy``. ``valid``
    (H, W) bool: pixels the flow may use (LK and HS weight the others out; every method
    gets NaN-free images). ``cells`` = f > 1 with LK (frame gradient, no ICI): the finest
    level is solved per f x f cell (:func:`_lk_cells`) and (u, v) are (H // f, W // f);
    ``keep["mom"]`` then holds the block moments. Other methods ignore it."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    frm = _as_image(frame, "frame")
    if isinstance(reference, PreparedReference):
        prep = reference
        if method in ("lk", "hs") and (prep.presmooth != presmooth or prep.levels != levels):
            raise ValueError("PreparedReference was built with presmooth="
                             f"{prep.presmooth}, levels={prep.levels}; the flow asks for "
                             f"presmooth={presmooth}, levels={levels}")
    elif method in ("lk", "hs"):
        prep = prepare_reference(reference, presmooth=presmooth, levels=levels)
    else:
        img = _as_image(reference, "reference")
        mean, scale = _normalisation(img)
        prep = PreparedReference(_fill_nonfinite(img, mean), mean, scale, 0.0, 1, (), ())
    if prep.shape != frm.shape:
        raise ValueError(f"reference {prep.shape} and frame {frm.shape} differ in shape")
    frm = _fill_nonfinite(frm, prep.mean)
    if method in ("lk", "hs"):
        fpyr = _pyramid(_standardise(frm, prep.mean, prep.scale, presmooth), len(prep.pyramid))
        weights = None if valid is None or valid.all() else _weight_pyramid(valid, len(prep.pyramid))
        if method == "lk":
            ici = None
            if ici_gamma > 0 and gradient == "frame":
                ici = {"windows": ici_windows(min(ici_min_window, window), window), "gamma": ici_gamma,
                       "info": info}
            u, v = _pyramid_flow(_lk_level, prep, fpyr, window=window, window_type=window_type,
                                 iterations=iterations, fine_iterations=fine_iterations,
                                 regularisation=regularisation, gradient=gradient,
                                 keep=keep, weights=weights, ici=ici, cells=cells)
        else:
            u, v = _pyramid_flow(_hs_level, prep, fpyr, iterations=iterations,
                                 fine_iterations=fine_iterations, alpha=alpha,
                                 inner_iterations=inner_iterations, weights=weights)
    else:
        ref = _standardise(prep.image, prep.mean, prep.scale, 0.0)
        frs = _standardise(frm, prep.mean, prep.scale, 0.0)
        if method == "dis":
            u, v = _dis_flow(ref, frs, dis_preset=dis_preset)
        else:
            u, v = _correlation_flow(ref, frs, corr_window=corr_window, corr_step=corr_step,
                                     corr_taper=corr_taper)
    return u, v


def _median_test(u: np.ndarray, v: np.ndarray, threshold: float, epsilon: float):
    """Normalised median test on two (H, W) float32 components; returns (u, v, outliers)."""
    bad = None
    meds = []
    for comp in (u, v):
        m = cv2.medianBlur(comp, 3)
        res = cv2.absdiff(comp, m)
        rm = cv2.medianBlur(res, 3)
        b = res > np.float32(threshold) * (rm + np.float32(epsilon))
        bad = b if bad is None else (bad | b)
        meds.append(m)
    if bad.any():
        u = np.where(bad, meds[0], u)
        v = np.where(bad, meds[1], v)
    return u, v, bad


def remove_outliers(flow: np.ndarray, *, threshold: float = 3.0, epsilon: float = 0.01
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Normalised median test (after Westerweel & Scarano 2005) with median replacement.

    For each vector and component, the residual to the 3x3 median is divided by the 3x3
    median of those residuals plus ``epsilon``; vectors where either component exceeds
    ``threshold`` are replaced by the 3x3 median. (The 3x3 median includes the centre
    vector, unlike the original 8-neighbour test; it is computed with OpenCV's SIMD
    median filter. An isolated outlier cannot move a 9-point median, so it is caught the
    same way.)

    Parameters
    ----------
    flow : ndarray, shape (H, W, 2)
    threshold : float
        Normalised residual above which a vector is an outlier (2-3 typical).
    epsilon : float
        Expected noise level, pixels (keeps the test meaningful in uniform regions).

    Returns
    -------
    cleaned : ndarray, shape (H, W, 2), float32
    outliers : ndarray, shape (H, W), bool
    """
    flow = np.asarray(flow, dtype=np.float32)
    u, v, bad = _median_test(np.ascontiguousarray(flow[..., 0]), np.ascontiguousarray(flow[..., 1]),
                             threshold, epsilon)
    return np.stack([u, v], axis=-1), bad


def smooth_flow(flow: np.ndarray, *, sigma: float) -> np.ndarray:
    """Gaussian smoothing of each flow component (sigma in pixels; 0 returns a copy)."""
    flow = np.asarray(flow, dtype=np.float32)
    if sigma <= 0:
        return flow.copy()
    return cv2.GaussianBlur(flow, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)


def downsample_flow(flow: np.ndarray, flow_grid: FlowGrid) -> np.ndarray:
    """Area-average full-resolution flow onto the flow grid (paper sec. 4).

    Cell ``(i, j)`` is the mean of image pixels ``[f*i : f*i+f, f*j : f*j+f]``; the
    remainder rows/columns beyond ``f * (H // f)`` are cropped. Values stay in pixels of
    the original image.

    Parameters
    ----------
    flow : ndarray, shape (H, W, 2)
    flow_grid : FlowGrid
        Its ``image_size`` must be ``(W, H)``.

    Returns
    -------
    ndarray, shape (H // f, W // f, 2), float32
    """
    flow = np.asarray(flow, dtype=np.float32)
    H, W = flow.shape[:2]
    if tuple(flow_grid.image_size) != (W, H):
        raise ValueError(f"flow is {W}x{H} but the flow grid is for {flow_grid.image_size}")
    f = flow_grid.factor
    rows, cols = flow_grid.shape
    crop = np.ascontiguousarray(flow[: rows * f, : cols * f])
    if f == 1:
        return crop.copy()
    # INTER_AREA with an integer factor is the exact block mean.
    return cv2.resize(crop, (cols, rows), interpolation=cv2.INTER_AREA)


def deflection_stage(reference, frame: np.ndarray, params: FlowParams = FlowParams(), *,
                     info: dict | None = None) -> np.ndarray:
    """Per camera-frame deflection stage: flow, area downsampling, outliers, smoothing.

    Paper sec. 4: full-resolution optical flow, downsampled to the flow grid
    ``FlowGrid((W, H), params.factor)`` *after* the flow, smoothed and filtered for
    outliers. The normalised median test and the smoothing run on the flow grid: the LK
    flow is correlated over its window (``window`` > ``factor``), so its outliers are
    window-sized, not single pixels, and filtering the 9x smaller grid is far cheaper.
    ``smoothing_sigma`` is given in full-resolution pixels (``sigma / factor`` on the grid).

    With ``texture_correction`` (LK), the first-order bias of the LK window mean is
    subtracted after the outlier test (:func:`_texture_bias`): where the deflection varies
    across the window, LK returns its structure-tensor weighted mean, centred on the
    texture's weighted centroid rather than on the pixel. On the buoyant-plume phantom this
    was the largest error term (benchmarks/flow.py); it costs about 10 % of the stage.
    Finally, with ``adaptive_sigma`` > 0, :func:`_adaptive_smoothing` smooths more where
    the flow is smooth (weak, slowly varying deflections: mostly noise) and keeps the
    ``smoothing_sigma`` result across structure.

    With ``invalid_check``, pixels of the reference or the frame that cannot carry a
    deflection (:func:`invalid_pixels`) get zero weight in the flow, and the flow-grid
    cells where they hold half or more of the cell or of its LK window come back as NaN
    (the masks treat them as "possibly flow", the tomography drops their rays).

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        Background (float32 grey levels, 8- or 16-bit range). Passing the
        :class:`PreparedReference` of the camera saves its per-call preparation.
    frame : ndarray, shape (H, W)
    params : FlowParams
    info : dict, optional
        Receives what the data chose (with ICI: the image noise, the median window, the
        fraction of pixels per window and the median predicted flow noise in pixels).

    Returns
    -------
    flow : ndarray, shape (H // f, W // f, 2), float32
        Deflection in original-image pixels (component 0 = u, 1 = v).
    """
    ici = params.method == "lk" and params.ici_gamma > 0 and params.gradient == "frame"
    keep = {} if params.method == "lk" and params.texture_correction and not ici else None
    valid = None
    if params.invalid_check:
        inv_ref = reference.invalid(params.texture_threshold) if isinstance(reference, PreparedReference) \
            else invalid_pixels(reference, texture_threshold=params.texture_threshold)
        inv = inv_ref | invalid_pixels(frame, texture_threshold=params.texture_threshold)
        valid = ~inv if inv.any() else None
    f = params.factor
    H, W = np.shape(frame)[:2]
    rows, cols = FlowGrid((W, H), f).shape
    on_cells = uses_cell_solve(params)
    if keep is None and on_cells:
        keep = {}
    u, v = _flow_components(reference, frame, **params.field_kwargs(), keep=keep, valid=valid, info=info,
                            cells=f if on_cells else 0)

    def block_mean(a):  # exact block means (INTER_AREA with an integer factor)
        crop = a[: rows * f, : cols * f]
        return np.ascontiguousarray(crop) if f == 1 else cv2.resize(crop, (cols, rows),
                                                                    interpolation=cv2.INTER_AREA)

    comps = [u, v] if u.shape == (rows, cols) and on_cells else [block_mean(u), block_mean(v)]
    bad_cells = None
    if valid is not None:
        # a cell is kept if most of the window weight around its pixels lies on valid ones
        w0 = _weight_pyramid(valid, 1)[0]
        support = block_mean(_window_filter(w0, _window_taps(params.window, params.window_type)))
        bad_cells = (block_mean(w0) < 0.5) | (support < 0.5)
        if bad_cells.all():
            return np.full((rows, cols, 2), np.nan, np.float32)
        filled = _nearest_fill(np.dstack(comps), bad_cells)
        comps = [np.ascontiguousarray(filled[..., 0]), np.ascontiguousarray(filled[..., 1])]
    if params.outlier_threshold > 0:
        cu, cv_, bad = _median_test(comps[0], comps[1], params.outlier_threshold,
                                    params.outlier_epsilon)
        comps = [cu, cv_]
        n_out = int(np.count_nonzero(bad))
        if n_out:
            log.debug("deflection_stage: replaced %d outlier vectors (%.3f%%)",
                      n_out, 100.0 * n_out / bad.size)
    if keep and params.texture_correction:
        bu, bv = _texture_bias(keep["gx"], keep["gy"], comps[0], comps[1], window=params.window,
                               window_type=params.window_type, factor=params.factor, mom=keep.get("mom"),
                               linear=on_cells, T=keep.get("T"))
        comps = [comps[0] - bu, comps[1] - bv]
    out = np.empty((rows, cols, 2), np.float32)
    sigma = params.smoothing_sigma / params.factor
    for k, comp in enumerate(comps):
        out[..., k] = comp if sigma <= 0 else cv2.GaussianBlur(
            comp, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    if params.adaptive_sigma > 0:
        out = _adaptive_smoothing(out, np.dstack(comps), params.adaptive_sigma / params.factor,
                                  params.adaptive_threshold)
    if bad_cells is not None and bad_cells.any():
        out[bad_cells] = np.nan
    return out


def _adaptive_smoothing(small: np.ndarray, flow: np.ndarray, sigma: float, threshold: float
                        ) -> np.ndarray:
    """Blend a strongly smoothed flow into ``small`` where both agree within the noise.

    Two-scale structure-adaptive smoothing (in the spirit of Lepski's scale selection):
    ``large`` = ``flow`` Gaussian-smoothed with ``sigma`` (grid cells). Where the flow is
    smooth, ``large`` differs from ``small`` only by noise; across structure it differs by
    the bias of the large scale. With ``D = |large - small|`` (vector norm) and the robust
    noise scale ``tau`` = lower quartile of ``D`` over the image (assumes at least a
    quarter of the image is flow-free or smooth; BOS images mostly are), the result is
    ``w large + (1 - w) small``, ``w = exp(-(D / (threshold tau))^2)``.
    """
    large = cv2.GaussianBlur(flow, (0, 0), sigmaX=sigma, sigmaY=sigma,
                             borderType=cv2.BORDER_REFLECT)
    diff = large - small
    d2 = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]
    tau2 = float(np.quantile(d2[::2, ::2], 0.25))  # lower quartile of D^2 = of D, squared
    if not np.isfinite(tau2) or tau2 <= 0:
        return small
    w = np.exp(d2 * np.float32(-1.0 / (threshold * threshold * tau2)))
    return (small + w[..., None] * diff).astype(np.float32)


def endpoint_error(flow: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean end-point error ``mean |flow - truth|`` (pixels), optionally inside ``mask``."""
    d = np.linalg.norm(np.asarray(flow, np.float64) - np.asarray(truth, np.float64), axis=-1)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(d.mean()) if d.size else float("nan")
