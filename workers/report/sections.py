"""The figure sections of the report page: deflections (paper Figure 4), the visual hull,
volume slices, the volume rendering (paper Figures 1 and 8) and the per-stage timings.

Each ``_<name>_section(page, rd, ...)`` reads what it needs through
:class:`~schlieren.storage.report.ReportReader`, draws with
:mod:`~schlieren.workers.report.figures`, :mod:`~schlieren.workers.report.volume_figures`
and :mod:`~schlieren.workers.report.volume_render`, hands the pixels to the
:class:`~schlieren.storage.report.ReportWriter` and adds its HTML to the
:class:`~schlieren.storage.report.ReportPage`; what the store lacks is said on the page.
"""

from __future__ import annotations

import html
import math

import numpy as np

from schlieren.pipeline.geometry import Grid
from schlieren.storage.report import ReportPage, ReportReader, ReportWriter, fmt_number, html_img, html_table, safe_name
from schlieren.workers.report._common import _figure
from schlieren.workers.report.figures import deflection_figure, timings_figure
from schlieren.workers.report.volume_figures import hull_figure, orthoslices_figure, render_figure
from schlieren.workers.report.volume_render import (TransferFunction, animation_frames, fit_image_size,
                                                    render_volume)

STRIP_FRAMES = 6
ANIMATION_FPS = 10.0


def _camera_names(rd: ReportReader, cameras, n) -> list[str]:
    if cameras and len(cameras) == n:
        return [c.name for c in cameras]
    return rd.camera_names(n)


def not_kept_note(rd: ReportReader, name: str) -> str | None:
    """Why array ``name`` is absent when the run's retention dropped it, else None."""
    from schlieren.storage.integrity import dropped_of

    if name not in dropped_of(rd.attrs):
        return None
    keep = (rd.attrs.get("retention") or {}).get("keep", "")
    return (f"<code>{name}</code> was not kept: the run's <code>--keep {html.escape(str(keep))}</code> drops it "
            "once the stages reading it are done (a run with <code>--keep all</code> stores it again).")


def _deflection_section(page: ReportPage, rd: ReportReader, writer: ReportWriter, shown, cameras, max_cameras):
    title = "Deflections (paper Figure 4)"
    if not rd.has("flow") or shown is None:
        page.add(title, f"<p class='missing'>{not_kept_note(rd, 'flow') or 'No <code>flow</code> in the store.'}</p>",
                 "deflections")
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
        fig = deflection_figure(image, flow, mask=None if mask is None else mask.astype(bool), potential=pot,
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
    fig = hull_figure(hull.astype(bool), grid, title=f"visual hull, frame {rd.capture_index(shown)}")
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
        fig = orthoslices_figure(vol * factor, grid, index=index, label=label, units=units, cmap=cmap,
                                 title=f"{label}, frame {rd.capture_index(shown)}{tstamp}")
        rel = _figure(writer, f"slices_{key}.png", fig)
        parts.append(html_img(rel, f"slices of {key}"))
    g = rd.volume("gradient", shown)
    if g is not None:
        mag = np.sqrt(np.sum(g ** 2, axis=-1))
        fig = orthoslices_figure(mag, grid, index=index, label="|grad n|", units="1/m", cmap="magma",
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
    tf = TransferFunction(r_ambient=r_amb, scale=scale)

    def volume(f):
        return np.nan_to_num(rd.volume("refractivity", f), nan=r_amb)

    frames_rgb = {}  # RGB renderings are small; the volumes are not kept
    for f in available:
        t = times[f] if times is not None and np.isfinite(times[f]) else None
        img = animation_frames([volume(f)], grid, r_ambient=r_amb, transfer=tf, image_size=render_size,
                               times=None if t is None else [t])[0]
        writer.image(f"render_{rd.capture_index(f):05d}.png", img)
        frames_rgb[f] = img
    done = list(frames_rgb)
    key = shown if shown in frames_rgb else done[len(done) // 2]
    cap = rd.capture_index
    _figure(writer, "render.png", render_figure(frames_rgb[key], tf, title=f"frame {cap(key)}"))
    # the shown frame from four sides (azimuth 30, 120, 210, 300 degrees)
    size = render_size or fit_image_size(grid, azimuth_deg=30.0, elevation_deg=15.0, long_side=360)
    vol = volume(key)
    views = [render_volume(vol, grid, azimuth_deg=az, elevation_deg=15.0, transfer=tf,
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
        rel = _figure(writer, "timings.png", timings_figure(bars))
        body += html_img(rel, "per-stage timings")
    page.add("Per-stage timings", body, "timings")
