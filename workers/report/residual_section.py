"""The report's re-projection residuals: measured deflections against the reconstruction's.

Each camera's stored flow is compared with the deflections predicted by pushing the
reconstructed gradient back through the tomography's own geometry and projection matrix
(:func:`schlieren.pipeline.tomography.build_geometry`, straight rays, paper sec. 5;
:func:`schlieren.pipeline.residuals.predict_flows`). The steps: check that the store and
the calibration fit together (:func:`_flow_factor`), pick up to
:data:`MAX_RESIDUAL_FRAMES` frames and their gradients (:func:`_frame_gradients`),
re-project them camera by camera (:func:`_reproject`), pool the statistics per camera
(:func:`_pooled_table`).
"""

from __future__ import annotations

import html

import numpy as np

from schlieren.pipeline.geometry import FlowGrid, Grid, Medium
from schlieren.storage.report import ReportPage, ReportReader, ReportWriter, fmt_number, html_img, html_table, safe_name
from schlieren.workers.report._common import _figure, _finite, _get
from schlieren.workers.report.figures import residual_figure

MAX_RESIDUAL_FRAMES = 8

_TITLE = "Re-projection residuals"


def _residual_section(page: ReportPage, rd: ReportReader, grid: Grid | None, cameras, cam_note,
                      writer: ReportWriter, sel, shown, medium: Medium, max_cameras, params):
    factor = _flow_factor(page, rd, grid, cameras, cam_note, shown)
    if factor is None:
        return
    grads, sources = _frame_gradients(rd, grid, sel, shown, medium)
    if not grads:
        page.add(_TITLE, "<p class='missing'>No frame has both its flow and its reconstruction yet.</p>",
                 "residuals")
        return
    stats, parts = _reproject(rd, grid, cameras, grads, factor, writer, shown, medium, max_cameras, params)
    table, used = _pooled_table(page, rd, cameras, stats, grads)
    body = ("<p>Each camera's measured deflections against those predicted by pushing the reconstructed "
            "gradient (" + html.escape(" / ".join(sorted(sources))) + ") back through the tomography's own "
            "geometry and projection matrix (<code>pipeline.tomography.build_geometry</code>; straight rays, "
            "paper sec. 5). RMS of the residual vector length in image pixels over "
            f"{len(used)} frame(s) ({', '.join(map(str, used))}).</p>"
            + html_table(["camera", "RMS residual (px)", "RMS residual in mask (px)", "RMS measured (px)",
                          "relative (1)"], table, "num")
            + "\n".join(parts))
    page.add(_TITLE, body, "residuals")


def _flow_factor(page: ReportPage, rd: ReportReader, grid: Grid | None, cameras, cam_note, shown) -> int | None:
    """The flow grid's downsampling factor, or None (and the reason on the page) when the
    store and the calibration cannot give residuals."""
    title = _TITLE
    if not rd.has("flow") or grid is None or shown is None or not (rd.has("gradient") or rd.has("refractivity")):
        from schlieren.workers.report.sections import not_kept_note

        page.add(title, "<p class='missing'>Needs <code>flow</code> and a reconstructed <code>gradient</code> "
                        "(or <code>refractivity</code>) in the store."
                        + (" " + not_kept_note(rd, "flow") if not_kept_note(rd, "flow") else "") + "</p>", "residuals")
        return None
    if not cameras:
        page.add(title, f"<p class='missing'>No usable camera calibration in the store"
                        f"{': ' + html.escape(cam_note) if cam_note else ''}.</p>", "residuals")
        return None
    flow_shape = rd.shape("flow")
    if flow_shape[0] != len(cameras):
        page.add(title, f"<p class='missing'>The store has flow for {flow_shape[0]} cameras but "
                        f"{len(cameras)} calibrations.</p>", "residuals")
        return None
    rows_f, cols_f = flow_shape[2:4]
    sizes = {cam.image_size for cam in cameras}
    W, H = cameras[0].image_size
    factor = int(_get(_get(rd.attrs, "run") or {}, "flow_factor") or (W // cols_f if cols_f else 0))
    if len(sizes) != 1 or factor < 1 or H // factor != rows_f or W // factor != cols_f:
        page.add(title, f"<p class='missing'>The flow grid ({rows_f} x {cols_f}) does not match the cameras' "
                        f"image sizes ({', '.join(map(str, sorted(sizes)))}).</p>", "residuals")
        return None
    return factor


def _frame_gradients(rd: ReportReader, grid: Grid, sel, shown, medium: Medium) -> tuple[dict, set]:
    """Up to MAX_RESIDUAL_FRAMES frames with flow (evenly spread, plus the shown one): their
    reconstructed gradient by store index, and where the gradients come from."""

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
    return grads, sources


def _reproject(rd: ReportReader, grid: Grid, cameras, grads: dict, factor: int, writer: ReportWriter, shown,
               medium: Medium, max_cameras, params) -> tuple[dict, list]:
    """Residual statistics per camera and frame, and the shown frame's residual figures."""
    from schlieren.pipeline.residuals import predict_flows, residual_stats
    from schlieren.pipeline.tomography import TomoParams, build_geometry

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
                fig = residual_figure(meas, pred, mask=mask, title=f"camera {cam.name}, frame {rd.capture_index(f)}")
                rel = _figure(writer, f"residual_{safe_name(cam.name)}.png", fig)
                parts.append(html_img(rel, f"residual of camera {cam.name}"))
        del geom
    return stats, parts


def _pooled_table(page: ReportPage, rd: ReportReader, cameras, stats: dict, grads: dict) -> tuple[list, list]:
    """Per camera the RMS residuals pooled over the frames (weighted by pixel counts), as table
    rows and in the page summary; also the capture indices of the frames used."""
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
    return table, used
