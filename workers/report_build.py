"""Builds the HTML report of a result store: reads via storage, computes via pipeline, writes via storage.

The one place that knows both sides of the report:

* :class:`schlieren.storage.report.ReportReader` gives plain data (arrays one frame at
  a time, attributes, completion markers, Grid, cameras, medium);
* :mod:`schlieren.pipeline.viz` draws the figures and renders the volume,
  :mod:`schlieren.pipeline.residuals` with :func:`schlieren.pipeline.tomography.build_geometry`
  re-projects the reconstruction for the residuals;
* :class:`schlieren.storage.report.ReportWriter` writes the finished RGB images, the GIF,
  ``index.html`` and ``summary.json``.

No Dask: the figures are small and each camera's forward operator is built once.
"""

from __future__ import annotations

import html
import json
import logging
import math
import os
from pathlib import Path

import numpy as np

from schlieren.pipeline import viz
from schlieren.pipeline.geometry import FlowGrid, Grid, Medium
from schlieren.storage import location
from schlieren.storage.report import (ReportPage, ReportReader, ReportWriter, fmt_number, frame_range,
                                      html_img, html_table, safe_name)

__all__ = ["build_report", "MAX_RESIDUAL_FRAMES", "STRIP_FRAMES"]

log = logging.getLogger(__name__)

MAX_RESIDUAL_FRAMES = 8
STRIP_FRAMES = 6
ANIMATION_FPS = 10.0


def _get(d: dict, key: str, default=None):
    return d.get(key, default) if isinstance(d, dict) else default


def _figure(writer: ReportWriter, name: str, fig) -> str:
    """Draw a Matplotlib figure to RGB, hand it to the writer, free it; returns the relative link."""
    rgb = viz.figure_to_rgb(fig)
    fig.clear()
    return writer.image(name, rgb)


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
    if grid is not None:
        _hull_section(page, rd, grid, writer, shown)
        _slices_section(page, rd, grid, writer, shown, times)
        _render_section(page, rd, grid, writer, sel, shown, times, medium.refractivity_ambient, render_size)
    _residual_section(page, rd, grid, cameras, cam_note, writer, sel, shown, medium, max_cameras, params)
    _timings_section(page, attrs, writer)
    if params:
        page.add("Parameters", f"<pre>{html.escape(json.dumps(params, indent=2, default=str))}</pre>", "params")
    page.summary.update({"session": name, "frames": [rd.capture_index(sel.start), rd.capture_index(sel.start)
                                                     + len(sel)] if len(sel) else [],
                         "shown_frame": None if shown is None else rd.capture_index(shown),
                         "missing": page.missing})
    return writer.finish(page)


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


def _finite(x) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None


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
        rows.append([r.get("frame", ""), fmt_number(r.get("time"), 6),
                     fmt_number(100.0 * rms if rms is not None else None), fmt_number(r.get("psnr")),
                     r.get("truth_from", "")])
    ov = evaluation.get("overall") or {}
    if ov:
        rms = ov.get("rms")
        rows.append(["overall", "", fmt_number(100.0 * rms if rms is not None else None),
                     fmt_number(ov.get("psnr")), ""])
        page.summary["accuracy"] = {k: (_finite(v) if isinstance(v, (int, float)) else v) for k, v in ov.items()}
    body = ("<p>Refractivity against the ground truth: RMS error relative to the truth's range per frame, and "
            "PSNR = 20 log10(1 / RMS) (paper Table 1).</p>"
            + html_table(["frame", "time (s)", "relative RMS (%)", "PSNR (dB)", "truth"], rows, "num"))
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


def _camera_names(rd: ReportReader, cameras, n) -> list[str]:
    if cameras and len(cameras) == n:
        return [c.name for c in cameras]
    return rd.camera_names(n)


