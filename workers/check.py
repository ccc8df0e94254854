"""``schlieren check``: a session's rig checked in seconds, before anyone reconstructs.

Loads the session's manifest (the calibration sanity of the session reader included),
reads each camera's reference frames, a few frames and its strobe window
(:func:`schlieren.storage.rigcheck.camera_inputs`), checks the cameras in threads
(:func:`schlieren.pipeline.rigcheck.check_camera`: OpenCV and numba release the GIL),
and renders the result as a terminal table (:func:`table_text`) and an HTML page
(:func:`write_page`, through :class:`~schlieren.storage.report.ReportWriter`).
:func:`watch` re-checks a folder that is being filled whenever its files change.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schlieren.pipeline.capture.params import CaptureParams
from schlieren.pipeline.flow.params import FlowParams
from schlieren.pipeline.rigcheck import (FLOW_NOISE_SHARE, CameraCheck, CheckParams, FamilyCase, check_camera,
                                         expected_accuracy, expected_psnr)
from schlieren.storage.errors import SchlierenInputError

log = logging.getLogger(__name__)

__all__ = ["RigCheck", "check_session", "table_rows", "table_text", "write_page", "watch", "HEADER"]

#: Where the family's results live in a source checkout (``--results`` overrides it).
DEFAULT_RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


@dataclass
class RigCheck:
    """A session's check: every camera's result (or why it could not be checked), the
    family case it is compared with, and how long it took."""

    name: str
    manifest: str
    cameras: list = field(default_factory=list)   # CameraCheck or (name, error text)
    family: FamilyCase | None = None
    family_files: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def checked(self) -> list[CameraCheck]:
        return [c for c in self.cameras if isinstance(c, CameraCheck)]


def _one_camera(session, c: int, flow: FlowParams, capture: CaptureParams, params: CheckParams):
    from schlieren.storage.rigcheck import camera_inputs

    cam = session.cameras[c]
    try:
        inp = camera_inputs(session, c, motion_frames=params.motion_frames)
        first = session.strobe_search[0] if session.strobe_search else 0
        return check_camera(cam, session.grid, inp.reference_frames, inp.frames, frame_indices=inp.frame_indices,
                            n_reference=inp.n_reference, strobe_rows=inp.strobe_rows, strobe_first=first,
                            frame_rate=session.frame_rate, full_scale=inp.full_scale, flow=flow, capture=capture,
                            params=params)
    except Exception as exc:  # a file still being written, a decoder's error: this camera's row says it
        return cam.name, str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def check_session(path, *, results: str | os.PathLike | None = None, params: CheckParams = CheckParams(),
                  flow: FlowParams = FlowParams(), capture: CaptureParams = CaptureParams(),
                  threads: int | None = None) -> RigCheck:
    """Check the session at ``path`` (:class:`RigCheck`); the manifest's problems raise
    :class:`~schlieren.storage.errors.SessionError` as ``schlieren run`` would.

    The cameras are checked in ``threads`` threads (default: one per core, at most 8):
    decoding, OpenCV, numpy and numba release the GIL, and each kernel runs
    single-threaded (:func:`~schlieren.workers.kernel_threads.single_threaded_kernels`) so the
    threads do not oversubscribe the cores."""
    from schlieren.storage.readers.kinds import is_video
    from schlieren.storage.rigcheck import family_cases
    from schlieren.storage.session import load_session
    from schlieren.workers.kernel_threads import single_threaded_kernels

    t0 = time.perf_counter()
    session = load_session(path, check_files=False)
    n = len(session.cameras)
    workers = threads or min(n, os.cpu_count() or 1, 8)
    with single_threaded_kernels(), ThreadPoolExecutor(max_workers=workers) as pool:
        cams = list(pool.map(lambda c: _one_camera(session, c, flow, capture, params), range(n)))
    cases, files = family_cases(results if results is not None else DEFAULT_RESULTS)
    video = any(is_video(s.frames) for s in session.sources)
    fam = expected_accuracy(cases, cameras=n, size=tuple(session.cameras[0].image_size), video=video)
    return RigCheck(session.name, str(session.manifest_path), cams, fam, files, time.perf_counter() - t0)


HEADER = ["camera", "noise", "flow noise", "window", "focus", "clipped", "shift", "hot/dead", "flash",
          "offset", "footprint", "voxel"]
UNITS = ["", "grey", "px", "px", "(rel. best)", "% dark/white", "px (max)", "px", "", "ms (rel.)", "px (% image)",
         "mm run / implied"]


def _focus_best(rig: RigCheck) -> float:
    vals = [c.focus for c in rig.checked if np.isfinite(c.focus)]
    return max(vals) if vals else float("nan")


def _offsets_ms(rig: RigCheck) -> dict:
    offs = {c.name: c.offset for c in rig.checked if c.offset is not None}
    if not offs:
        return {}
    med = float(np.median(list(offs.values())))
    return {k: 1e3 * (v - med) for k, v in offs.items()}


def table_rows(rig: RigCheck, params: CheckParams = CheckParams()) -> list[list[str]]:
    """One row of strings per camera (the columns of :data:`HEADER`)."""
    best = _focus_best(rig)
    offs = _offsets_ms(rig)
    rows = []
    for c in rig.cameras:
        if not isinstance(c, CameraCheck):
            rows.append([c[0], "error: " + c[1]] + [""] * (len(HEADER) - 2))
            continue
        s = c.shift
        fp = c.footprint
        flash = c.flash.split(" (SNR")[0] if c.flash else "-"
        rows.append([
            c.name, f"{c.noise:.2f}", f"{c.flow_noise:.4f}", str(c.window),
            f"{c.focus:.3f} ({c.focus / best:.2f})" if best > 0 else f"{c.focus:.3f}",
            f"{100 * c.clipped[0]:.2f} / {100 * c.clipped[1]:.2f}",
            "-" if s is None else f"{s.du:+.3f},{s.dv:+.3f}",
            f"{len(c.hot)}/{len(c.dead)}", flash,
            f"{offs[c.name]:+.3f}" if c.name in offs else "-",
            f"{fp.size[0]}x{fp.size[1]} ({100 * fp.fraction:.0f} %)",
            f"{1e3 * fp.px_per_voxel * fp.metres_per_px:.2f} / {1e3 * fp.implied_voxel:.2f}"])
    return rows


def flow_noise_ratios(rig: RigCheck) -> dict[str, tuple[float, float]]:
    """Per checked camera: its predicted flow noise over what the family case's in-focus
    background gives at its LK window, at its own sensor noise and reference frames (what
    is left is the background: focus and texture) and at the family's (everything, the
    sensor and the reference included); empty without the family's flow noise
    (``check_family.json``)."""
    f = rig.family
    out = {}
    for c in rig.checked:
        ref = f.flow_noise_at(c.window) if f is not None else None
        if ref and np.isfinite(c.flow_noise) and np.isfinite(c.noise) and c.noise > 0:
            out[c.name] = (c.flow_noise / f.flow_noise_at(c.window, c.noise, c.n_reference), c.flow_noise / ref)
    return out


def _loss(ratio: float) -> float:
    """The in-plume dB a rig of cameras with this flow-noise ratio loses (expect.py)."""
    return 10.0 * np.log10(1.0 - FLOW_NOISE_SHARE + FLOW_NOISE_SHARE * ratio * ratio)


def _flow_noise_notes(rig: RigCheck, params: CheckParams) -> list[str]:
    """One line naming the cameras whose background gives well more flow noise than the
    family's in focus, one for those whose flow noise is high for another reason (the sensor)."""
    ratios = flow_noise_ratios(rig)
    soft = {k: v for k, v in ratios.items() if v[0] > params.max_flow_noise_excess}
    noisy = {k: v for k, v in ratios.items() if k not in soft and v[1] > params.max_flow_noise_excess}
    out = []
    if soft:
        r = [v[0] for v in soft.values()]
        out.append(f"{', '.join(soft)}: predicted flow noise {min(r):.2f}-{max(r):.2f}x what the benchmark family's "
                   f"in-focus background gives at the same window and sensor noise: out of focus, or a weaker "
                   f"texture (about -{_loss(float(np.median(r))):.1f} dB in plume)")
    if noisy:
        r = [v[1] for v in noisy.values()]
        out.append(f"{', '.join(noisy)}: predicted flow noise {min(r):.2f}-{max(r):.2f}x the benchmark family's at "
                   f"the same window: a noisier sensor or fewer reference frames (about "
                   f"-{_loss(float(np.median(r))):.1f} dB in plume)")
    return out


