"""The HTML report of a result store: figures (PNG), an animation (GIF) and ``index.html``.

Reads the store with zarr directly (read-only) and tolerates a partial run: every figure
is made from what exists, and the page lists what is missing. The pictures come from
:mod:`schlieren.pipeline.viz`; this module only reads arrays and writes files.

Layout of the output folder::

    index.html
    figures/deflection_<camera>.png     paper Figure 4 for the shown frame
    figures/hull.png                    visual hull
    figures/slices_<quantity>.png       refractivity / temperature / density / |grad n|
    figures/render.png                  volume rendering of the shown frame, with colour bar
    figures/render_views.png            the same frame from four sides
    figures/render_strip.png            a row of frames (paper Figure 8)
    figures/render_<frame>.png          one rendering per frame
    figures/render.gif                  the renderings as an animation
    figures/residual_<camera>.png       measured vs re-projected deflections
    figures/timings.png                 per-stage wall-clock times
    summary.json                        the numbers on the page (residual RMS, what is missing)
"""

from __future__ import annotations

import html
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schlieren.pipeline import viz
from schlieren.pipeline.geometry import Camera, FlowGrid, Grid, Medium, rodrigues
from schlieren.storage.errors import SchlierenInputError, StoreError
from schlieren.storage.layout import STORE_FORMAT

__all__ = ["write_report", "open_result", "volume_grid", "cameras_from_session", "medium_from_session",
           "frame_range", "STORE_FORMAT"]

log = logging.getLogger(__name__)

EXPECTED_ARRAYS = ("time", "flow", "mask", "potential", "hull", "gradient", "refractivity", "density",
                   "temperature")
VOLUME_ARRAYS = ("hull", "gradient", "refractivity", "density", "temperature")
MAX_RESIDUAL_FRAMES = 8
STRIP_FRAMES = 6


# ---------------------------------------------------------------------------------------
# Reading the store
# ---------------------------------------------------------------------------------------

def open_result(store_path: str | os.PathLike):
    """Open a result store read-only.

    Raises
    ------
    StoreError
        The path does not exist, is not a Zarr group, or has another ``format``.
    """
    import zarr

    path = Path(store_path)
    if not path.exists():
        raise StoreError("result store not found", file=str(path))
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for "not a group"
        raise StoreError(f"not a Zarr group ({type(exc).__name__}: {exc})", file=str(path)) from None
    fmt = group.attrs.get("format")
    if fmt is not None and fmt != STORE_FORMAT:
        raise StoreError(f"unknown store format {fmt!r} (expected {STORE_FORMAT})", file=str(path),
                         field="format")
    return group


def volume_grid(array) -> Grid:
    """The :class:`Grid` of a volume array from its ``origin`` / ``voxel_size`` attributes.

    Parameters
    ----------
    array : zarr.Array
        Dims ``(frame, z, y, x[, component])``.

    Raises
    ------
    StoreError
        Missing or inconsistent attributes, or anisotropic voxels (``Grid`` is isotropic).
    """
    attrs = dict(array.attrs)
    name = array.basename if hasattr(array, "basename") else str(array)
    try:
        origin = np.asarray(attrs["origin"], dtype=np.float64).reshape(3)
        vs = np.asarray(attrs["voxel_size"], dtype=np.float64).ravel()
    except (KeyError, ValueError, TypeError):
        raise StoreError("volume array lacks origin (x, y, z) / voxel_size attributes",
                         field=f"{name}.attrs") from None
    if vs.size == 1:
        vs = np.repeat(vs, 3)
    if vs.size != 3 or np.any(vs <= 0):
        raise StoreError(f"voxel_size must be 3 positive numbers, got {vs.tolist()}", field=f"{name}.attrs")
    if not np.allclose(vs, vs[0], rtol=1e-9):
        raise StoreError(f"anisotropic voxels {vs.tolist()} are not supported", field=f"{name}.attrs")
    nz, ny, nx = (int(v) for v in array.shape[1:4])
    h = float(vs[0])
    vmin = origin - 0.5 * h
    vmax = vmin + h * np.array([nx, ny, nz], dtype=np.float64)
    grid = Grid(tuple(vmin), tuple(vmax), h)
    if grid.shape != (nz, ny, nx):  # round-off in (vmax - vmin) / h
        raise StoreError(f"grid from attributes has shape {grid.shape}, array has {(nz, ny, nx)}",
                         field=f"{name}.attrs")
    return grid


