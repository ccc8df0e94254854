"""Frames a reconstruction must not use: dark, saturated, frozen (repeated) and dropped frames.

Cheap camcorders and real labs produce them: a frame taken while the lights flickered or
the lens cap was on (dark), a frame blown out by a reflection or the strobe of another
rig (saturated), and a frame the camera repeated because it dropped the real one
(frozen: identical to the previous frame, which sensor noise never is). Each would put a
false deflection field into the tomography (docs/tuning.md, "Frame quality").
A camera that dropped a frame without repeating one leaves a time slot with no frame
(a gap in the numbered file names or in a video's timestamps, found by
:mod:`schlieren.storage.frames`): the slot is flagged :data:`DROPPED`, so frame indices
stay time indices and the frames after the gap keep their true capture times.
:func:`frame_quality` measures a frame against its camera's reference and the previous
frame; the run excludes flagged frames from rolling-shutter resampling exactly like the
strobe flash frames (``excluded_frames`` of :func:`schlieren.pipeline.sync.resample_flow`).

A raw frame of the rolling-shutter margins that no output instant needs is not processed
at all: its slot is flagged :data:`UNUSED` (statistics NaN, no flow), which is not a
problem of the capture (:data:`PROBLEMS` leaves it out).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["DARK", "SATURATED", "FROZEN", "DROPPED", "UNUSED", "PROBLEMS", "QUALITY_NAMES", "FrameQualityParams",
           "frame_quality", "dropped_quality", "unused_quality", "flag_names"]

DARK, SATURATED, FROZEN, DROPPED, UNUSED = 1, 2, 4, 8, 16
#: The flags that say something is wrong with a frame (what the run reports as excluded).
PROBLEMS = DARK | SATURATED | FROZEN | DROPPED
_CV_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.int16), np.dtype(np.float32), np.dtype(np.float64))
#: Entries of the vector :func:`frame_quality` returns.
QUALITY_NAMES = ("mean", "saturated_fraction", "mean_abs_change", "flags", "std", "min", "max")
_NAMES = {DARK: "dark", SATURATED: "saturated", FROZEN: "frozen (repeats the previous frame)",
          DROPPED: "dropped by the camera (no frame at this time)",
          UNUSED: "not needed by any output instant (not processed)"}


@dataclass(frozen=True)
class FrameQualityParams:
    """Thresholds of :func:`frame_quality`.

    Attributes
    ----------
    dark_fraction : float
        Dark: the frame's mean grey level is below this fraction of the reference's.
    saturated_fraction : float
        Saturated: more than this fraction of the pixels sit at the sensor's full scale.
    frozen_level : float
        Frozen: the mean absolute change from the previous frame is at most this fraction
        of full scale (0.0026 grey levels at 8 bits: fewer than one pixel in 400 changed by
        one level). Sensor noise alone gives about 1 grey level on raw frames, but lossy
        video removes it: H.264 frames of a weak, slowly moving plume at camcorder bitrates
        (0.16 bit/pixel) change by only 0.02-0.12 grey levels from frame to frame, and the
        former default (1e-4, 0.026 levels) excluded such genuine frames. A repeated frame
        that the codec re-encoded with changes above this level is not caught here.
    """

    dark_fraction: float = 0.25
    saturated_fraction: float = 0.25
    frozen_level: float = 1e-5


def frame_quality(frame: np.ndarray, previous: np.ndarray | None, *, reference_mean: float,
                  full_scale: float | None, params: FrameQualityParams = FrameQualityParams(),
                  finite: bool = False) -> np.ndarray:
    """Statistics and flags of one frame.

    Parameters
    ----------
    frame : ndarray, shape (H, W)
        Grey levels.
    previous : ndarray, shape (H, W), or None
        The camera's previous frame in capture order (None for the first frame).
    reference_mean : float
        Mean grey level of the camera's reference (background) image.
    full_scale : float or None
        The sensor's largest value (255, 65535); None (floating-point frames) skips the
        saturation test.
    finite : bool
        The caller knows that ``frame`` holds no NaN or inf (grey levels decoded from
        integer samples): floating-point frames skip the finiteness scan.

    Returns
    -------
    ndarray, shape (7,), float32
        :data:`QUALITY_NAMES`: ``mean``, ``saturated_fraction``, ``mean_abs_change`` (NaN
        without a previous frame), ``flags`` (bit sum of :data:`DARK`, :data:`SATURATED`,
        :data:`FROZEN`), and the grey levels' ``std``, ``min`` and ``max`` (exposure drift,
        the strobe flash; NaN for a frame with NaN pixels). These are the run's per-frame
        statistics: every frame a reconstruction uses passes through one deflection task.
    """
    f = np.asarray(frame)
    p = None if previous is None else np.asarray(previous)
    if f.ndim == 2 and f.dtype in _CV_DTYPES and (p is None or p.dtype == f.dtype) and \
            (f.dtype.kind != "f" or finite or cv2.checkRange(f)[0]):
        # OpenCV's sums accumulate in double without float64 copies of the frame (one
        # deflection task per camera-frame calls this; docs/tuning.md, "Speed")
        m, sd = cv2.meanStdDev(f)
        mean, std = float(m[0, 0]), float(sd[0, 0])
        lo, hi = (float(v) for v in cv2.minMaxLoc(f)[:2])
        change = float(cv2.mean(cv2.absdiff(f, p))[0]) if p is not None else np.nan
    else:  # other types, and frames with NaN (whose statistics are NaN)
        f = f.astype(np.float64)
        mean, std, lo, hi = float(f.mean()), float(f.std()), float(f.min()), float(f.max())
        change = float(np.mean(np.abs(f - p.astype(np.float64)))) if p is not None else np.nan
    if full_scale is None:
        sat = 0.0
    else:  # no pixel at full scale when the maximum is below it (skips a pass over the frame)
        sat = float(np.count_nonzero(f >= full_scale)) / f.size if not hi < full_scale else 0.0
    flags = 0
    if mean < params.dark_fraction * float(reference_mean):
        flags |= DARK
    if sat > params.saturated_fraction:
        flags |= SATURATED
    if previous is not None and change <= params.frozen_level * float(full_scale or max(hi, 1.0)):
        flags |= FROZEN
    return np.array([mean, sat, change, flags, std, lo, hi], dtype=np.float32)


def dropped_quality() -> np.ndarray:
    """The :func:`frame_quality` vector of a time slot with no frame (statistics NaN)."""
    return np.array([np.nan, np.nan, np.nan, DROPPED, np.nan, np.nan, np.nan], dtype=np.float32)


def unused_quality() -> np.ndarray:
    """The :func:`frame_quality` vector of a margin frame no output instant needs (not read)."""
    return np.array([np.nan, np.nan, np.nan, UNUSED, np.nan, np.nan, np.nan], dtype=np.float32)


def flag_names(flags: float) -> list[str]:
    """``["dark", ...]`` for a flags value (NaN or 0: none)."""
    if not np.isfinite(flags):
        return []
    return [name for bit, name in _NAMES.items() if int(flags) & bit]
