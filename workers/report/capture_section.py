"""The report's capture section (issue 33): each camera's motion against its reference
over the frames, the frames' gain and offset, the defective pixels and the flow's
pre-smoothing chosen from the reference's sharpness.

Reads ``background_motion``, ``photometric``, ``capture_fit``, ``defective_pixels`` and ``presmooth``
(:mod:`schlieren.pipeline.capture`) through the
:class:`~schlieren.storage.report.ReportReader`; a store without them (an older run) says
so on the page.
"""

from __future__ import annotations

import html
import warnings

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from schlieren.pipeline.capture import (DEFECT_NAMES, FALLBACK, GAIN_UNKNOWN, MOTION_APPLIED, PHOTOMETRIC_APPLIED,
                                        motion_displacement)
from schlieren.storage.report import ReportPage, ReportReader, ReportWriter, fmt_number, html_img, html_table
from schlieren.workers.report._common import _figure
from schlieren.workers.report.figures import _new_figure

__all__ = ["capture_section", "motion_figure"]


def _corner_extent(motion: np.ndarray, image_size) -> np.ndarray:
    """Largest displacement over the image's corners of each motion vector (..., 8), pixels."""
    W, H = image_size
    xs = np.array([0.0, W - 1.0, 0.0, W - 1.0])
    ys = np.array([0.0, 0.0, H - 1.0, H - 1.0])
    m = np.nan_to_num(np.asarray(motion, np.float64))
    out = np.zeros(m.shape[:-1])
    for x, y in zip(xs, ys):
        dx, dy = motion_displacement(m, x, y, image_size)
        out = np.maximum(out, np.hypot(dx, dy))
    return np.where(np.isfinite(motion).all(axis=-1), out, np.nan)


def motion_figure(frames: np.ndarray, motion: np.ndarray, names: list[str], image_size) -> Figure:
    """The background's translation (pixels at the image centre) and rotation (pixels at the
    image's corner) per camera over the raw frames.

    Parameters
    ----------
    frames : ndarray, shape (R,)
        Capture indices of the raw frames.
    motion : ndarray, shape (C, R, 8)
        ``background_motion`` (NaN where no flow was computed).
    names : list of str
    image_size : (int, int)
    """
    W, H = image_size
    corner = 0.5 * np.hypot(W - 1, H - 1)
    rot = 0.5 * (motion[..., 4] - motion[..., 3]) * corner
    fig = _new_figure(9.0, 6.6)
    axes = fig.subplots(3, 1, sharex=True)
    for c, name in enumerate(names):
        for ax, y in zip(axes, (motion[c, :, 0], motion[c, :, 1], rot[c])):
            ax.plot(frames, y, marker="o", ms=2.5, lw=1.0, label=name if ax is axes[0] else None)
    for ax, label in zip(axes, ("u (px, image x)", "v (px, image y)", "rotation (px at a corner)")):
        ax.set_ylabel(label)
        ax.axhline(0.0, color="0.6", lw=0.6)
        ax.grid(True, lw=0.3)
    axes[-1].set_xlabel("capture frame")
    fig.suptitle("background motion against the reference")
    axes[-1].xaxis.set_major_locator(MaxNLocator(integer=True))
    if len(names) <= 16:
        fig.legend(fontsize=7, loc="outside right upper")
    return fig


def photometric_figure(frames: np.ndarray, photometric: np.ndarray, names: list[str]) -> Figure:
    """Each frame's mean gain and its row banding (the gain profile's range) per camera."""
    gain = photometric[:, :, 0, :]
    fig = _new_figure(9.0, 4.2)
    axes = fig.subplots(2, 1, sharex=True)
    with warnings.catch_warnings():  # all-NaN camera-frames (no flow computed)
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(gain, axis=-1)
        band = np.nanmax(gain, axis=-1) - np.nanmin(gain, axis=-1)
    for c, name in enumerate(names):
        axes[0].plot(frames, 100 * (mean[c] - 1.0), marker="o", ms=2.5, lw=1.0)
        axes[1].plot(frames, 100 * band[c], marker="o", ms=2.5, lw=1.0)
    axes[0].set_ylabel("mean gain - 1 (%)")
    axes[1].set_ylabel("banding (gain range, %)")
    axes[1].set_xlabel("capture frame")
    axes[1].xaxis.set_major_locator(MaxNLocator(integer=True))
    axes[0].set_title("gain of each frame against the reference (lamp flicker, rolling-shutter banding)")
    for ax in axes:
        ax.grid(True, lw=0.3)
    return fig