def _notes(rig: RigCheck, params: CheckParams) -> list[str]:
    best = _focus_best(rig)
    out = []
    for c in rig.checked:
        notes = list(c.notes)
        if best > 0 and c.focus < params.min_focus_ratio * best:
            notes.append(f"focus {c.focus / best:.2f} of the rig's best: out of focus, or a coarser view of the "
                         "background")
        out += [f"{c.name}: {n}" for n in notes]
    return out + _flow_noise_notes(rig, params)


def expectation_text(rig: RigCheck) -> str:
    """The in-plume accuracy to expect from this rig's predicted flow noise, and where it comes from."""
    f = rig.family
    if f is None:
        return "expected accuracy: no benchmark family results found (benchmarks/results/realistic.json)"
    files = ", ".join(os.path.relpath(p) if not os.path.relpath(p).startswith("..") else p
                      for p in rig.family_files)
    case = (f"the benchmark family's nearest case {f.name} ({f.cameras} cameras, {f.size[0]}x{f.size[1]}, "
            f"{'video' if f.video else 'lossless'}), which reached {f.plume:.1f} dB in plume and {f.whole:.1f} dB "
            f"in the whole box for 0.25-0.4 px deflections")
    bound = f" (its tomography's bound {f.plume_bound:.1f} dB)" if f.plume_bound is not None else ""
    ratios = [v[1] for v in flow_noise_ratios(rig).values()]
    if not ratios:
        noise = [c.noise for c in rig.checked if np.isfinite(c.noise)]
        r = float(np.median(noise)) / f.noise if noise else float("nan")
        return (f"expected in plume: {f.plume:.1f} dB, whole box {f.whole:.1f} dB{bound}, as {case}; this rig's "
                f"sensor noise is {r:.2g}x the family's {f.noise:g} grey levels (the family's flow noise is not "
                f"measured: check_family.json) [{files}]")
    plume = expected_psnr(f.plume, ratios, bound=f.plume_bound)
    whole = expected_psnr(f.whole, ratios)
    rms = float(np.sqrt(np.mean(np.square(ratios))))
    return (f"expected in plume: {plume:.1f} dB, whole box {whole:.1f} dB, from this rig's predicted flow noise "
            f"({rms:.2f}x, RMS over the cameras, what the family's in-focus background gives at the same window, "
            f"the family's {f.noise:.2f} grey levels and {f.n_reference} reference frames) against {case}{bound} "
            f"[{files}]")


