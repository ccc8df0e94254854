"""Register a frame's background to the reference: the camera's motion and the lighting's
change, measured on the pixels whose rays miss the volume, before any flow.

The model, over the static pixels ``p`` (:func:`~.static_region.static_region`)::

    frame(p) = gain(row) * reference(p + motion(p)) + offset(row)

with ``motion`` a translation, an affine map or a homography (:mod:`.motion`) and
``gain``, ``offset`` piecewise linear in the row (:mod:`.photometric`). It is solved by
Gauss-Newton on the prepared reference's pyramid, coarse to fine (the flow's own
pre-smoothed, standardised images and cubic B-spline coefficients, so no image is
resampled twice), each step a weighted least-squares solve with Huber weights
(iteratively reweighted least squares, k = 1.345 robust standard deviations): a convex
robust loss with one minimum, no random sampling, 95 % of least squares' efficiency on
Gaussian noise, and a bounded influence for what the static region still holds (a
plume leaving the box, a missed hot pixel, a speck of dust). Iterated to convergence it
has no linearisation bias (one Lucas-Kanade step underestimates a 0.3 px shift), and
over 10^5 pixels its noise is a few ten-thousandths of a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from schlieren.pipeline.flow.reference import PreparedReference, frame_pyramid, prepare_reference

from ._kernels import _residuals
from .motion import _design, motion_extent, motion_size, no_motion
from .params import CaptureParams
from .photometric import Photometric, row_knots

__all__ = ["BackgroundFit", "SampleRegion", "register_background", "sample_region", "HUBER_K"]

#: Huber's constant (robust standard deviations): 95 % efficiency on Gaussian residuals.
HUBER_K = 1.345
#: Samples of the finest level at most (a regular subsampling of the region beyond it;
#: a quarter of that on each coarser level).
MAX_SAMPLES = 100_000
#: A Gauss-Newton step below this (pixels at full resolution, times the level's scale)
#: and below :data:`_STEP_PHOTOMETRIC` in gain (and offset, in the reference's standard
#: deviations) ends a level: the noise of the fit is a few 1e-4 px, and its convergence is
#: linear (about 7x per step: the images' noise and curvature).
_STEP_PX = 3e-4
_STEP_PHOTOMETRIC = 2e-4
#: Relative weight of the second-difference penalty on the gain and offset knots (holds
#: knots without static pixels to their neighbours; negligible where data are).
_SMOOTH = 1e-3


@dataclass(frozen=True)
class BackgroundFit:
    """What :func:`register_background` measured.

    Attributes
    ----------
    motion : ndarray, shape (8,)
        :data:`~.motion.MOTION_PARAMS` (pixels about the image centre).
    photometric : Photometric
        Gain and offset profiles (grey levels).
    noise : float
        Robust standard deviation of the fit's residual, grey levels.
    samples : int
        Samples of the finest level fitted (:attr:`level`).
    static_fraction : float
        Fraction of the image in the static region.
    fallback : bool
        The static region was too small: every valid pixel was used.
    converged : bool
    motion_sigma : float
        Standard deviation (pixels) of the motion's displacement where it is largest (the
        image corners), from the fit's noise and normal equations.
    gain_sigma, level_sigma : ndarray, shape (K,)
        Standard deviations of the gain at the knots, and of the change of the reference's
        mean grey level there (grey levels).
    level : int
        The finest pyramid level fitted (0 = full resolution; more when ``stop_early`` of
        :func:`register_background` ended the fit before it).
    """

    motion: np.ndarray
    photometric: Photometric
    noise: float
    samples: int
    static_fraction: float
    fallback: bool
    converged: bool
    motion_sigma: float = float("nan")
    gain_sigma: np.ndarray | None = None
    level_sigma: np.ndarray | None = None
    level: int = 0


@dataclass(frozen=True)
class SampleRegion:
    """The pixels a camera's registrations are fitted on, per pyramid level: the same for
    all its frames (:func:`sample_region`).

    Attributes
    ----------
    samples : tuple of (ndarray, ndarray)
        Per level (fine first), the columns and rows of the level's samples (:func:`_samples`).
    fraction : float
        Fraction of the image in the static region.
    fallback : bool
        The static region was too small: every valid pixel is used.
    empty : bool
        No pixel to fit on.
    """

    samples: tuple
    fraction: float
    fallback: bool
    empty: bool


def register_background(reference, frame: np.ndarray, *, static: np.ndarray | None = None,
                        valid: np.ndarray | None = None, model: str = "affine",
                        photometric: bool = CaptureParams.photometric, banding_rows: int = CaptureParams.banding_rows,
                        min_static_fraction: float = CaptureParams.min_static_fraction, presmooth: float = 0.6,
                        levels: int = 3, iterations: int = 8, region: SampleRegion | None = None,
                        pyramid: list | None = None,
                        stop_early: Callable[[BackgroundFit], bool] | None = None) -> BackgroundFit:
    """Measure a frame's background motion, gain and offset against the reference.

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        The background without flow (the camera's prepared reference saves its pyramid).
    frame : ndarray, shape (H, W)
        Grey levels.
    static : ndarray, shape (H, W), bool, optional
        Pixels whose rays miss the volume; None: every pixel.
    valid : ndarray, shape (H, W), bool, optional
        Pixels that may be used (not defective, not clipped); None: every pixel.
    model : {"none", "translation", "affine", "homography"}
    photometric : bool
        Fit the gain and offset profiles (else gain 1, offset 0).
    banding_rows : int
        Rows between the profiles' knots (:func:`~.photometric.row_knots`).
    min_static_fraction : float
        Below this fraction of static pixels, every valid pixel is used (``fallback``).
    presmooth, levels : float, int
        Of the flow (used when ``reference`` is an array).
    iterations : int
        Gauss-Newton steps per pyramid level at most.
    region : SampleRegion, optional
        :func:`sample_region` of ``static``, ``valid`` and ``min_static_fraction`` when
        already made (then those are not read).
    pyramid : list of ndarray, optional
        The frame's :func:`~schlieren.pipeline.flow.frame_pyramid` when already made.
    stop_early : callable, optional
        Called with the fit of the coarse levels before the finest one is fitted; when it
        returns True, that fit is returned (``level`` > 0): a screen that spares the finest
        level's cost on frames where it could not change what is applied.

    Returns
    -------
    BackgroundFit
    """
    prep = reference if isinstance(reference, PreparedReference) else \
        prepare_reference(reference, presmooth=presmooth, levels=levels)
    img = np.asarray(frame, np.float32)
    if img.shape != prep.shape:
        raise ValueError(f"reference {prep.shape} and frame {img.shape} differ in shape")
    H, W = img.shape
    nm = motion_size(model)
    knots = row_knots(H, banding_rows)
    nk = len(knots) if photometric else 0
    if region is None:
        region = sample_region(prep, static=static, valid=valid, min_static_fraction=min_static_fraction)
    if nm + nk == 0 or region.empty:
        return BackgroundFit(no_motion(), Photometric(knots, np.ones(len(knots)), np.zeros(len(knots))),
                             float("nan"), 0, region.fraction, region.fallback, nm + nk == 0)
    fpyr = frame_pyramid(prep, img) if pyramid is None else pyramid
    state = _State(theta=np.zeros(8), gam=np.zeros(len(knots)), bet=np.zeros(len(knots)))
    solver = _Solver(nm, nk, knots, ((W - 1) / 2.0, (H - 1) / 2.0), (W, H))
    converged, samples, sigma, fitted = False, 0, float("nan"), None
    for lev in range(len(prep.pyramid) - 1, -1, -1):
        xs, ys = region.samples[lev]
        if len(xs) < 4 * (nm + 2 * nk):
            continue
        if lev == 0 and fitted is not None and stop_early is not None:
            fit = _result(prep, solver, state, knots, sigma, samples, region, converged, fitted)
            if stop_early(fit):
                return fit
        converged, sigma = solver.run(prep.coefficients[lev], fpyr[lev], xs, ys, 2.0 ** lev, state,
                                      iterations if lev == 0 else max(2, iterations // 2))
        samples, fitted = len(xs), lev
    return _result(prep, solver, state, knots, sigma, samples, region, converged, fitted or 0)


def _result(prep, solver, state, knots, sigma, samples, region, converged, level) -> BackgroundFit:
    """The fit so far as a :class:`BackgroundFit` (gain and offset in grey levels)."""
    gain = 1.0 + state.gam
    offset = state.bet / prep.scale - state.gam * prep.mean  # grey levels (see the module docstring)
    msig, gsig, lsig = solver.uncertainty(sigma, prep.scale, len(knots))
    return BackgroundFit(state.theta.copy(), Photometric(knots, gain, offset), sigma / prep.scale, samples,
                         region.fraction, region.fallback, converged, msig, gsig, lsig, level)


def sample_region(reference: PreparedReference, *, static: np.ndarray | None = None,
                  valid: np.ndarray | None = None,
                  min_static_fraction: float = CaptureParams.min_static_fraction) -> SampleRegion:
    """The samples of every pyramid level of ``reference`` that a camera's registrations
    fit on (the arguments as those of :func:`register_background`)."""
    region, fraction, fallback = _region(static, valid, reference.shape, min_static_fraction)
    empty = not region.any()
    samples = tuple(_samples(region, lev, p.shape) for lev, p in enumerate(reference.pyramid))
    return SampleRegion(samples, fraction, fallback, empty)


def _region(static, valid, shape, min_static_fraction) -> tuple[np.ndarray, float, bool]:
    """The pixels to fit on, the static fraction, and whether the fit falls back to every pixel."""
    ok = np.ones(shape, bool) if valid is None else np.asarray(valid, bool)
    if static is None:
        return ok, 1.0, False
    static = np.asarray(static, bool)
    fraction = float(np.mean(static))
    region = static & ok
    if fraction < min_static_fraction or np.mean(region) < 0.5 * min_static_fraction:
        return ok, fraction, True
    return region, fraction, False


def _samples(region: np.ndarray, lev: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Level ``lev`` pixels whose pyramid footprint lies in ``region`` (away from the border),
    regularly subsampled to :data:`MAX_SAMPLES` / 4^lev."""
    s = 2 ** lev
    r = 2 * s + 1   # pyrDown's reach on the full-resolution image, and the pre-smoothing
    er = cv2.erode(region.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8),
                   borderType=cv2.BORDER_CONSTANT, borderValue=0)[::s, ::s][:shape[0], :shape[1]]
    b = 3
    er[:b] = 0
    er[-b:] = 0
    er[:, :b] = 0
    er[:, -b:] = 0
    n = int(np.count_nonzero(er))
    most = MAX_SAMPLES // 4 ** lev  # coarse levels only start the finer ones
    stride = int(np.ceil(np.sqrt(n / most))) if n > most else 1
    ys, xs = np.nonzero(er[::stride, ::stride])  # the pixels on the stride's grid, in row-major order
    return xs.astype(np.int64) * stride, ys.astype(np.int64) * stride


