"""Builds the HTML report of a result store: reads via storage, computes via pipeline, writes via storage.

The one place that knows both sides of the report:

* :class:`schlieren.storage.report.ReportReader` gives plain data (arrays one frame at
  a time, attributes, completion markers, Grid, cameras, medium);
* :mod:`schlieren.workers.report.figures`, :mod:`~schlieren.workers.report.volume_figures`
  and :mod:`~schlieren.workers.report.volume_render` draw the figures and render the volume
  (the sections in :mod:`~schlieren.workers.report.sections`),
  :mod:`schlieren.pipeline.residuals` with :func:`schlieren.pipeline.tomography.build_geometry`
  re-projects the reconstruction for the residuals
  (:mod:`~schlieren.workers.report.residual_section`);
* :class:`schlieren.storage.report.ReportWriter` writes the finished RGB images, the GIF,
  ``index.html`` and ``summary.json``.

This module holds the entry point :func:`build_report` and the page's tables (summary,
accuracy, completion). No Dask: the figures are small and each camera's forward operator
is built once.
"""

from __future__ import annotations

import html
import json
import logging
import os
from pathlib import Path

import numpy as np

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.storage import location
from schlieren.storage.report import ReportPage, ReportReader, ReportWriter, fmt_number, frame_range, html_table
from schlieren.workers.report._common import _finite, _get
from schlieren.workers.report.capture_section import capture_section
from schlieren.workers.report.residual_section import _residual_section
from schlieren.workers.report.sections import (_deflection_section, _hull_section, _render_section,
                                               _slices_section, _timings_section)
from schlieren.workers.report.uncertainty_section import uncertainty_section

__all__ = ["build_report"]

log = logging.getLogger(__name__)


def build_report(store_path: str | os.PathLike, out_dir: str | os.PathLike, *, frames=None,
                 render_size: tuple[int, int] | None = None, max_cameras: int | None = None,
                 evaluation: dict | None = None) -> Path:
    """Write figures, an animation and ``index.html`` for a result store.

    Reads whatever the store holds: missing arrays, unfinished frames (completion
    markers ``status/<stage>`` unset, or NaN-filled chunks) and missing attributes are
    listed on the page instead of failing.

    Parameters
    ----------
    store_path : path
        The Zarr result store (read-only).
    out_dir : path
        Created if needed; files in it are overwritten.
    frames : (a, b), optional
        Half-open range of capture frames to show (default: all). The single-frame figures
        use the middle complete frame; the animation covers the complete frames of the range.
    render_size : (width, height), optional
        Pixels of each volume rendering (default: 480 on the long side, the box's aspect).
    max_cameras : int, optional
        Deflection and residual figures for at most this many cameras (tables list all).
    evaluation : dict, optional
        Accuracy against a ground truth (``workers.evaluate.evaluate`` output:
        ``{"frames": [{"frame", "time", "rms", "psnr", ...}], "overall": {"rms", "psnr", ...}}``),
        shown as a table (SPEC section 4).

    Returns
    -------
    Path
        ``out_dir / "index.html"`` (beside it: ``figures/`` and ``summary.json``).

    Raises
    ------
    StoreError
        The store is missing or of another format, or ``frames`` is outside its frames.
    """
    rd = ReportReader(store_path)
    writer = ReportWriter(out_dir)
    attrs = rd.attrs
    name = rd.name
    page = ReportPage(title=f"schlieren report: {name}")
    page.missing = rd.missing_arrays
    for key in ("format", "session", "params", "version", "stage_times"):
        if key not in attrs:
            page.missing.append(f"attribute {key}")

    n_frames = rd.n_frames
    sel = frame_range(frames, n_frames, rd.capture_index(0)) if n_frames else range(0)
    shown = _pick_shown(rd, sel, n_frames)
    times = rd.times()
    medium = rd.medium()
    params = rd.params
    grid = rd.grid()
    cameras, cam_note = rd.cameras()

    page.add("Summary", _summary_html(rd, store_path, name, grid, cameras, n_frames, sel, shown, times, medium),
             "summary")
    if evaluation:
        _accuracy_section(page, evaluation)
    _completion_section(page, rd)
    _deflection_section(page, rd, writer, shown, cameras, max_cameras)
    capture_section(page, rd, writer, cameras)
    if grid is not None:
        _hull_section(page, rd, grid, writer, shown)
        _slices_section(page, rd, grid, writer, shown, times)
        uncertainty_section(page, rd, grid, writer, shown, times)
        _render_section(page, rd, grid, writer, sel, shown, times, medium.refractivity_ambient, render_size)
    _residual_section(page, rd, grid, cameras, cam_note, writer, sel, shown, medium, max_cameras, params)
    _timings_section(page, attrs, writer)
    if params or attrs.get("derived"):
        page.add("Parameters", _parameters_html(params, attrs.get("derived")), "params")
    page.summary.update({"session": name, "frames": [rd.capture_index(sel.start), rd.capture_index(sel.start)
                                                     + len(sel)] if len(sel) else [],
                         "shown_frame": None if shown is None else rd.capture_index(shown),
                         "missing": page.missing})
    return writer.finish(page)


