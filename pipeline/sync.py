"""Strobe synchronisation and rolling-shutter / inter-camera resampling of flow fields.

Paper section 4 ("Camera synchronization", Figure 5). Timing model (SPEC, docs/design.md):
row ``r`` of frame ``f`` of a camera starts its exposure at
``offset + f / frame_rate + r * line_time`` on the session clock.

* Strobe: a flash of negligible duration at session time ``t = 0`` brightens every row
  whose exposure interval ``[start, start + exposure)`` contains 0. The lower edge of the
  lit band (the last row with ``start <= 0``) gives the camera's offset to within one line
  time (:func:`detect_flash`, :func:`offset_from_flash`). Frames carrying the flash are
  never used as data (:func:`flash_frames`).
* Resampling: each camera's flow fields are resampled to common instants
  (:func:`output_times`) row by row, by warping between successive flow fields with the
  motion estimated between those fields, each row weighted by its own time offset
  (:func:`resample_flow`). Flow fields are smooth, so warping them (rather than the raw
  images) keeps the high frequencies the optical flow needs (paper sec. 4).
"""

from __future__ import annotations

import hashlib
import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from schlieren.pipeline.flow import prolong_flow, spline_coefficients, warp_coefficient_rows, warp_coefficients
from schlieren.pipeline.geometry import FlowGrid
from schlieren.pipeline.params import param

__all__ = [
    "FlashDetection",
    "FlashParams",
    "ResampleParams",
    "row_means",
    "detect_flash",
    "offset_from_flash",
    "flash_frames",
    "row_times",
    "output_times",
    "frames_needed",
    "field_motion",
    "resample_flow",
]

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------
# Strobe detection
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FlashParams:
    """Parameters of :func:`detect_flash` (field names = its keyword names).

    Attributes
    ----------
    min_snr : float
        The band's brightening must exceed this many robust noise sigmas of the
        frame-to-frame row-mean fluctuations.
    min_contrast : float
        The band's brightening must also exceed this many grey levels.
    """

    min_snr: float = param(10.0, unit="1", gt=0, le=1e6)
    min_contrast: float = param(2.0, unit="grey levels", ge=0, le=65535)


@dataclass(frozen=True)
class FlashDetection:
    """Where the strobe flash appears in one camera's search window.

    Frame indices are 0-based *within the search window* (``row_means[i]``).

    Attributes
    ----------
    frame : int
        Frame holding the lower edge of the band (the last lit frame).
    first_row, last_row : int
        First and last lit row in ``frame``.
    upper_frame, upper_row : int
        Frame and row where the band starts (first lit row of the first lit frame).
    height : int
        Image rows.
    n_frames : int
        Frames in the search window.
    cut_top : bool
        The band reaches row 0 of ``upper_frame`` (its upper edge may lie in the frame gap).
    cut_bottom : bool
        The band reaches the last row of ``frame``: its lower edge lies in the gap
        between frames (vertical blanking), not on a row.
    lit_frames : tuple of int
        Every frame of the window with lit rows.
    contrast : float
        Median brightening of the lit rows (grey levels).
    confidence : float
        ``contrast`` divided by the robust noise of the row means (a signal-to-noise ratio).
    """

    frame: int
    first_row: int
    last_row: int
    upper_frame: int
    upper_row: int
    height: int
    n_frames: int
    cut_top: bool
    cut_bottom: bool
    lit_frames: tuple
    contrast: float
    confidence: float


def row_means(frame: np.ndarray) -> np.ndarray:
    """Mean grey level of every row of one frame, shape (H,) float64 (input of
    :func:`detect_flash`, stacked over the frames of ``sync.search_frames``)."""
    return np.asarray(frame, dtype=np.float64).mean(axis=1)