def frame_range(frames, n_frames: int) -> range:
    """Validated half-open frame range ``[a, b)`` within ``0 .. n_frames``.

    Parameters
    ----------
    frames : None, (a, b) or range
        ``None`` = every frame; ``b`` may be None (to the end) and is clipped to ``n_frames``.
    """
    if frames is None:
        return range(n_frames)
    if isinstance(frames, range):
        a, b = frames.start, frames.stop
    else:
        a, b = frames
    a = 0 if a is None else int(a)
    want = f"{a}:{'' if b is None else int(b)}"
    b = n_frames if b is None else min(int(b), n_frames)
    if a < 0 or a >= b:
        raise StoreError(f"frame range {want} is empty or outside the store's frames 0:{n_frames}",
                         field="frames")
    return range(a, b)


def _get(d: dict, key: str, default=None):
    return d.get(key, default) if isinstance(d, dict) else default


def medium_from_session(session: dict | None) -> Medium:
    """The session's ``medium`` block (SPEC defaults for what is missing)."""
    m = _get(session, "medium") or {}
    base = Medium()
    kw = {}
    for k in ("n_ambient", "T_ambient", "p_ambient", "gladstone_dale"):
        if k in m and m[k] is not None:
            kw[k] = float(m[k])
    return Medium(**{**base.__dict__, **kw})


def cameras_from_session(session: dict, time_offsets=None) -> list[Camera]:
    """Cameras of a stored session manifest (SPEC section 1 fields).

    Parameters
    ----------
    session : dict
        The manifest as stored in the root attribute ``session``.
    time_offsets : sequence of float, optional
        Per-camera session-clock offsets (the store's ``time_offset``).

    Raises
    ------
    StoreError
        A camera entry lacks a field the geometry needs (named as ``cameras[i].field``).
    """
    cams = _get(session, "cameras")
    if not isinstance(cams, list) or not cams:
        raise StoreError("the stored session has no cameras", field="session.cameras")
    out = []
    for i, c in enumerate(cams):
        name = str(c.get("name", f"cam{i:02d}"))
        where = f"session.cameras[{i}]"
        try:
            K = np.asarray(c["K"], dtype=np.float64)
            dist = np.asarray(c.get("dist") or [0.0] * 5, dtype=np.float64)
            if c.get("R") is not None:
                R = np.asarray(c["R"], dtype=np.float64)
            elif c.get("rvec") is not None:
                R = rodrigues(c["rvec"])
            else:
                raise KeyError("R")
            t = np.asarray(c["t"], dtype=np.float64)
            size = tuple(int(v) for v in c["image_size"])
            bg = c.get("background") or {}
            if bg.get("point") is not None and bg.get("normal") is not None:
                point, normal = bg["point"], bg["normal"]
            elif bg.get("distance") is not None:
                point, normal = Camera.background_from_distance(R, t, float(bg["distance"]))
            else:
                raise KeyError("background")
            rs = c.get("rolling_shutter") or {}
            line_time = float(rs.get("line_time", 0.0) or 0.0)
        except KeyError as exc:
            raise StoreError("camera entry lacks a field", camera=name, field=f"{where}.{exc.args[0]}") from None
        except (TypeError, ValueError) as exc:
            raise StoreError(f"malformed camera entry ({exc})", camera=name, field=where) from None
        offset = c.get("time_offset")
        if time_offsets is not None and i < len(time_offsets) and np.isfinite(time_offsets[i]):
            offset = float(time_offsets[i])
        out.append(Camera(name, K, dist, R, t, size, point, normal, line_time,
                          None if offset is None else float(offset)))
    return out


def _session_root(attrs: dict) -> Path | None:
    p = attrs.get("session_path")
    if not p:
        return None
    p = Path(p)
    return p.parent if p.suffix.lower() in (".yaml", ".yml", ".json") or p.is_file() else p


def _first_session_frame(attrs: dict) -> int:
    for src in (attrs, _get(attrs, "params") or {}, _get(attrs, "session") or {}):
        fr = _get(src, "frames")
        if isinstance(fr, (list, tuple)) and fr and fr[0] is not None:
            try:
                return int(fr[0])
            except (TypeError, ValueError):
                continue
    return 0