def capture_section(page: ReportPage, rd: ReportReader, writer: ReportWriter, cameras) -> None:
    """Add the "Camera motion and lighting" section."""
    title = "Camera motion and lighting"
    motion = rd.whole("background_motion")
    if motion is None:
        page.add(title, "<p class='missing'>No <code>background_motion</code> in the store (a run of a version "
                        "without the capture corrections).</p>", "capture")
        return
    C, R = motion.shape[:2]
    names = [c.name for c in cameras] if cameras and len(cameras) == C else rd.camera_names(C)
    raw = rd.whole("raw_frame")
    frames = np.asarray(raw, np.int64) if raw is not None and len(raw) == R else np.arange(R)
    size = tuple(cameras[0].image_size) if cameras else _image_size(rd)
    parts = [html_img(_figure(writer, "background_motion.png", motion_figure(frames, motion, names, size)),
                      "background motion per camera",
                      "The background's motion against each camera's reference, measured on the pixels whose "
                      "rays miss the volume: translation at the image centre and rotation as the displacement "
                      "it gives an image corner (stored in <code>background_motion</code>).")]
    ph = rd.whole("photometric")
    if ph is not None:
        parts.append(html_img(_figure(writer, "photometric.png", photometric_figure(frames, ph, names)),
                              "gain per camera", "The gain of each frame against its reference (stored with the "
                                                 "offsets in <code>photometric</code>)."))
    parts.append(_camera_table(rd, motion, names, size))
    page.add(title, "\n".join(parts), "capture")


def _image_size(rd: ReportReader) -> tuple[int, int]:
    d = rd.whole("defective_pixels")
    return (int(d.shape[2]), int(d.shape[1])) if d is not None else (1, 1)


def _camera_table(rd: ReportReader, motion: np.ndarray, names: list[str], size) -> str:
    """Per camera: the largest motion, the frames corrected, the defective pixels and the
    flow's pre-smoothing."""
    fit = rd.whole("capture_fit")
    defects = rd.whole("defective_pixels")
    smooth = rd.whole("presmooth")
    ext = _corner_extent(motion, size)
    rows = []
    for c, name in enumerate(names):
        flags = fit[c, :, 4] if fit is not None else np.array([])
        ok = np.isfinite(flags)
        fl = flags[ok].astype(int)
        counts = ([int(np.count_nonzero(defects[c] & bit)) for bit in DEFECT_NAMES] if defects is not None
                  else ["-"] * len(DEFECT_NAMES))
        e = ext[c][np.isfinite(ext[c])]
        rows.append([html.escape(name), fmt_number(float(e.max())) if e.size else "-",
                     f"{int(np.count_nonzero(fl & MOTION_APPLIED))} / {fl.size}",
                     f"{int(np.count_nonzero(fl & PHOTOMETRIC_APPLIED))} / {fl.size}",
                     f"{int(np.count_nonzero(fl & FALLBACK))}",
                     f"{int(np.count_nonzero(fl & GAIN_UNKNOWN))}",
                     fmt_number(float(np.nanmean(fit[c, :, 0]))) if fit is not None and ok.any() else "-", *counts,
                     fmt_number(float(smooth[c])) if smooth is not None and np.isfinite(smooth[c]) else "-"])
    header = ["camera", "largest motion (px)", "motion removed (frames)", "gain/offset removed (frames)",
              "measured on every pixel (frames)", "gain unknown, not normalised (frames)", "static fraction"] + \
        [f"{n} pixels" for n in DEFECT_NAMES.values()] + ["flow pre-smoothing (px)"]
    return html_table(header, rows)