def _format_table(header: list[str], units: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(h), len(u), *(len(r[k]) for r in rows)) for k, (h, u) in enumerate(zip(header, units))]

    def line(cells):
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()

    return [line(header), line(units)] + [line(r) for r in rows]


def table_text(rig: RigCheck, params: CheckParams = CheckParams()) -> str:
    """The terminal output: the table, the notes, the expected accuracy and the time taken."""
    lines = [f"check of {rig.name} ({rig.manifest}), {len(rig.cameras)} cameras"]
    lines += _format_table(HEADER, UNITS, table_rows(rig, params))
    notes = _notes(rig, params)
    lines += ["", "notes:"] + [f"  {n}" for n in notes] if notes else ["", "notes: none"]
    lines += ["", expectation_text(rig), f"checked in {rig.seconds:.1f} s"]
    return "\n".join(lines)


def write_page(rig: RigCheck, out_dir, params: CheckParams = CheckParams()) -> Path:
    """Write ``out_dir/index.html`` (the table, notes and expectation) and ``summary.json``."""
    import html

    from schlieren.storage.report import ReportPage, ReportWriter, html_table

    page = ReportPage(f"Rig check: {rig.name}")
    header = [f"{h} ({u})" if u else h for h, u in zip(HEADER, UNITS)]
    page.add("Cameras", html_table(header, table_rows(rig, params), cls="num"), "cameras")
    notes = _notes(rig, params)
    body = "<ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>" if notes else "<p>none</p>"
    page.add("Notes", body, "notes")
    page.add("Expected accuracy", f"<p>{html.escape(expectation_text(rig))}</p>", "expected")
    page.add("About", f"<p>{html.escape(rig.manifest)}; checked in {rig.seconds:.1f} s. Columns: "
                      "docs/check.md.</p>", "about")
    page.summary = {"session": rig.manifest, "seconds": rig.seconds, "header": HEADER,
                    "rows": table_rows(rig, params), "notes": notes,
                    "family_case": None if rig.family is None else rig.family.name}
    return ReportWriter(out_dir).finish(page)


def _state_or_none(folder):
    from schlieren.storage.rigcheck import folder_state

    return folder_state(folder)


# long: the watch loop's states (no manifest yet, a refused manifest, a table) in one place
def watch(folder, *, interval: float = 2.0, results=None, params: CheckParams = CheckParams(),
          flow: FlowParams = FlowParams(), out=print, sleep=time.sleep, max_polls: int | None = None) -> int:
    """Re-check ``folder`` whenever its files change (polling every ``interval`` seconds),
    printing only what changed: the table's header once, then each camera's row when it
    differs from the last one printed, new notes, and the manifest's problem while it
    has one. Ctrl-C ends it (returns 0)."""
    from schlieren.storage.session.types import MANIFEST_NAME

    last_state, last_rows, last_notes, last_error, header_done = None, {}, set(), None, False
    polls = 0
    try:
        while max_polls is None or polls < max_polls:
            polls += 1
            state = _state_or_none(folder)
            if state != last_state:
                last_state = state
                if not (Path(folder) / MANIFEST_NAME).is_file():
                    msg = f"waiting for {MANIFEST_NAME} in {folder}"
                    if msg != last_error:
                        out(msg)
                        last_error = msg
                else:
                    try:
                        rig = check_session(folder, results=results, params=params, flow=flow)
                    except SchlierenInputError as exc:
                        if str(exc) != last_error:
                            out(f"session refused: {exc}")
                            last_error = str(exc)
                    else:
                        last_error = None
                        lines = _format_table(HEADER, UNITS, table_rows(rig, params))
                        if not header_done:
                            out("\n".join(lines[:2]))
                            header_done = True
                        for cam, line in zip(rig.cameras, lines[2:]):
                            name = cam.name if isinstance(cam, CameraCheck) else cam[0]
                            if last_rows.get(name) != line:
                                out(line)
                                last_rows[name] = line
                        for n in _notes(rig, params):
                            if n not in last_notes:
                                out(f"note: {n}")
                                last_notes.add(n)
            if max_polls is None or polls < max_polls:
                sleep(interval)
    except KeyboardInterrupt:
        out("watch stopped")
    return 0