def _read_camera_frame(attrs: dict, cam_index: int, capture_index: int) -> tuple[np.ndarray | None, str]:
    """Input frame ``capture_index`` of a camera (from the session folder), or None and why not."""
    from schlieren.storage.frames import open_frames

    root = _session_root(attrs)
    cams = _get(_get(attrs, "session") or {}, "cameras") or []
    if root is None or cam_index >= len(cams) or not cams[cam_index].get("frames"):
        return None, "the store does not name the session's frames"
    spec = root / str(cams[cam_index]["frames"])
    try:
        src = open_frames(spec, camera_name=cams[cam_index].get("name"))
        idx = min(max(capture_index, 0), len(src) - 1)
        return src.read(idx), f"{spec.name}, capture frame {idx}"
    except (SchlierenInputError, OSError, ValueError) as exc:
        return None, f"camera frame not readable: {exc}"


# ---------------------------------------------------------------------------------------
# Writing the report
# ---------------------------------------------------------------------------------------

@dataclass
class _Page:
    title: str
    sections: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    anchors: list[tuple[str, str]] = field(default_factory=list)

    def add(self, heading: str, body: str, anchor: str):
        self.anchors.append((anchor, heading.split(" (")[0]))
        self.sections.append(f'<section id="{anchor}"><h2>{html.escape(heading)}</h2>\n{body}\n</section>')


def _img(rel: str, alt: str, caption: str | None = None) -> str:
    cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
    return (f'<figure><a href="{html.escape(rel)}"><img src="{html.escape(rel)}" '
            f'alt="{html.escape(alt)}"></a>{cap}</figure>')


def _table(header: list[str], rows: list[list], cls: str = "") -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    head = f"<thead><tr>{h}</tr></thead>" if any(header) else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}">{head}<tbody>{body}</tbody></table>'


def _fmt(x, digits=4) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(x):
        return "n/a"
    return f"{x:.{digits}g}"


def _save(fig, path: Path, dpi: int = 100) -> None:
    fig.savefig(path, dpi=dpi)
    fig.clear()


def _stage_rows(stage_times) -> list[tuple[str, dict]]:
    """Stage -> {started, completed (epoch s or ISO), seconds | task_seconds, executor}, by start."""
    if not isinstance(stage_times, dict):
        return []
    items = [(k, v if isinstance(v, dict) else {"seconds": v}) for k, v in stage_times.items()]

    def key(kv):
        t = _parse_time(kv[1].get("started"))
        return (t is None, t.timestamp() if t else 0.0, kv[0])

    return sorted(items, key=key)


class _Reader:
    """What the report reads from a store, tolerant of missing arrays and unfinished chunks.

    Completion comes from the ``status/<stage>`` markers when the store has them; a frame
    that is marked incomplete, or whose values are all NaN (the arrays' fill value), counts
    as missing.
    """

    STAGE_OF = {"flow": "resample", "mask": "mask", "potential": "potential", "hull": "hull",
                "gradient": "tomography", "refractivity": "integrate", "density": "integrate",
                "temperature": "integrate"}

    def __init__(self, group):
        self.group = group
        self.attrs = dict(group.attrs)
        self.arrays = {k: group[k] for k in EXPECTED_ARRAYS if k in group}
        self._done: dict[str, np.ndarray | None] = {}

    def marker(self, stage: str) -> np.ndarray | None:
        """The completion marker of ``stage`` as bool, or None if the store has none."""
        if stage not in self._done:
            try:
                self._done[stage] = np.asarray(self.group[f"status/{stage}"][...]) == 1
            except KeyError:
                self._done[stage] = None
        return self._done[stage]

    def frame_done(self, name: str, n_frames: int) -> np.ndarray:
        """Per store frame: is ``name`` complete (for every camera)? Unknown -> True."""
        if name not in self.arrays:
            return np.zeros(n_frames, bool)
        m = self.marker(self.STAGE_OF.get(name, ""))
        if m is None:
            return np.ones(n_frames, bool)
        if m.ndim == 2:  # (camera, frame)
            m = m.all(axis=0)
        return m.reshape(-1)[:n_frames] if m.size >= n_frames else np.ones(n_frames, bool)

    def volume(self, name: str, f: int) -> np.ndarray | None:
        """Frame ``f`` of a volume array, or None if missing, unfinished or all NaN."""
        if name not in self.arrays:
            return None
        m = self.marker(self.STAGE_OF.get(name, ""))
        if m is not None and m.ndim == 1 and f < m.size and not m[f]:
            return None
        v = np.asarray(self.arrays[name][f])
        if v.dtype.kind == "f":
            if not np.isfinite(v).any():
                return None
            v = v.astype(np.float64)
        return v

    def camera_frame(self, name: str, c: int, f: int) -> np.ndarray | None:
        """``name[c, f]`` of a per-camera array, or None if missing or unfinished."""
        if name not in self.arrays:
            return None
        m = self.marker(self.STAGE_OF.get(name, ""))
        if m is not None and m.ndim == 2 and c < m.shape[0] and f < m.shape[1] and not m[c, f]:
            return None
        v = np.asarray(self.arrays[name][c, f])
        if v.dtype.kind == "f":
            if not np.isfinite(v).any():
                return None
            v = v.astype(np.float64)
        return v

    def capture_index(self, f: int) -> int:
        """Capture frame index of store frame ``f`` (the ``frame`` coordinate)."""
        if "frame" in self.group:
            try:
                return int(np.asarray(self.group["frame"][f]))
            except (IndexError, ValueError, TypeError):
                pass
        run = _get(self.attrs, "run") or {}
        fr = _get(run, "frames")
        if isinstance(fr, (list, tuple)) and fr:
            return int(fr[0]) + f
        return _first_session_frame(self.attrs) + f