def _deflection_section(page: ReportPage, rd: ReportReader, writer: ReportWriter, shown, cameras, max_cameras):
    title = "Deflections (paper Figure 4)"
    if not rd.has("flow") or shown is None:
        page.add(title, "<p class='missing'>No <code>flow</code> in the store.</p>", "deflections")
        return
    n_cam = rd.shape("flow")[0]
    names = _camera_names(rd, cameras, n_cam)
    threshold = rd.mask_threshold()
    units = rd.array_attrs("potential").get("units", "px$^2$") if rd.has("potential") else "px$^2$"
    parts = []
    for c in range(n_cam if max_cameras is None else min(n_cam, max_cameras)):
        flow = rd.camera_frame("flow", c, shown)
        if flow is None:
            parts.append(f"<p class='missing'>Camera {html.escape(names[c])}: flow of frame {rd.capture_index(shown)} "
                         "not computed yet.</p>")
            continue
        mask = rd.camera_frame("mask", c, shown)
        pot = rd.camera_frame("potential", c, shown)
        image, source = rd.camera_image(c, rd.capture_index(shown))
        fig = viz.deflection_figure(image, flow, mask=None if mask is None else mask.astype(bool), potential=pot,
                                    threshold=threshold, step=max(1, flow.shape[1] // 16),
                                    potential_units=str(units), title=f"camera {names[c]}, frame {rd.capture_index(shown)}")
        rel = _figure(writer, f"deflection_{safe_name(names[c])}.png", fig)
        parts.append(html_img(rel, f"deflections of camera {names[c]}",
                              f"Camera {names[c]} ({source}). Top: camera frame, deflection colour coding "
                              "(hue = direction, saturation = magnitude in pixels; key in the corner), quiver "
                              "plot. Bottom: Poisson-integrated deflections, threshold (or the deflection "
                              "magnitude when the store has no threshold), mask."))
    page.add(title, "\n".join(parts), "deflections")


def _hull_section(page: ReportPage, rd: ReportReader, grid: Grid, writer: ReportWriter, shown):
    hull = rd.volume("hull", shown) if shown is not None else None
    if hull is None:
        page.add("Visual hull", "<p class='missing'>No visual hull for this frame in the store.</p>", "hull")
        return
    fig = viz.hull_figure(hull.astype(bool), grid, title=f"visual hull, frame {rd.capture_index(shown)}")
    rel = _figure(writer, "hull.png", fig)
    page.add("Visual hull", html_img(rel, "visual hull",
                                     "The conservative visual hull: a rendering and the fraction of hull voxels "
                                     "along each world axis."), "hull")


def _slices_section(page: ReportPage, rd: ReportReader, grid: Grid, writer: ReportWriter, shown, times):
    if shown is None:
        return
    parts = []
    index = None
    r = rd.volume("refractivity", shown)
    if r is not None:
        index = np.unravel_index(np.nanargmin(r), r.shape)  # the hottest voxel
    tstamp = f", t = {fmt_number(times[shown], 6)} s" if times is not None and np.isfinite(times[shown]) else ""
    specs = [("refractivity", "refractivity n - 1", "10$^{-6}$", 1e6, "viridis"),
             ("temperature", "temperature", "K", 1.0, "inferno"),
             ("density", "density", "kg/m$^3$", 1.0, "cividis")]
    for key, label, units, factor, cmap in specs:
        vol = rd.volume(key, shown)
        if vol is None:
            continue
        if key == "temperature" and r is not None:  # T = T_amb r_amb / r is meaningless for r <= 0
            vol = np.where(r > 0, vol, np.nan)
        fig = viz.orthoslices_figure(vol * factor, grid, index=index, label=label, units=units, cmap=cmap,
                                     title=f"{label}, frame {rd.capture_index(shown)}{tstamp}")
        rel = _figure(writer, f"slices_{key}.png", fig)
        parts.append(html_img(rel, f"slices of {key}"))
    g = rd.volume("gradient", shown)
    if g is not None:
        mag = np.sqrt(np.sum(g ** 2, axis=-1))
        fig = viz.orthoslices_figure(mag, grid, index=index, label="|grad n|", units="1/m", cmap="magma",
                                     vectors=g, title=f"reconstructed gradient (arrows: in-plane components), "
                                                      f"frame {rd.capture_index(shown)}{tstamp}")
        rel = _figure(writer, "slices_gradient.png", fig)
        parts.append(html_img(rel, "slices of the gradient magnitude"))
    where = "" if index is None else " through the voxel of lowest refractivity (the hottest gas)"
    body = (f"<p>Axis-aligned slices{where}; world coordinates in millimetres.</p>" + "\n".join(parts)
            if parts else "<p class='missing'>No volume quantities for this frame in the store.</p>")
    page.add("Slices", body, "slices")


def _side_by_side(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """RGB images of one height in a row, separated by white gaps of ``gap`` pixels."""
    sep = np.full((images[0].shape[0], gap, 3), 255, np.uint8)
    parts = []
    for k, im in enumerate(images):
        parts.extend([sep, im] if k else [im])
    return np.concatenate(parts, axis=1)


def _render_section(page: ReportPage, rd: ReportReader, grid: Grid, writer: ReportWriter, sel, shown, times,
                    r_amb: float, render_size):
    # two streaming passes (one volume in memory at a time): the common scale, then the renderings
    deficit, available = 0.0, []
    for f in sel:
        v = rd.volume("refractivity", f)
        if v is not None:
            available.append(f)
            deficit = max(deficit, float(np.nanmax(r_amb - v)))
    if not available:
        page.add("Volume rendering", "<p class='missing'>No reconstructed <code>refractivity</code> in the "
                                     "store.</p>", "render")
        return
    scale = deficit if deficit > 0 else 1e-6
    tf = viz.TransferFunction(r_ambient=r_amb, scale=scale)

    def volume(f):
        return np.nan_to_num(rd.volume("refractivity", f), nan=r_amb)

    frames_rgb = {}  # RGB renderings are small; the volumes are not kept
    for f in available:
        t = times[f] if times is not None and np.isfinite(times[f]) else None
        img = viz.animation_frames([volume(f)], grid, r_ambient=r_amb, transfer=tf, image_size=render_size,
                                   times=None if t is None else [t])[0]
        writer.image(f"render_{rd.capture_index(f):05d}.png", img)
        frames_rgb[f] = img
    done = list(frames_rgb)
    key = shown if shown in frames_rgb else done[len(done) // 2]
    cap = rd.capture_index
    _figure(writer, "render.png", viz.render_figure(frames_rgb[key], tf, title=f"frame {cap(key)}"))
    # the shown frame from four sides (azimuth 30, 120, 210, 300 degrees)
    size = render_size or viz.fit_image_size(grid, azimuth_deg=30.0, elevation_deg=15.0, long_side=360)
    vol = volume(key)
    views = [viz.render_volume(vol, grid, azimuth_deg=az, elevation_deg=15.0, transfer=tf,
                               image_size=size) for az in (30.0, 120.0, 210.0, 300.0)]
    writer.image("render_views.png", _side_by_side(views))
    # a row of frames as in the paper's Figure 8
    pick = [done[i] for i in np.unique(np.linspace(0, len(done) - 1, min(STRIP_FRAMES, len(done))).round()
                                       .astype(int))]
    writer.image("render_strip.png", _side_by_side([frames_rgb[f] for f in pick]))
    fps = ANIMATION_FPS
    writer.animation("render.gif", np.stack([frames_rgb[f] for f in done]), fps=fps)
    links = " ".join(f'<a href="figures/render_{cap(f):05d}.png">{cap(f)}</a>' for f in done)
    skipped = [cap(f) for f in sel if f not in frames_rgb]
    body = (
        "<p>Emission-absorption ray marching of the refractivity (paper Figures 1 and 8): hot, "
        "less dense gas (refractivity below ambient) glows; one transfer function for all frames, "
        f"full signal at a deficit of {scale:.3g}.</p>"
        + html_img("figures/render.png", "volume rendering", f"Frame {cap(key)}.")
        + html_img("figures/render_views.png", "four views",
                   f"Frame {cap(key)} seen from azimuth 30, 120, 210 and 300 degrees (elevation 15).")
        + html_img("figures/render_strip.png", "rendering over time",
                   "Frames " + ", ".join(str(cap(f)) for f in pick) + ", left to right.")
        + html_img("figures/render.gif", "animation", f"Animation of {len(done)} frame(s) ({fps:g} per second).")
        + f"<p>Per-frame renderings: {links}</p>"
        + (f"<p class='missing'>Not reconstructed yet: frames {', '.join(map(str, skipped))}.</p>"
           if skipped else ""))
    page.add("Volume rendering", body, "render")


def _residual_section(page: ReportPage, rd: ReportReader, grid: Grid | None, cameras, cam_note,
                      writer: ReportWriter, sel, shown, medium: Medium, max_cameras, params):
    title = "Re-projection residuals"
    if not rd.has("flow") or grid is None or shown is None or not (rd.has("gradient") or rd.has("refractivity")):
        page.add(title, "<p class='missing'>Needs <code>flow</code> and a reconstructed <code>gradient</code> "
                        "(or <code>refractivity</code>) in the store.</p>", "residuals")
        return
    if not cameras:
        page.add(title, f"<p class='missing'>No usable camera calibration in the store"
                        f"{': ' + html.escape(cam_note) if cam_note else ''}.</p>", "residuals")
        return
    from schlieren.pipeline.residuals import predict_flows, residual_stats
    from schlieren.pipeline.tomography import TomoParams, build_geometry

    flow_shape = rd.shape("flow")
    if flow_shape[0] != len(cameras):
        page.add(title, f"<p class='missing'>The store has flow for {flow_shape[0]} cameras but "
                        f"{len(cameras)} calibrations.</p>", "residuals")
        return
    rows_f, cols_f = flow_shape[2:4]
    sizes = {cam.image_size for cam in cameras}
    W, H = cameras[0].image_size
    factor = int(_get(_get(rd.attrs, "run") or {}, "flow_factor") or (W // cols_f if cols_f else 0))
    if len(sizes) != 1 or factor < 1 or H // factor != rows_f or W // factor != cols_f:
        page.add(title, f"<p class='missing'>The flow grid ({rows_f} x {cols_f}) does not match the cameras' "
                        f"image sizes ({', '.join(map(str, sorted(sizes)))}).</p>", "residuals")
        return

    def gradient_of(f):
        g = rd.volume("gradient", f)
        if g is not None:
            return g, "stored"
        r = rd.volume("refractivity", f)
        if r is None:
            return None, ""
        h = grid.voxel_size
        gz, gy, gx = np.gradient(np.nan_to_num(r, nan=medium.refractivity_ambient), h)
        return np.stack([gx, gy, gz], axis=-1), "central differences of the refractivity"

    flow_done = rd.frame_done("flow", sel.stop)
    candidates = [f for f in sel if flow_done[f]]
    frames = sorted(set(candidates[i] for i in np.unique(
        np.linspace(0, len(candidates) - 1, min(MAX_RESIDUAL_FRAMES, len(candidates))).round().astype(int)))
        | ({shown} if shown in candidates else set())) if candidates else []
    grads = {}
    sources = set()
    for f in frames:
        g, src = gradient_of(f)
        if g is not None:
            grads[f] = g
            sources.add(src)
    if not grads:
        page.add(title, "<p class='missing'>No frame has both its flow and its reconstruction yet.</p>",
                 "residuals")
        return
    tparams = _get(params, "tomography") or {}
    tomo = TomoParams(step=float(tparams.get("step", TomoParams.step)))
    n_amb = float(tparams.get("n_ambient", medium.n_ambient))
    fg = FlowGrid(cameras[0].image_size, factor)
    stats = {c: [] for c in range(len(cameras))}
    parts = []
    for c, cam in enumerate(cameras):  # one camera's geometry at a time bounds the memory
        geom = build_geometry([cam], grid, fg, params=tomo)
        for f, g in grads.items():
            meas = rd.camera_frame("flow", c, f)
            if meas is None:
                continue
            pred = predict_flows(geom, [cam], g, n_ambient=n_amb)[0]
            mask = rd.camera_frame("mask", c, f)
            mask = None if mask is None else mask.astype(bool)
            stats[c].append(residual_stats(meas, pred, mask))
            if f == shown and (max_cameras is None or c < max_cameras):
                fig = viz.residual_figure(meas, pred, mask=mask, title=f"camera {cam.name}, frame {rd.capture_index(f)}")
                rel = _figure(writer, f"residual_{safe_name(cam.name)}.png", fig)
                parts.append(html_img(rel, f"residual of camera {cam.name}"))
        del geom
    table = []
    used = [rd.capture_index(f) for f in sorted(grads)]
    for c, cam in enumerate(cameras):
        n = np.array([s.count for s in stats[c]], dtype=np.float64)

        def pooled(vals):
            v = np.array(vals, dtype=np.float64)
            ok = np.isfinite(v) & (n > 0)
            return float(np.sqrt(np.sum(n[ok] * v[ok] ** 2) / np.sum(n[ok]))) if ok.any() else float("nan")

        rms = pooled([s.rms for s in stats[c]])
        rms_m = pooled([s.rms_measured for s in stats[c]])
        rms_in = pooled([s.rms_in_mask for s in stats[c]])
        table.append([cam.name, fmt_number(rms), fmt_number(rms_in), fmt_number(rms_m),
                      fmt_number(rms / rms_m if rms_m > 0 else float("nan"), 3)])
        page.summary.setdefault("residual_rms_px", {})[cam.name] = {
            "rms": _finite(rms), "rms_in_mask": _finite(rms_in), "rms_measured": _finite(rms_m),
            "frames": used}
    body = ("<p>Each camera's measured deflections against those predicted by pushing the reconstructed "
            "gradient (" + html.escape(" / ".join(sorted(sources))) + ") back through the tomography's own "
            "geometry and projection matrix (<code>pipeline.tomography.build_geometry</code>; straight rays, "
            "paper sec. 5). RMS of the residual vector length in image pixels over "
            f"{len(used)} frame(s) ({', '.join(map(str, used))}).</p>"
            + html_table(["camera", "RMS residual (px)", "RMS residual in mask (px)", "RMS measured (px)",
                          "relative (1)"], table, "num")
            + "\n".join(parts))
    page.add(title, body, "residuals")


def _parse_time(s):
    """A stage time stamp: epoch seconds (number) or ISO 8601 text -> aware datetime (UTC)."""
    import datetime as _dt

    if isinstance(s, (int, float)) and not isinstance(s, bool) and math.isfinite(s):
        return _dt.datetime.fromtimestamp(float(s), tz=_dt.timezone.utc)
    if not isinstance(s, str) or not s:
        return None
    try:
        t = _dt.datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        return None
    return t if t.tzinfo else t.replace(tzinfo=_dt.timezone.utc)


def _show_time(t) -> str:
    return "" if t is None else t.strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _stage_rows(stage_times) -> list[tuple[str, dict]]:
    """Stage -> {started, completed (epoch s or ISO), seconds | task_seconds, executor}, by start."""
    if not isinstance(stage_times, dict):
        return []
    items = [(k, v if isinstance(v, dict) else {"seconds": v}) for k, v in stage_times.items()]

    def key(kv):
        t = _parse_time(kv[1].get("started"))
        return (t is None, t.timestamp() if t else 0.0, kv[0])

    return sorted(items, key=key)


def _timings_section(page: ReportPage, attrs: dict, writer: ReportWriter):
    rows = _stage_rows(attrs.get("stage_times"))
    if not rows:
        page.add("Per-stage timings", "<p class='missing'>No <code>stage_times</code> in the store.</p>",
                 "timings")
        return
    bars, table, starts, ends, task_total = {}, [], [], [], 0.0
    for name, v in rows:
        t0, t1 = _parse_time(v.get("started")), _parse_time(v.get("completed"))
        wall = (t1 - t0).total_seconds() if t0 and t1 else v.get("seconds")
        task = v.get("task_seconds")
        if t0:
            starts.append(t0)
        if t1:
            ends.append(t1)
        try:
            if task is not None and math.isfinite(float(task)):
                task_total += float(task)
            if wall is not None and math.isfinite(float(wall)):
                bars[name] = float(wall)
        except (TypeError, ValueError):
            pass
        table.append([name, _show_time(t0) or v.get("started", ""), _show_time(t1) or v.get("completed", ""),
                      fmt_number(wall), fmt_number(task), v.get("executor", "")])
    total_wall = (max(ends) - min(starts)).total_seconds() if starts and ends else sum(bars.values())
    table.append(["run (first start to last completion)", "", "", fmt_number(total_wall), fmt_number(task_total),
                  ""])
    page.summary["stage_seconds"] = bars
    body = html_table(["stage", "started", "completed", "wall-clock (s)", "task time (s)", "executor"], table,
                      "num")
    body += ("<p>Wall-clock: completion minus start of each stage (stages overlap when the executor "
             "pipelines them); task time: the sum of the stage's task durations.</p>")
    if bars:
        rel = _figure(writer, "timings.png", viz.timings_figure(bars))
        body += html_img(rel, "per-stage timings")
    page.add("Per-stage timings", body, "timings")
