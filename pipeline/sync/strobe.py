"""Strobe synchronisation (paper sec. 4, Figure 5): the band of rows a flash of negligible
duration at session time 0 lights in a rolling-shutter camera, the camera's time offset
its lower edge gives (to within a line time), and the frames that carry it (never used as
data).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .params import FlashParams

__all__ = ["FlashDetection", "FlashParams", "row_means", "detect_flash", "offset_from_flash", "flash_frames"]

log = logging.getLogger(__name__)


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


def detect_flash(row_means: np.ndarray, *, min_snr: float = FlashParams.min_snr,
                 min_contrast: float = FlashParams.min_contrast) -> FlashDetection:
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