def write_report(store_path: str | os.PathLike, out_dir: str | os.PathLike, *, frames=None,
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
        Half-open range of store frames to show (default: all). The single-frame figures
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
    """
    rd = _Reader(open_result(store_path))
    attrs, arrays = rd.attrs, rd.arrays
    out = Path(out_dir)
    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    for old in list(figdir.glob("*.png")) + list(figdir.glob("*.gif")):  # an earlier report's figures
        old.unlink()
    session = _get(attrs, "session") or {}
    name = str(attrs.get("session_name") or _get(session, "name") or Path(store_path).name)
    page = _Page(title=f"schlieren report: {name}")
    page.missing = [k for k in EXPECTED_ARRAYS if k not in arrays]
    for key in ("format", "session", "params", "version", "stage_times"):
        if key not in attrs:
            page.missing.append(f"attribute {key}")

    n_frames = _frame_count(arrays)
    sel = frame_range(frames, n_frames) if n_frames else range(0)
    shown = _pick_shown(rd, sel, n_frames)
    times = None
    if "time" in arrays:
        times = np.asarray(arrays["time"][:], dtype=np.float64)
        if not np.isfinite(times).any():
            times = None
    medium = medium_from_session(session)
    params = _get(attrs, "params") or {}
    grid = None
    for k in VOLUME_ARRAYS:
        if k in arrays:
            grid = volume_grid(arrays[k])
            break
    cameras, cam_note = None, ""
    if session:
        try:
            offs = np.asarray(rd.group["time_offset"][:]) if "time_offset" in rd.group else None
            cameras = cameras_from_session(session, offs)
        except StoreError as exc:
            cam_note = str(exc)

    page.add("Summary", _summary_html(rd, store_path, name, grid, cameras, n_frames, sel, shown, times, medium),
             "summary")
    if evaluation:
        _accuracy_section(page, evaluation)
    _completion_section(page, rd)
    _deflection_section(page, rd, figdir, shown, cameras, max_cameras)
    if grid is not None:
        _hull_section(page, rd, grid, figdir, shown)
        _slices_section(page, rd, grid, figdir, shown, times)
        _render_section(page, rd, grid, figdir, sel, shown, times, medium.refractivity_ambient, render_size)
    _residual_section(page, rd, grid, cameras, cam_note, figdir, sel, shown, medium, max_cameras, params)
    _timings_section(page, attrs, figdir)
    if params:
        page.add("Parameters", f"<pre>{html.escape(json.dumps(params, indent=2, default=str))}</pre>", "params")
    index = out / "index.html"
    index.write_text(_page_html(page), encoding="utf-8")
    page.summary.update({"session": name, "frames": [sel.start, sel.stop] if len(sel) else [],
                         "shown_frame": shown, "missing": page.missing,
                         "figures": sorted(str(p.relative_to(out)) for p in figdir.iterdir())})
    (out / "summary.json").write_text(json.dumps(page.summary, indent=2, default=_json_default),
                                      encoding="utf-8")
    log.info("report written to %s", index)
    return index


def _pick_shown(rd: _Reader, sel: range, n_frames: int) -> int | None:
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


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return None if not np.isfinite(o) else float(o)
    return str(o)


def _frame_count(arrays: dict) -> int:
    if "time" in arrays:
        return int(arrays["time"].shape[0])
    for k in VOLUME_ARRAYS:
        if k in arrays:
            return int(arrays[k].shape[0])
    for k in ("flow", "mask", "potential"):
        if k in arrays:
            return int(arrays[k].shape[1])
    return 0


def _summary_html(rd, store_path, name, grid, cameras, n_frames, sel, shown, times, medium) -> str:
    attrs = rd.attrs
    session = _get(attrs, "session") or {}
    when = "none" if shown is None else f"store frame {shown} (capture frame {rd.capture_index(shown)}" + (
        f", t = {_fmt(times[shown], 6)} s)" if times is not None and np.isfinite(times[shown]) else ")")
    rows = [["session", name], ["store", str(Path(store_path).resolve())],
            ["format", attrs.get("format", "missing")], ["software version", attrs.get("version", "missing")],
            ["frames in store", n_frames],
            ["frames shown", f"{sel.start}:{sel.stop}" if len(sel) else "none"],
            ["single-frame figures", when]]
    if _get(session, "frame_rate") is not None:
        rows.append(["frame rate", f"{_fmt(session['frame_rate'])} 1/s"])
    if cameras:
        rows.append(["cameras", ", ".join(c.name for c in cameras)])
    if grid is not None:
        nz, ny, nx = grid.shape
        rows.append(["volume grid (x, y, z)", f"{nx} x {ny} x {nz} voxels of {grid.voxel_size * 1e3:.3g} mm"])
        rows.append(["box (m)", f"x {grid.vmin[0]:.4g}..{grid.vmax[0]:.4g}, y {grid.vmin[1]:.4g}.."
                                f"{grid.vmax[1]:.4g}, z {grid.vmin[2]:.4g}..{grid.vmax[2]:.4g}"])
    rows.append(["ambient medium", f"n = {medium.n_ambient:.6f}, T = {medium.T_ambient:.2f} K, "
                                   f"p = {medium.p_ambient:.0f} Pa, G = {medium.gladstone_dale:.3g} m^3/kg"])
    return _table(["", ""], rows, "kv")


def _accuracy_section(page, evaluation: dict):
    """SPEC section 4: relative RMS of the refractivity against ground truth, and PSNR."""
    rows = []
    for r in evaluation.get("frames") or []:
        rms = r.get("rms")
        rows.append([r.get("frame", ""), _fmt(r.get("time"), 6),
                     _fmt(100.0 * rms if rms is not None else None), _fmt(r.get("psnr")), r.get("truth_from", "")])
    ov = evaluation.get("overall") or {}
    if ov:
        rms = ov.get("rms")
        rows.append(["overall", "", _fmt(100.0 * rms if rms is not None else None), _fmt(ov.get("psnr")), ""])
        page.summary["accuracy"] = {k: (_finite(v) if isinstance(v, (int, float)) else v) for k, v in ov.items()}
    body = ("<p>Refractivity against the ground truth: RMS error relative to the truth's range per frame, and "
            "PSNR = 20 log10(1 / RMS) (paper Table 1).</p>"
            + _table(["frame", "time (s)", "relative RMS (%)", "PSNR (dB)", "truth"], rows, "num"))
    if evaluation.get("truth"):
        body += f"<p>Truth: <code>{html.escape(str(evaluation['truth']))}</code></p>"
    page.add("Accuracy", body, "accuracy")


def _completion_section(page, rd: _Reader):
    try:
        status = rd.group["status"]
    except KeyError:
        return
    rows = []
    for stage, arr in sorted(status.arrays(), key=lambda kv: kv[0]):
        done = np.asarray(arr[...]) == 1
        total = int(done.size)
        n = int(done.sum())
        rows.append([stage, f"{n} of {total}", "complete" if n == total else ("not started" if n == 0 else "partial")])
    if rows:
        page.add("Completion", "<p>Completion markers (<code>status/&lt;stage&gt;</code>), per camera-frame "
                               "or frame.</p>" + _table(["stage", "done", "state"], rows, "num"), "completion")
        page.summary["completion"] = {r[0]: r[1] for r in rows}


def _deflection_section(page, rd: _Reader, figdir, shown, cameras, max_cameras):
    title = "Deflections (paper Figure 4)"
    if "flow" not in rd.arrays or shown is None:
        page.add(title, "<p class='missing'>No <code>flow</code> in the store.</p>", "deflections")
        return
    n_cam = rd.arrays["flow"].shape[0]
    names = _camera_names(rd, cameras, n_cam)
    threshold = None
    if "mask_threshold" in rd.group:
        thr = np.asarray(rd.group["mask_threshold"][...], dtype=np.float64).ravel()
        threshold = float(thr[0]) if thr.size and np.isfinite(thr[0]) else None
    units = rd.arrays["potential"].attrs.get("units", "px$^2$") if "potential" in rd.arrays else "px$^2$"
    parts = []
    for c in range(n_cam if max_cameras is None else min(n_cam, max_cameras)):
        flow = rd.camera_frame("flow", c, shown)
        if flow is None:
            parts.append(f"<p class='missing'>Camera {html.escape(names[c])}: flow of store frame {shown} "
                         "not computed yet.</p>")
            continue
        mask = rd.camera_frame("mask", c, shown)
        pot = rd.camera_frame("potential", c, shown)
        image, source = _read_camera_frame(rd.attrs, c, rd.capture_index(shown))
        fig = viz.deflection_figure(image, flow, mask=None if mask is None else mask.astype(bool), potential=pot,
                                    threshold=threshold, step=max(1, flow.shape[1] // 16),
                                    potential_units=str(units), title=f"camera {names[c]}, store frame {shown}")
        rel = f"figures/deflection_{_safe(names[c])}.png"
        _save(fig, figdir.parent / rel)
        parts.append(_img(rel, f"deflections of camera {names[c]}",
                          f"Camera {names[c]} ({source}). Top: camera frame, deflection colour coding "
                          "(hue = direction, saturation = magnitude in pixels; key in the corner), quiver "
                          "plot. Bottom: Poisson-integrated deflections, threshold (or the deflection "
                          "magnitude when the store has no threshold), mask."))
    page.add(title, "\n".join(parts), "deflections")


def _camera_names(rd: _Reader, cameras, n) -> list[str]:
    if cameras and len(cameras) == n:
        return [c.name for c in cameras]
    cams = _get(_get(rd.attrs, "session") or {}, "cameras") or []
    names = [str(c.get("name", f"cam{i:02d}")) for i, c in enumerate(cams)]
    return names if len(names) == n else [f"cam{i:02d}" for i in range(n)]


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def _hull_section(page, rd: _Reader, grid, figdir, shown):
    hull = rd.volume("hull", shown) if shown is not None else None
    if hull is None:
        page.add("Visual hull", "<p class='missing'>No visual hull for this frame in the store.</p>", "hull")
        return
    fig = viz.hull_figure(hull.astype(bool), grid, title=f"visual hull, store frame {shown}")
    _save(fig, figdir / "hull.png")
    page.add("Visual hull", _img("figures/hull.png", "visual hull",
                                 "The conservative visual hull: a rendering and the fraction of hull voxels "
                                 "along each world axis."), "hull")


def _slices_section(page, rd: _Reader, grid, figdir, shown, times):
    if shown is None:
        return
    parts = []
    index = None
    r = rd.volume("refractivity", shown)
    if r is not None:
        index = np.unravel_index(np.nanargmin(r), r.shape)  # the hottest voxel
    tstamp = f", t = {_fmt(times[shown], 6)} s" if times is not None and np.isfinite(times[shown]) else ""
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
                                     title=f"{label}, store frame {shown}{tstamp}")
        rel = f"figures/slices_{key}.png"
        _save(fig, figdir.parent / rel)
        parts.append(_img(rel, f"slices of {key}"))
    g = rd.volume("gradient", shown)
    if g is not None:
        mag = np.sqrt(np.sum(g ** 2, axis=-1))
        fig = viz.orthoslices_figure(mag, grid, index=index, label="|grad n|", units="1/m", cmap="magma",
                                     vectors=g, title=f"reconstructed gradient (arrows: in-plane components), "
                                                      f"store frame {shown}{tstamp}")
        _save(fig, figdir / "slices_gradient.png")
        parts.append(_img("figures/slices_gradient.png", "slices of the gradient magnitude"))
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


def _render_section(page, rd: _Reader, grid, figdir, sel, shown, times, r_amb, render_size):
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
    import imageio.v3 as iio

    scale = deficit if deficit > 0 else 1e-6
    tf = viz.TransferFunction(r_ambient=r_amb, scale=scale)

    def volume(f):
        return np.nan_to_num(rd.volume("refractivity", f), nan=r_amb)

    frames_rgb = {}  # RGB renderings are small; the volumes are not kept
    for f in available:
        t = times[f] if times is not None and np.isfinite(times[f]) else None
        img = viz.animation_frames([volume(f)], grid, r_ambient=r_amb, transfer=tf, image_size=render_size,
                                   times=None if t is None else [t])[0]
        iio.imwrite(figdir / f"render_{f:05d}.png", img)
        frames_rgb[f] = img
    done = list(frames_rgb)
    key = shown if shown in frames_rgb else done[len(done) // 2]
    _save(viz.render_figure(frames_rgb[key], tf, title=f"store frame {key}"), figdir / "render.png")
    # the shown frame from four sides (azimuth 30, 120, 210, 300 degrees)
    size = render_size or viz.fit_image_size(grid, azimuth_deg=30.0, elevation_deg=15.0, long_side=360)
    vol = volume(key)
    views = [viz.render_volume(vol, grid, azimuth_deg=az, elevation_deg=15.0, transfer=tf,
                               image_size=size) for az in (30.0, 120.0, 210.0, 300.0)]
    iio.imwrite(figdir / "render_views.png", _side_by_side(views))
    # a row of frames as in the paper's Figure 8
    pick = [done[i] for i in np.unique(np.linspace(0, len(done) - 1, min(STRIP_FRAMES, len(done))).round()
                                       .astype(int))]
    iio.imwrite(figdir / "render_strip.png", _side_by_side([frames_rgb[f] for f in pick]))
    fps = 10.0
    iio.imwrite(figdir / "render.gif", np.stack([frames_rgb[f] for f in done]), duration=int(1000 / fps), loop=0)
    links = " ".join(f'<a href="figures/render_{f:05d}.png">{f}</a>' for f in done)
    skipped = [f for f in sel if f not in frames_rgb]
    body = (
        "<p>Emission-absorption ray marching of the refractivity (paper Figures 1 and 8): hot, "
        "less dense gas (refractivity below ambient) glows; one transfer function for all frames, "
        f"full signal at a deficit of {scale:.3g}.</p>"
        + _img("figures/render.png", "volume rendering", f"Store frame {key}.")
        + _img("figures/render_views.png", "four views",
               f"Store frame {key} seen from azimuth 30, 120, 210 and 300 degrees (elevation 15).")
        + _img("figures/render_strip.png", "rendering over time",
               "Frames " + ", ".join(map(str, pick)) + ", left to right.")
        + _img("figures/render.gif", "animation", f"Animation of {len(done)} frame(s) ({fps:g} per second).")
        + f"<p>Per-frame renderings: {links}</p>"
        + (f"<p class='missing'>Not reconstructed yet: frames {', '.join(map(str, skipped))}.</p>"
           if skipped else ""))
    page.add("Volume rendering", body, "render")


def _residual_section(page, rd: _Reader, grid, cameras, cam_note, figdir, sel, shown, medium, max_cameras,
                      params):
    title = "Re-projection residuals"
    arrays = rd.arrays
    if "flow" not in arrays or grid is None or shown is None or not (
            "gradient" in arrays or "refractivity" in arrays):
        page.add(title, "<p class='missing'>Needs <code>flow</code> and a reconstructed <code>gradient</code> "
                        "(or <code>refractivity</code>) in the store.</p>", "residuals")
        return
    if not cameras:
        page.add(title, f"<p class='missing'>No usable camera calibration in the store"
                        f"{': ' + html.escape(cam_note) if cam_note else ''}.</p>", "residuals")
        return
    from schlieren.pipeline.residuals import predict_flows, residual_stats
    from schlieren.pipeline.tomography import TomoParams, build_geometry

    flow_a = arrays["flow"]
    if flow_a.shape[0] != len(cameras):
        page.add(title, f"<p class='missing'>The store has flow for {flow_a.shape[0]} cameras but "
                        f"{len(cameras)} calibrations.</p>", "residuals")
        return
    rows_f, cols_f = flow_a.shape[2:4]
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
                fig = viz.residual_figure(meas, pred, mask=mask, title=f"camera {cam.name}, store frame {f}")
                rel = f"figures/residual_{_safe(cam.name)}.png"
                _save(fig, figdir.parent / rel)
                parts.append(_img(rel, f"residual of camera {cam.name}"))
        del geom
    table = []
    used = sorted(grads)
    for c, cam in enumerate(cameras):
        n = np.array([s.count for s in stats[c]], dtype=np.float64)

        def pooled(vals):
            v = np.array(vals, dtype=np.float64)
            ok = np.isfinite(v) & (n > 0)
            return float(np.sqrt(np.sum(n[ok] * v[ok] ** 2) / np.sum(n[ok]))) if ok.any() else float("nan")

        rms = pooled([s.rms for s in stats[c]])
        rms_m = pooled([s.rms_measured for s in stats[c]])
        rms_in = pooled([s.rms_in_mask for s in stats[c]])
        table.append([cam.name, _fmt(rms), _fmt(rms_in), _fmt(rms_m),
                      _fmt(rms / rms_m if rms_m > 0 else float("nan"), 3)])
        page.summary.setdefault("residual_rms_px", {})[cam.name] = {
            "rms": _finite(rms), "rms_in_mask": _finite(rms_in), "rms_measured": _finite(rms_m),
            "frames": used}
    body = ("<p>Each camera's measured deflections against those predicted by pushing the reconstructed "
            "gradient (" + html.escape(" / ".join(sorted(sources))) + ") back through the tomography's own "
            "geometry and projection matrix (<code>pipeline.tomography.build_geometry</code>; straight rays, "
            "paper sec. 5). RMS of the residual vector length in image pixels over "
            f"{len(used)} frame(s) ({', '.join(map(str, used))}).</p>"
            + _table(["camera", "RMS residual (px)", "RMS residual in mask (px)", "RMS measured (px)",
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


def _timings_section(page, attrs, figdir):
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
                      _fmt(wall), _fmt(task), v.get("executor", "")])
    total_wall = (max(ends) - min(starts)).total_seconds() if starts and ends else sum(bars.values())
    table.append(["run (first start to last completion)", "", "", _fmt(total_wall), _fmt(task_total), ""])
    page.summary["stage_seconds"] = bars
    body = _table(["stage", "started", "completed", "wall-clock (s)", "task time (s)", "executor"], table, "num")
    body += ("<p>Wall-clock: completion minus start of each stage (stages overlap when the executor "
             "pipelines them); task time: the sum of the stage's task durations.</p>")
    if bars:
        _save(viz.timings_figure(bars), figdir / "timings.png")
        body += _img("figures/timings.png", "per-stage timings")
    page.add("Per-stage timings", body, "timings")


_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1400px; padding: 0 1.5em;
       color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.6em; }
nav a { margin-right: 1em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
table { border-collapse: collapse; margin: 0.8em 0; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
table.num td:not(:first-child) { text-align: right; font-variant-numeric: tabular-nums; }
.missing { color: #a33; } pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }
"""


def _page_html(page: _Page) -> str:
    missing = ""
    if page.missing:
        missing = ("<p class='missing'>Missing from the store (partial run?): "
                   + ", ".join(html.escape(m) for m in page.missing) + ".</p>")
    nav = " ".join(f'<a href="#{a}">{html.escape(t)}</a>' for a, t in page.anchors)
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<title>{html.escape(page.title)}</title><style>{_CSS}</style></head><body>\n"
        f"<h1>{html.escape(page.title)}</h1>\n<nav>{nav}</nav>\n{missing}\n"
        + "\n".join(page.sections) + "\n</body></html>\n")