def _longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(start, stop) of the longest run of True in a 1-D mask ((0, 0) if none)."""
    if not mask.any():
        return 0, 0
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    k = int(np.argmax(stops - starts))
    return int(starts[k]), int(stops[k])


def detect_flash(row_means: np.ndarray, *, min_snr: float = 10.0, min_contrast: float = 2.0
                 ) -> FlashDetection:
    """Find the strobe's band of lit rows in one camera (paper sec. 4, Figure 5).

    The static background makes every row's mean nearly constant over the window; the
    flash adds a step to a contiguous band of rows (in one frame, or split over two
    consecutive frames when it spans the end of a readout). Each row mean is compared with
    that row's median over the window; rows brighter by more than half of the peak
    brightening are lit (the half-maximum places the edge mid-way on a short strobe's
    ramp).

    Parameters
    ----------
    row_means : ndarray, shape (F, H)
        Mean grey level of every row of the ``F`` frames of the search window (F >= 3).
    min_snr, min_contrast : float
        See :class:`FlashParams`.

    Returns
    -------
    FlashDetection

    Raises
    ------
    ValueError
        If no band stands out (no flash in the window), with the measured brightening.
    """
    rm = np.asarray(row_means, dtype=np.float64)
    if rm.ndim != 2 or rm.shape[0] < 3:
        raise ValueError(f"row_means must have shape (frames >= 3, rows), got {rm.shape}")
    F, H = rm.shape
    diff = rm - np.median(rm, axis=0, keepdims=True)
    noise = 1.4826 * float(np.median(np.abs(diff - np.median(diff))))
    peak = float(diff.max())
    if not np.isfinite(peak) or peak < min_contrast or peak < min_snr * max(noise, 1e-12):
        raise ValueError(
            f"no strobe flash found in the {F} searched frames: the brightest row rises "
            f"{peak:.3g} grey levels above its median (noise {noise:.3g}; needs > "
            f"{min_contrast:g} and > {min_snr:g} x noise)")
    lit = diff > 0.5 * peak
    runs = [_longest_run(lit[f]) for f in range(F)]
    lengths = np.array([b - a for a, b in runs])
    lit_frames = tuple(int(f) for f in np.flatnonzero(lengths > 0))
    # the band is at most two consecutive frames; keep the frames adjacent to the strongest
    best = int(np.argmax([diff[f, a:b].sum() if b > a else -np.inf for f, (a, b) in enumerate(runs)]))
    keep = [f for f in lit_frames if abs(f - best) <= 1]
    if len(keep) == 3:  # best in the middle: keep the neighbour that continues the band
        before, after = keep[0], keep[2]
        cont_before = runs[before][1] == H and runs[best][0] == 0
        keep = [before, best] if cont_before else [best, after]
    if len(keep) == 2:
        f0, f1 = keep
        # a genuine split band ends at the bottom of f0 and resumes at the top of f1
        if not (runs[f0][1] == H and runs[f1][0] == 0):
            keep = [best]
    if len(lit_frames) > len(keep):
        log.warning("detect_flash: bright rows in frames %s besides the flash band in %s",
                    sorted(set(lit_frames) - set(keep)), keep)
    upper, lower = keep[0], keep[-1]
    a_low, b_low = runs[lower]
    a_up, _ = runs[upper]
    vals = np.concatenate([diff[f, runs[f][0]:runs[f][1]] for f in keep])
    contrast = float(np.median(vals))
    return FlashDetection(
        frame=lower, first_row=a_low, last_row=b_low - 1,
        upper_frame=upper, upper_row=a_up, height=H, n_frames=F,
        cut_top=a_up == 0, cut_bottom=b_low == H,
        lit_frames=tuple(keep), contrast=contrast,
        confidence=contrast / max(noise, 1e-12),
    )


def offset_from_flash(det: FlashDetection, *, first_frame: int, frame_rate: float,
                      line_time: float, exposure: float | None = None) -> float:
    """Camera time offset (session-clock start of row 0 of frame 0) from the flash band.

    Strobe model (docs/design.md): the flash at ``t = 0`` lights the rows with
    ``start <= 0 < start + exposure``. The lower edge ``r`` of the band in absolute frame
    ``f`` satisfies ``start(f, r) <= 0 < start(f, r + 1)``, so
    ``offset = -f / frame_rate - (r + 1/2) * line_time``, within half a line time.

    When the band runs to the last row (``det.cut_bottom``), its lower edge lies in the
    frame gap. With a known ``exposure`` the upper edge ``r_u`` in frame ``f_u`` gives
    ``offset = -exposure - f_u / frame_rate - (r_u - 1/2) * line_time``; otherwise the
    offset is only known to lie in the vertical blanking interval, and its middle is
    returned (uncertainty +- half the blanking, logged).

    Parameters
    ----------
    det : FlashDetection
    first_frame : int
        Absolute index of the first frame of the search window.
    frame_rate : float
        Frames per second.
    line_time : float
        Seconds between the exposure starts of successive rows (> 0).
    exposure : float, optional
        Row exposure time, seconds (only needed when the band is cut by the frame bottom).

    Returns
    -------
    float
        Offset in seconds.

    Raises
    ------
    ValueError
        If the band's lower edge cannot be located (cut by the bottom of the last searched
        frame, so the next frame may continue it) and no exposure is given, or if
        ``line_time`` is not positive (a global shutter cannot be synchronised to better
        than a frame by a flash).
    """
    if line_time <= 0:
        raise ValueError("strobe sync needs a rolling shutter (line_time > 0)")
    period = 1.0 / frame_rate
    if not det.cut_bottom:
        f = first_frame + det.frame
        return -f * period - (det.last_row + 0.5) * line_time
    upper_usable = not (det.cut_top and det.upper_frame == 0)
    if exposure is not None and upper_usable and not det.cut_top:
        fu = first_frame + det.upper_frame
        return -exposure - fu * period - (det.upper_row - 0.5) * line_time
    if det.frame == det.n_frames - 1:
        raise ValueError("the flash band runs to the bottom of the last searched frame: "
                         "extend sync.search_frames by one frame so that its lower edge "
                         "is visible")
    f = first_frame + det.frame
    blank = period - det.height * line_time
    lo = -(f + 1) * period       # offset > this: row 0 of frame f+1 starts after the flash
    hi = -f * period - (det.height - 1) * line_time  # last row of frame f started before it
    if blank > 4 * line_time:
        log.warning("flash band ends in the vertical blanking: offset known to +-%.3g s "
                    "(%.1f line times)", 0.5 * (hi - lo), 0.5 * (hi - lo) / line_time)
    return 0.5 * (lo + hi)


def flash_frames(det: FlashDetection, *, first_frame: int, margin: int = 0) -> set[int]:
    """Absolute indices of the frames that carry the flash (never used as data).

    Parameters
    ----------
    det : FlashDetection
    first_frame : int
        Absolute index of the first frame of the search window.
    margin : int
        Also exclude this many frames on each side.
    """
    lo = first_frame + min(det.lit_frames) - margin
    hi = first_frame + max(det.lit_frames) + margin
    return set(range(lo, hi + 1))


# ----------------------------------------------------------------------------------------
# Time bookkeeping
# ----------------------------------------------------------------------------------------
def row_times(frame: int, rows, *, offset: float, frame_rate: float, line_time: float
              ) -> np.ndarray:
    """Session time at which ``rows`` (image rows, may be fractional) of ``frame`` start."""
    return offset + frame / frame_rate + np.asarray(rows, dtype=np.float64) * line_time


def output_times(first_frame: int, n_frames: int, *, offsets, frame_rate: float, height,
                 line_time) -> np.ndarray:
    """Session-clock instants of the reconstructed frames (docs/design.md).

    ``time[k] = (first_frame + k) / frame_rate + mean_c(offset_c + 0.5 * height_c *
    line_time_c)``: the mid-frame instant of the average camera. ``height`` and
    ``line_time`` may be scalars or one value per camera.

    Returns
    -------
    ndarray, shape (n_frames,), float64, seconds
    """
    offs = np.atleast_1d(np.asarray(offsets, dtype=np.float64))
    h = np.broadcast_to(np.asarray(height, dtype=np.float64), offs.shape)
    lt = np.broadcast_to(np.asarray(line_time, dtype=np.float64), offs.shape)
    mid = float(np.mean(offs + 0.5 * h * lt))
    return (first_frame + np.arange(n_frames, dtype=np.float64)) / frame_rate + mid


def _fractional_frame(target_time, rows, *, offset, frame_rate, line_time):
    """Fractional frame index at which each image row is exposed at ``target_time``."""
    return (target_time - offset - np.asarray(rows, np.float64) * line_time) * frame_rate


def frames_needed(target_time: float, *, offset: float, frame_rate: float, line_time: float,
                  height: int, excluded_frames=(), frame_range: tuple[int, int] | None = None
                  ) -> tuple[int, int]:
    """Half-open range ``[f0, f1)`` of raw frames whose rows bracket ``target_time``.

    Every image row ``r`` is exposed at ``target_time`` between frames
    ``floor(phi_r)`` and ``floor(phi_r) + 1`` with
    ``phi_r = (target_time - offset - r * line_time) * frame_rate``; the range covers all
    rows, extended past excluded (flash) frames at either end, and clipped to
    ``frame_range`` (the frames that exist) if given.

    Returns
    -------
    (f0, f1) : tuple of int
    """
    phi = _fractional_frame(target_time, [0.0, height - 1.0], offset=offset,
                            frame_rate=frame_rate, line_time=line_time)
    # rounding only ever widens the range: a row exposed 1e-11 s before frame f still
    # needs frame f - 1 (hypothesis found phi = 29.9999999995 dropping it)
    lo = int(np.floor(phi.min()))
    hi = int(np.floor(phi.max() + 1e-9)) + 1
    excluded = set(int(e) for e in excluded_frames)
    if frame_range is not None:
        a, b = int(frame_range[0]), int(frame_range[1])
        lo = min(max(lo, a), b - 1)
        hi = min(max(hi, a), b - 1)
    else:
        a, b = -(2**62), 2**62
    while lo in excluded and lo > a:
        lo -= 1
    while hi in excluded and hi < b - 1:
        hi += 1
    return lo, hi + 1


# ----------------------------------------------------------------------------------------
# Motion between flow fields and row-wise resampling (paper Figure 5)
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ResampleParams:
    """Parameters of :func:`resample_flow`.

    Attributes
    ----------
    method : {"motion", "linear", "nearest"}
        ``motion``: warp between successive flow fields along the motion estimated between
        them (paper sec. 4); ``linear``: per-row linear blend without motion compensation;
        ``nearest``: per row, the field of the nearest frame in time.
    window : int
        Window (flow-grid cells, odd) of the Lucas-Kanade motion estimate between fields.
    levels : int
        Pyramid levels of the motion estimate.
    iterations : int
        Warping iterations per level of the motion estimate. 2 (was 4): on the paper-scale
        session's flow fields the motion moves by 0.008 cells RMS (of 0.86) and the estimate
        takes 13 instead of 22 ms; the realistic family's tune cases are unchanged to the
        reported digit with 2 and with 1 (1: 0.044 cells, 10 ms).
    regularisation : float
        Tikhonov weight of the motion estimate relative to the strongest structure
        (pulls the motion of flow-free regions to zero).
    finest_level : int
        Finest pyramid level the motion is estimated on (0: the flow grid itself); the
        levels below it take the motion prolonged (bilinear, doubled per level). 1 (was 0):
        the motion between two flow fields is smooth (its window is 15 cells), and its
        estimate on the full grid mostly fits the fields' noise. Resampled flow against the
        rendered truth (RMS error where the deflection exceeds 0.02 px): paper-scale session
        (4 cameras x 8 frames) 0.03035 -> 0.02854 px and the resample task 62 -> 35 ms per
        camera-frame; the realistic family's tune cases 0.01542 -> 0.01541 (16 cameras),
        0.01314 -> 0.01314 (8 cameras), 0.05318 -> 0.05284 (8 cameras H.264), 1.7-1.9x
        faster; level 2 was no better (0.02897, 0.01548, 0.01321, 0.05265).
    """

    method: str = param("motion", choices=("motion", "linear", "nearest"))
    window: int = param(15, unit="flow cells", ge=3, le=101, odd=True)
    levels: int = param(3, unit="1", ge=1, le=8)
    iterations: int = param(2, unit="1", ge=1, le=50)
    regularisation: float = param(1e-2, unit="1", ge=0, le=1e3)
    finest_level: int = param(1, unit="1", ge=0, le=7)

    def __post_init__(self):
        if self.method not in ("motion", "linear", "nearest"):
            raise ValueError(f"ResampleParams.method must be motion/linear/nearest, got {self.method!r}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"ResampleParams.window must be odd and >= 3, got {self.window}")


def _coefficients(field: np.ndarray) -> list:
    return [spline_coefficients(np.ascontiguousarray(field[..., k])) for k in range(field.shape[-1])]


def _warp_channel_rows(coefs: list, rows: np.ndarray, disp: np.ndarray) -> np.ndarray:
    return np.stack([warp_coefficient_rows(c, rows, disp) for c in coefs], axis=-1)


#: Motions between frame pairs recently computed in this process, keyed by the two
#: fields' contents and the parameters: successive output instants of a rolling-shutter
#: camera share a frame pair, so a task (or the next task of the camera on this worker)
#: finds the motion of the pair it shares with the previous instant here. Keyed by
#: content, so a hit returns exactly what :func:`field_motion` would.
_MOTION_CACHE: OrderedDict = OrderedDict()
_MOTION_CACHE_SIZE = 8
_MOTION_LOCK = threading.Lock()


def _digest(a: np.ndarray) -> bytes:
    # SHA-256 runs on the CPU's SHA extensions: 0.7 ms per paper-scale flow field against
    # BLAKE2b's 1.3 ms (four digests per resampled frame: 9 % of the resample task)
    a = np.ascontiguousarray(a, dtype=np.float32)
    return hashlib.sha256(memoryview(a).cast("B")).digest() + repr(a.shape).encode()


def field_digest(field: np.ndarray) -> bytes:
    """The motion cache's key of one flow field (its contents and shape): pass it to
    :func:`cached_field_motion` / :func:`resample_flow` where the caller has it already."""
    return _digest(field)


def cached_field_motion(source: np.ndarray, target: np.ndarray, *, digests: tuple[bytes, bytes] | None = None,
                        **kwargs) -> np.ndarray:
    """:func:`field_motion`, remembered for the last few frame pairs of this process.

    ``digests``: :func:`field_digest` of ``source`` and ``target`` if the caller kept them
    (the resampling of neighbouring instants meets each raw field several times)."""
    ds, dt = digests if digests is not None else (_digest(source), _digest(target))
    key = (ds, dt, tuple(sorted(kwargs.items())))
    with _MOTION_LOCK:
        hit = _MOTION_CACHE.get(key)
        if hit is not None:
            _MOTION_CACHE.move_to_end(key)
            return hit.copy()
    m = field_motion(source, target, **kwargs)
    with _MOTION_LOCK:
        _MOTION_CACHE[key] = m.copy()
        while len(_MOTION_CACHE) > _MOTION_CACHE_SIZE:
            _MOTION_CACHE.popitem(last=False)
    return m


def field_motion(source: np.ndarray, target: np.ndarray, *, window: int = 15, levels: int = 3,
                 iterations: int = 4, regularisation: float = 1e-2, finest: int = 0) -> np.ndarray:
    """Motion ``m`` between two multi-channel fields: ``source(p) ~= target(p + m(p))``.

    Dense pyramidal Lucas-Kanade summing the structure tensors of all channels (here the
    u and v flow components), with a Tikhonov term so that regions without structure get
    zero motion. Used between successive flow fields of one camera (paper sec. 4).

    Parameters
    ----------
    source, target : ndarray, shape (h, w, C)
    window : int
        Window edge (cells, odd).
    finest : int
        Finest pyramid level estimated (0: the fields' own grid); below it the motion is
        only prolonged to the fields' grid.

    Returns
    -------
    m : ndarray, shape (h, w, 2), float32 (component 0 = columns, 1 = rows)
    """
    src = np.asarray(source, np.float32)
    tgt = np.asarray(target, np.float32)
    if src.ndim == 2:
        src, tgt = src[..., None], tgt[..., None]
    C = src.shape[-1]
    # per level: lists of 2-D channel images (fine first)
    pyr_s = [[np.ascontiguousarray(src[..., k]) for k in range(C)]]
    pyr_t = [[np.ascontiguousarray(tgt[..., k]) for k in range(C)]]
    for _ in range(levels - 1):
        if min(pyr_s[-1][0].shape) < 2 * window:
            break
        pyr_s.append([cv2.pyrDown(a) for a in pyr_s[-1]])
        pyr_t.append([cv2.pyrDown(a) for a in pyr_t[-1]])
    h, w = pyr_s[-1][0].shape
    mu = np.zeros((h, w), np.float32)
    mv = np.zeros((h, w), np.float32)
    taps = np.full(window, 1.0 / window, np.float32)

    def box(a):
        return cv2.sepFilter2D(a, cv2.CV_32F, taps, taps, borderType=cv2.BORDER_REFLECT)

    stop = min(finest, len(pyr_s) - 1)
    for lev in range(len(pyr_s) - 1, stop - 1, -1):
        s_ch, t_ch = pyr_s[lev], pyr_t[lev]
        h, w = s_ch[0].shape
        if mu.shape != (h, w):
            mu, mv = prolong_flow(mu, mv, (h, w))
        gx = [cv2.Scharr(a, cv2.CV_32F, 1, 0, scale=1 / 32) for a in s_ch]
        gy = [cv2.Scharr(a, cv2.CV_32F, 0, 1, scale=1 / 32) for a in s_ch]
        sxx = box(sum(g * g for g in gx))
        sxy = box(sum(a * b for a, b in zip(gx, gy)))
        syy = box(sum(g * g for g in gy))
        lam = np.float32(regularisation * float(np.percentile((sxx + syy)[::2, ::2], 99)) + 1e-12)
        pxx = sxx + lam
        pyy = syy + lam
        det = pxx * pyy - sxy * sxy
        coefs = [spline_coefficients(a) for a in t_ch]
        for _ in range(iterations):
            disp = np.stack([mu, mv], -1)
            bx = np.zeros((h, w), np.float32)
            by = np.zeros((h, w), np.float32)
            for k in range(C):
                # linearised around each cell's own warp (as in pipeline.flow LK)
                e = s_ch[k] - warp_coefficients(coefs[k], disp) + gx[k] * mu + gy[k] * mv
                bx += gx[k] * e
                by += gy[k] * e
            bx = box(bx)
            by = box(by)
            mu = ((pyy * bx - sxy * by) / det).astype(np.float32)
            mv = ((pxx * by - sxy * bx) / det).astype(np.float32)
    for lev in range(stop - 1, -1, -1):  # levels below ``finest``: the motion prolonged only
        mu, mv = prolong_flow(mu, mv, pyr_s[lev][0].shape)
    return np.stack([mu, mv], -1)


def resample_flow(raw: np.ndarray, first_frame: int, target_time: float, *, offset: float,
                  frame_rate: float, line_time: float, flow_grid: FlowGrid,
                  excluded_frames=(), params: ResampleParams = ResampleParams(),
                  digests: list | None = None) -> np.ndarray:
    """One camera's flow field at the session instant ``target_time``, row by row.

    Paper sec. 4 and Figure 5: flow-grid row ``i`` of raw frame ``f`` was exposed at
    ``offset + f / frame_rate + row_of_cell[i] * line_time``. For each row the instant
    falls between two usable frames ``a0 <= phi_i < a1`` (flash frames excluded) with
    weight ``alpha_i = (phi_i - a0) / (a1 - a0)``. With ``method="motion"`` the motion
    ``m`` between the fields (``F_a0(p) ~= F_a1(p + m)``, :func:`field_motion`) is
    estimated once per frame pair and the row is read from
    ``(1 - alpha) F_a0(p - alpha m) + alpha F_a1(p + (1 - alpha) m)``. Instants before
    the first or after the last usable frame are clamped to that frame.

    Parameters
    ----------
    raw : ndarray, shape (k, h, w, 2)
        Flow fields of the consecutive raw frames ``first_frame .. first_frame + k - 1``
        (see :func:`frames_needed`).
    first_frame : int
        Absolute index of ``raw[0]``.
    target_time : float
        Session time, seconds.
    offset, frame_rate, line_time : float
        The camera's timing (seconds, frames per second, seconds per row).
    flow_grid : FlowGrid
        Geometry of the flow grid (row centres in image rows).
    excluded_frames : iterable of int
        Absolute indices of frames that must not be used (the flash).
    params : ResampleParams
    digests : list of bytes, optional
        :func:`field_digest` of each ``raw[j]`` (``None`` entries computed here): the
        motion cache's keys, which a caller resampling neighbouring instants can keep.

    Returns
    -------
    flow : ndarray, shape (h, w, 2), float32
    """
    raw = np.asarray(raw, dtype=np.float32)
    k, h, w = raw.shape[:3]
    if (h, w) != tuple(flow_grid.shape):
        raise ValueError(f"raw flow grid {(h, w)} does not match the flow grid {flow_grid.shape}")
    excluded = set(int(e) for e in excluded_frames)
    usable = [j for j in range(k) if first_frame + j not in excluded]
    if not usable:
        raise ValueError(f"no usable frame among {first_frame}..{first_frame + k - 1} "
                         f"(excluded: {sorted(excluded)})")
    phi = _fractional_frame(target_time, flow_grid.row_of_cell(), offset=offset,
                            frame_rate=frame_rate, line_time=line_time) - first_frame
    ua = np.asarray(usable, dtype=np.float64)
    # bracket each row between usable frames j0 <= phi < j1 (clamped at the ends)
    pos = np.searchsorted(ua, phi, side="right")
    j0 = ua[np.clip(pos - 1, 0, len(ua) - 1)]
    j1 = ua[np.clip(pos, 0, len(ua) - 1)]
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.where(j1 > j0, (phi - j0) / np.where(j1 > j0, j1 - j0, 1.0), 0.0)
    alpha = np.clip(alpha, 0.0, 1.0)
    j0 = j0.astype(int)
    j1 = j1.astype(int)
    if params.method == "nearest":
        j0 = np.where(alpha >= 0.5, j1, j0)
        alpha = np.zeros_like(alpha)
    n_clamped = int(np.sum((phi < ua[0]) | (phi > ua[-1])))
    if n_clamped:
        log.debug("resample_flow: %d of %d rows clamped to the ends of frames %d..%d",
                  n_clamped, h, first_frame + usable[0], first_frame + usable[-1])
    out = np.empty((h, w, 2), np.float32)
    coef_memo: dict = {}

    def coefs(j):  # a frame can be the end of one pair and the start of the next
        if j not in coef_memo:
            coef_memo[j] = _coefficients(raw[j])
        return coef_memo[j]

    for a, b in sorted(set(zip(j0.tolist(), j1.tolist()))):
        rows = np.flatnonzero((j0 == a) & (j1 == b))
        al = alpha[rows].astype(np.float32)[:, None, None]
        fa = raw[a]
        if a == b or params.method == "nearest" or np.all(al == 0):
            out[rows] = fa[rows]
            continue
        fb = raw[b]
        if params.method == "linear":
            out[rows] = (1 - al) * fa[rows] + al * fb[rows]
            continue
        keys = None
        if digests is not None:
            keys = tuple(digests[j] if digests[j] is not None else _digest(raw[j]) for j in (a, b))
        m = cached_field_motion(fa, fb, window=params.window, levels=params.levels,
                                iterations=params.iterations, regularisation=params.regularisation,
                                finest=params.finest_level, digests=keys)
        # only the rows that use this frame pair are warped
        mr = m[rows]
        wa = _warp_channel_rows(coefs(a), rows, -al * mr)
        wb = _warp_channel_rows(coefs(b), rows, (1 - al) * mr)
        out[rows] = (1 - al) * wa + al * wb
    return out