@dataclass
class _State:
    theta: np.ndarray  # (8,) motion
    gam: np.ndarray    # gain - 1 at the knots (standardised images)
    bet: np.ndarray    # offset at the knots (standardised images)


class _Solver:
    """Gauss-Newton with Huber weights on one pyramid level."""

    def __init__(self, nm: int, nk: int, knots: np.ndarray, centre, image_size):
        self.nm, self.nk = nm, nk
        self.knots = knots
        self.k0 = float(knots[0])
        self.step = float(knots[1] - knots[0]) if len(knots) > 1 else 1.0
        self.centre = centre
        self.image_size = image_size
        self.penalty = _second_differences(nk) if nk > 2 else None
        self.normal = None  # the last step's normal matrix (for the uncertainty)

    def uncertainty(self, sigma: float, scale: float, n_knots: int) -> tuple[float, np.ndarray, np.ndarray]:
        """Standard deviations of the motion's largest displacement, of the gains and of the
        mean grey level's change at the knots, ``sigma^2 A^-1`` of the last step (residuals
        are correlated over the pre-smoothing's few pixels: an underestimate by about that)."""
        nan = np.full(n_knots, np.nan)
        if self.normal is None or not np.isfinite(sigma):
            return float("nan"), nan, nan
        try:
            cov = sigma * sigma * np.linalg.pinv(self.normal)
        except np.linalg.LinAlgError:
            return float("nan"), nan, nan
        msig = 0.0
        if self.nm:
            W, H = self.image_size
            qx = np.array([0.0, W - 1.0, 0.0, W - 1.0]) - self.centre[0]
            qy = np.array([0.0, 0.0, H - 1.0, H - 1.0]) - self.centre[1]
            jx, jy = _design(qx, qy, self.nm)
            cm = cov[:self.nm, :self.nm]
            var = np.einsum("ij,jk,ik->i", jx, cm, jx) + np.einsum("ij,jk,ik->i", jy, cm, jy)
            msig = float(np.sqrt(max(float(np.max(var)), 0.0)))
        if not self.nk:
            return msig, nan, nan
        d = np.diag(cov)
        gsig = np.sqrt(np.maximum(d[self.nm:self.nm + self.nk], 0.0))
        lsig = np.sqrt(np.maximum(d[self.nm + self.nk:], 0.0)) / scale
        return msig, gsig, lsig

    def run(self, cp, frame, xs, ys, scale, state: _State, iterations: int) -> tuple[bool, float]:
        n = len(xs)
        e = np.empty(n)
        J = np.empty((n, self.nm + 4))
        kk = np.empty(n, np.int64)
        sigma = float("nan")
        for _ in range(iterations):
            self._residuals(cp, frame, xs, ys, scale, state, e, J, kk)
            sigma = 1.4826 * float(np.median(np.abs(e)))
            if not np.isfinite(sigma) or sigma <= 0:
                return False, sigma
            a = np.abs(e)
            wt = np.where(a <= HUBER_K * sigma, 1.0, HUBER_K * sigma / np.maximum(a, 1e-30))
            delta = self._step(state, e, J, kk, wt)
            if delta is None:
                return False, sigma
            dm = np.zeros(8)
            dm[:self.nm] = delta[:self.nm]
            state.theta += dm
            if self.nk:
                state.gam += delta[self.nm:self.nm + self.nk]
                state.bet += delta[self.nm + self.nk:]
            # converged below the fit's own noise (a few 1e-4 px): coarser levels only start the next
            small = motion_extent(dm, self.image_size) < _STEP_PX * scale and \
                (not self.nk or float(np.max(np.abs(delta[self.nm:]))) < _STEP_PHOTOMETRIC * scale)
            if small:
                return True, sigma
        return False, sigma

    def _residuals(self, cp, frame, xs, ys, scale, state, e, J, kk):
        gam = state.gam if self.nk else np.zeros(1)
        bet = state.bet if self.nk else np.zeros(1)
        _residuals(cp, frame, xs, ys, float(scale), self.centre[0], self.centre[1], state.theta, self.nm,
                   self.k0, self.step, gam, bet, e, J, kk)

    def _normal(self, e, J, kk, wt) -> tuple[np.ndarray, np.ndarray]:
        """``J^T W J`` and ``J^T W e`` over every unknown: the samples come row by row, so
        those of one knot interval are contiguous and share their four photometric columns."""
        nm, nk = self.nm, max(self.nk, 1)
        P = nm + 2 * nk
        A = np.zeros((P, P))
        rhs = np.zeros(P)
        cuts = (np.flatnonzero(np.diff(kk)) + 1).tolist()
        motion = list(range(nm))
        for s0, s1 in zip([0] + cuts, cuts + [len(kk)]):
            k = int(kk[s0])
            k1 = min(k + 1, nk - 1)
            cols = np.array(motion + [nm + k, nm + k1, nm + nk + k, nm + nk + k1])
            Jw = J[s0:s1] * wt[s0:s1, None]
            if k1 != k:  # distinct columns: one addition per entry, as np.add.at makes
                A[cols[:, None], cols] += Jw.T @ J[s0:s1]
                rhs[cols] += Jw.T @ e[s0:s1]
            else:  # the last knot's interval names its knot twice: the additions accumulate
                np.add.at(A, (cols[:, None], cols[None, :]), Jw.T @ J[s0:s1])
                np.add.at(rhs, cols, Jw.T @ e[s0:s1])
        return A, rhs

    def _step(self, state, e, J, kk, wt) -> np.ndarray | None:
        A, rhs = self._normal(e, J, kk, wt)
        keep = self.nm + 2 * self.nk
        A, rhs = A[:keep, :keep], rhs[:keep]
        if self.penalty is not None:  # smooth profiles across knots without data
            for off, cur in ((self.nm, state.gam), (self.nm + self.nk, state.bet)):
                blk = slice(off, off + self.nk)
                lam = _SMOOTH * float(np.mean(np.diag(A)[blk]))
                A[blk, blk] += lam * self.penalty
                rhs[blk] -= lam * (self.penalty @ cur)
        self.normal = A
        d = np.sqrt(np.maximum(np.diag(A), 1e-300))
        As = A / d[:, None] / d[None, :] + 1e-10 * np.eye(keep)
        try:
            y = np.linalg.solve(As, rhs / d)
        except np.linalg.LinAlgError:
            return None
        out = y / d
        return out if np.all(np.isfinite(out)) else None


def _second_differences(n: int) -> np.ndarray:
    """``D^T D`` of the second-difference operator on ``n`` knots."""
    D = np.zeros((n - 2, n))
    for i in range(n - 2):
        D[i, i:i + 3] = (1.0, -2.0, 1.0)
    return D.T @ D