def _parameters_html(params, derived) -> str:
    """The values the run derived in place of parameters (the store's ``derived`` attribute:
    requested, effective, unit, from what), then every parameter as stored."""
    body = ""
    if isinstance(derived, dict) and derived:
        def show(v):
            return ", ".join(fmt_number(x) for x in v) if isinstance(v, list) else \
                "not given" if v is None else fmt_number(v)

        rows = [[name, show(d.get("requested")), show(d.get("effective")), d.get("unit", ""), d.get("from", "")]
                for name, d in derived.items() if isinstance(d, dict)]
        body += ("<p>Values the run derived in place of the parameters (per-camera values in camera "
                 "order):</p>" + html_table(["parameter", "requested", "effective", "unit", "from"], rows))
    if params:
        body += f"<pre>{html.escape(json.dumps(params, indent=2, default=str))}</pre>"
    return body


def _pick_shown(rd: ReportReader, sel: range, n_frames: int) -> int | None:
    """The middle frame of ``sel`` among those with the most advanced complete results."""
    if not len(sel):
        return None
    for name in ("refractivity", "gradient", "hull", "flow"):
        done = rd.frame_done(name, n_frames)
        cands = [f for f in sel if done[f]]
        if cands:
            return cands[len(cands) // 2]
    return sel[len(sel) // 2]


def _summary_html(rd: ReportReader, store_path, name, grid: Grid | None, cameras, n_frames, sel, shown, times,
                  medium: Medium) -> str:
    attrs = rd.attrs
    session = rd.session
    when = "none" if shown is None else f"frame {rd.capture_index(shown)}" + (
        f" (t = {fmt_number(times[shown], 6)} s)" if times is not None and np.isfinite(times[shown]) else "")
    rows = [["session", name], ["store", location.display(store_path)],
            ["format", attrs.get("format", "missing")], ["software version", attrs.get("version", "missing")],
            ["frames in store", n_frames],
            ["frames shown", f"{rd.capture_index(sel.start)}:{rd.capture_index(sel.start) + len(sel)}"
             if len(sel) else "none"],
            ["single-frame figures", when]]
    if _get(session, "frame_rate") is not None:
        rows.append(["frame rate", f"{fmt_number(session['frame_rate'])} 1/s"])
    if cameras:
        rows.append(["cameras", ", ".join(c.name for c in cameras)])
    if grid is not None:
        nz, ny, nx = grid.shape
        rows.append(["volume grid (x, y, z)", f"{nx} x {ny} x {nz} voxels of {grid.voxel_size * 1e3:.3g} mm"])
        rows.append(["box (m)", f"x {grid.vmin[0]:.4g}..{grid.vmax[0]:.4g}, y {grid.vmin[1]:.4g}.."
                                f"{grid.vmax[1]:.4g}, z {grid.vmin[2]:.4g}..{grid.vmax[2]:.4g}"])
    rows.append(["ambient medium", f"n = {medium.n_ambient:.6f}, T = {medium.T_ambient:.2f} K, "
                                   f"p = {medium.p_ambient:.0f} Pa, G = {medium.gladstone_dale:.3g} m^3/kg"])
    return html_table(["", ""], rows, "kv")


def _accuracy_section(page: ReportPage, evaluation: dict):
    """SPEC section 4: relative RMS of the refractivity against ground truth, and PSNR."""
    rows = []
    for r in evaluation.get("frames") or []:
        rms = r.get("rms")
        rms_p = r.get("rms_plume")
        rows.append([r.get("frame", ""), fmt_number(r.get("time"), 6),
                     fmt_number(100.0 * rms if rms is not None else None), fmt_number(r.get("psnr")),
                     fmt_number(r.get("psnr_plume")), fmt_number(r.get("peak_ratio")), r.get("truth_from", "")])
    ov = evaluation.get("overall") or {}
    pl = evaluation.get("plume") or {}
    if ov:
        rms = ov.get("rms")
        rows.append(["overall", "", fmt_number(100.0 * rms if rms is not None else None),
                     fmt_number(ov.get("psnr")), fmt_number(pl.get("psnr")), "", ""])
        page.summary["accuracy"] = {k: (_finite(v) if isinstance(v, (int, float)) else v) for k, v in ov.items()}
        if pl:
            page.summary["accuracy"]["psnr_plume"] = _finite(pl.get("psnr"))
    body = ("<p>Refractivity against the ground truth: RMS error relative to the truth's range per frame, and "
            "PSNR = 20 log10(1 / RMS) (paper Table 1), over the whole box and in the plume (voxels where the "
            "truth departs from ambient by more than 1 % of its range; the same normalisation). Peak ratio: "
            "the reconstructed largest excursion from ambient over the truth's.</p>"
            + html_table(["frame", "time (s)", "relative RMS (%)", "PSNR (dB)", "in-plume PSNR (dB)", "peak ratio",
                          "truth"], rows, "num"))
    if evaluation.get("truth"):
        body += f"<p>Truth: <code>{html.escape(str(evaluation['truth']))}</code></p>"
    page.add("Accuracy", body, "accuracy")


def _completion_section(page: ReportPage, rd: ReportReader):
    rows = [[stage, f"{n} of {total}", "complete" if n == total else ("not started" if n == 0 else "partial")]
            for stage, n, total in rd.completion()]
    if rows:
        page.add("Completion", "<p>Completion markers (<code>status/&lt;stage&gt;</code>), per camera-frame "
                               "or frame.</p>" + html_table(["stage", "done", "state"], rows, "num"), "completion")
        page.summary["completion"] = {r[0]: r[1] for r in rows}
