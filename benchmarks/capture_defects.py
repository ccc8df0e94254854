"""What a lab capture's defects cost, and what the capture corrections win back (issue 33).

    python benchmarks/capture_defects.py [--clean /work/realistic/plume1-16cam-640]
        [--work capture-defects-out] [--seed 0] [--runs clean,lab-off,lab,...]

Takes a rendered clean session of the realistic family (default: ``plume1-16cam-640``,
16 cameras at 640x480, 0.25 px deflections; ``schlieren bench realistic`` renders it),
writes the lab copies of it that the runs need (benchmarks/lab_perturbation.py: camera
motion, defocus, flicker and banding, defective pixels, all together or one at a time),
and reconstructs each run's session with the run's configuration (:data:`RUNS`). Each
run is scored against the truth: whole box and in-plume dB, the masks' and the hull's
fill fractions, the motion the flow still shows on the static cells (median over
camera-frames), the stored motion against the true one (RMS displacement error over the
image), the defective pixels found, and the pipeline's time; with the lamp drawn, the
stored gain and offset profiles against the true ones. ``--score-lab STORE`` scores stores
of captures rendered with lab effects (the family's ``-lab`` cases) against their
``lab.json`` the same way (:func:`score_lab_store`). Writes
``benchmarks/results/capture_defects.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lab_perturbation import SESSIONS, LabSpec, perturb_session, rigid_motion, true_photometric  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CLEAN = Path("/work/realistic/plume1-16cam-640")


# ------------------------------------------------------------------------------ runs
_OFF = {"capture": {"motion_model": "none", "photometric": False, "defective_pixels": False}}
#: name -> (session, params, description)
RUNS = {
    "clean": ("clean", {}, "clean capture, defaults"),
    "clean-off": ("clean", _OFF, "clean capture, capture corrections off (today's pipeline)"),
    "lab-off": ("lab", _OFF, "lab capture, capture corrections off (today's pipeline)"),
    "lab": ("lab", {}, "lab capture, defaults (motion, photometric, defective pixels)"),
    "lab-motion-only": ("lab", {"capture": {"photometric": False, "defective_pixels": False}},
                        "lab capture, motion only"),
    "lab-no-motion": ("lab", {"capture": {"motion_model": "none"}},
                      "lab capture, photometric and defective pixels only"),
    "lab-background": ("lab", {"capture": {"motion_source": "background"}},
                       "lab capture, defaults but motion_source background (no resampling)"),
    "sharp-off": ("sharp", _OFF, "lab capture without defocus, corrections off"),
    "sharp": ("sharp", {}, "lab capture without defocus, defaults"),
    "defocus": ("defocus", {}, "clean capture with the defocus alone, defaults"),
    "noisy": ("noisy", {}, "clean capture in focus, sensor noise raised to the defocus's predicted flow noise"),
    "noisier": ("noisier", {}, "clean capture in focus, sensor noise raised to the defocus's measured flow noise"),
    "motion": ("motion", {}, "camera motion alone, defaults"),
    "motion-off": ("motion", _OFF, "camera motion alone, corrections off"),
    "flicker": ("flicker", {}, "flicker and row banding alone, defaults"),
    "flicker-off": ("flicker", _OFF, "flicker and row banding alone, corrections off"),
    "pixels": ("pixels", {}, "hot, dead and stuck pixels alone, defaults"),
    "pixels-off": ("pixels", _OFF, "hot, dead and stuck pixels alone, corrections off"),
}


def _file_name(run: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", run).strip("_")


def probe_run(text: str) -> tuple[str, tuple[str, dict, str]]:
    """A run from ``--probe SESSION:GROUP.NAME=VALUE[;...]`` (values as JSON, else strings):
    ``(name, (session, params, description))``."""
    which, _, settings = text.partition(":")
    if which not in SESSIONS:
        raise SystemExit(f"--probe {text}: no session {which!r} (one of {', '.join(SESSIONS)})")
    params: dict = {}
    for item in (i for i in settings.split(";") if i):
        key, _, value = item.partition("=")
        group, _, field = key.strip().partition(".")
        try:
            v = json.loads(value)
        except json.JSONDecodeError:
            v = value.strip()
        params.setdefault(group, {})[field] = v
    return f"{which}[{settings}]", (which, params, f"{which} capture, {settings or 'defaults'}")


def run_one(name: str, session: Path, truth: Path, store: Path, params: dict, *, motion_truth=None,
            defects_truth=None, lamp_truth=None, spec: LabSpec | None = None, describe: str = "") -> dict:
    """Reconstruct ``session`` serially with ``params`` and score it."""
    from schlieren.pipeline.stages import config_from_dict
    from schlieren.storage import bench_io
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.run import run_session

    bench_io.remove_tree(store)
    t0 = time.perf_counter()
    summary = run_session(session, store, serial=True, config=config_from_dict(params))
    seconds = time.perf_counter() - t0
    res = {"run": name, "describe": describe or name, "params": params,
           "pipeline_seconds": seconds,
           "cpu_seconds": {k: float(v) for k, v in (summary.stage_cpu_seconds or {}).items()}}
    if not summary.ok:
        res["failures"] = dict(summary.root_failures())
        return res
    ev = evaluate(store, truth)
    res.update(psnr=ev["overall"]["psnr"], psnr_plume=ev["plume"]["psnr"], warnings=list(summary.warnings))
    res.update(_store_metrics(store, session, motion_truth, defects_truth))
    if lamp_truth and spec is not None and spec.photometric:
        res.update(_photometric_errors(store, session, lamp_truth, spec))
    return res


def _store_metrics(store: Path, session: Path, motion_truth, defects_truth) -> dict:
    """Fill fractions, the motion left in the flow, the motion's error and the defects found."""
    from schlieren.pipeline import capture
    from schlieren.storage.session import load_session
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store, mode="r")
    sess = load_session(session)
    g = sess.grid
    a = st.attrs
    f = int(a["run"]["flow_factor"])
    raw_first, first = int(a["run"]["raw_first"]), int(a["run"]["frames"][0])
    n = int(a["run"]["n_frames"])
    flow_raw = np.asarray(st.array("flow_raw")[:])
    stored = np.asarray(st.array("background_motion")[:])
    left, err = [], []
    for c, cam in enumerate(sess.cameras):
        cells = capture.static_cells(capture.static_region(cam, g.vmin, g.vmax), f)
        for j in range(first - raw_first, first - raw_first + n):
            m, _ = capture.fit_flow_motion(flow_raw[c, j], cells, cam.image_size, f)
            left.append(capture.motion_extent(m, cam.image_size))
            if motion_truth and motion_truth.get(cam.name):
                true = np.asarray(motion_truth[cam.name][str(raw_first + j)])
                err.append(_displacement_rms(stored[c, j] - true, cam.image_size))
    out = {"mask_fill": float(np.mean(st.array("mask")[:])), "hull_fill": float(np.mean(st.array("hull")[:])),
           "motion_left_median": float(np.median(left))}
    if err:
        out["motion_error_rms"] = float(np.sqrt(np.mean(np.square(err))))
        out["motion_error_max"] = float(np.max(err))
    out["defects"] = _defects_found(np.asarray(st.array("defective_pixels")[:]), sess, defects_truth)
    return out


def _photometric_errors(store: Path, session: Path, lamp_truth: dict, spec: LabSpec) -> dict:
    """The stored gain and offset profiles (``photometric``) against the lamp drawn: RMS
    over knots and processed camera-frames of the gain's error, of the offset's error in
    grey levels, and of the true gain's departure from 1 (the size of what was removed)."""
    from schlieren.storage.session import load_session
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store, mode="r")
    sess = load_session(session)
    a = st.attrs
    raw_first, first, n = int(a["run"]["raw_first"]), int(a["run"]["frames"][0]), int(a["run"]["n_frames"])
    knots = np.asarray(st.array("row_knot")[:], np.float64)
    ph = np.asarray(st.array("photometric")[:], np.float64)
    dg, do, g0, o0 = [], [], [], []
    for c, cam in enumerate(sess.cameras):
        for j in range(first - raw_first, first - raw_first + n):
            gain, offset = true_photometric(lamp_truth[cam.name], spec, knots, raw_first + j)
            dg.append(ph[c, j, 0] - gain)
            do.append(ph[c, j, 1] - offset)
            g0.append(gain - 1.0)
            o0.append(offset)
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    return {"gain_error_rms": rms(dg), "offset_error_rms": rms(do), "gain_true_rms": rms(g0),
            "offset_true_rms": rms(o0)}


def _displacement_rms(dm: np.ndarray, image_size) -> float:
    """RMS over the image (every 8th pixel) of the displacement of motion vector ``dm``."""
    from schlieren.pipeline.capture import motion_displacement

    W, H = image_size
    y, x = np.mgrid[0:H:8, 0:W:8]
    dx, dy = motion_displacement(dm, x, y, image_size)
    return float(np.sqrt(np.mean(dx * dx + dy * dy)))


def _defects_found(found: np.ndarray, sess, truth) -> dict:
    total = int(np.count_nonzero(found))
    if truth is None:
        return {"flagged": total}
    hit = missed = 0
    for c, cam in enumerate(sess.cameras):
        t = truth[cam.name]
        ok = found[c, t["rows"], t["cols"]] != 0
        hit += int(np.count_nonzero(ok))
        missed += int(np.count_nonzero(~ok))
    return {"flagged": total, "found": hit, "missed": missed, "false": total - hit}


# ------------------------------------------------------------------------------ rendered lab captures
def score_lab_store(store: Path, session_dir: Path) -> dict:
    """A store of a capture rendered with lab effects (``schlieren synth --lab``, the family's
    ``-lab`` cases) against what its ``lab.json`` says was drawn: the stored motion's RMS
    displacement error over the image (and the true motion's RMS), the gain and offset
    profiles' RMS errors (and the true ones' departures), and the defective pixels found."""
    from schlieren.storage.session import load_session
    from schlieren.storage.store import ResultStore
    from schlieren.pipeline.capture import motion_displacement
    from schlieren.storage.synthetic_io import read_lab_truth

    lab = read_lab_truth(session_dir)
    st = ResultStore.open(store, mode="r")
    sess = load_session(session_dir / "session.yaml")
    a = st.attrs
    raw_first, first, n = int(a["run"]["raw_first"]), int(a["run"]["frames"][0]), int(a["run"]["n_frames"])
    motion = np.asarray(st.array("background_motion")[:], np.float64)
    ph = np.asarray(st.array("photometric")[:], np.float64)
    knots = np.asarray(st.array("row_knot")[:], np.float64)
    found = np.asarray(st.array("defective_pixels")[:])
    band, hz, line = float(lab["params"].get("banding", 0.0)), float(lab["params"].get("banding_frequency", 100.0)), \
        float(lab["line_time"])
    err, true, dg, do, g0, o0 = [], [], [], [], [], []
    hit = missed = 0
    for c, cam in enumerate(sess.cameras):
        t = lab["cameras"][cam.name]
        W, H = cam.image_size
        y, x = np.mgrid[0:H:8, 0:W:8].astype(np.float64)
        ref = {k: np.asarray(t["ref_" + k], np.float64) for k in ("gain", "offset", "phase")}
        G = np.mean(ref["gain"][:, None] * (1.0 + band * np.sin(2 * np.pi * hz * line * knots[None] +
                                                                 ref["phase"][:, None])), axis=0)
        O = float(np.mean(ref["offset"]))
        for j in range(first - raw_first, first - raw_first + n):
            r = raw_first + j
            Hi = np.linalg.inv(np.asarray(t["homography"][r], np.float64))  # frame pixel -> reference pixel
            den = Hi[2, 0] * x + Hi[2, 1] * y + Hi[2, 2]
            tx = (Hi[0, 0] * x + Hi[0, 1] * y + Hi[0, 2]) / den - x
            ty = (Hi[1, 0] * x + Hi[1, 1] * y + Hi[1, 2]) / den - y
            mx, my = motion_displacement(motion[c, j], x, y, cam.image_size)
            err.append(float(np.sqrt(np.mean((mx - tx) ** 2 + (my - ty) ** 2))))
            true.append(float(np.sqrt(np.mean(tx ** 2 + ty ** 2))))
            gain = t["gain"][r] * (1.0 + band * np.sin(2 * np.pi * hz * line * knots + t["phase"][r])) / G
            offset = t["offset"][r] - gain * O
            dg.append(ph[c, j, 0] - gain)
            do.append(ph[c, j, 1] - offset)
            g0.append(gain - 1.0)
            o0.append(offset)
        pix = [tuple(p) for k in ("hot", "dead", "stuck") for p in t.get(k, [])]
        if pix:
            rows, cols = np.asarray(pix).T
            ok = found[c, rows, cols] != 0
            hit += int(np.count_nonzero(ok))
            missed += int(np.count_nonzero(~ok))
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    total = int(np.count_nonzero(found))
    return {"motion_error_rms": rms(err), "motion_error_max": float(np.max(err)), "motion_true_rms": rms(true),
            "gain_error_rms": rms(dg), "offset_error_rms": rms(do), "gain_true_rms": rms(g0),
            "offset_true_rms": rms(o0), "defects": {"flagged": total, "found": hit, "missed": missed,
                                                    "false": total - hit}}


# ------------------------------------------------------------------------------ flow start
def flow_start_probe(clean: Path, *, camera: int = 0, frames=(4, 5, 6),
                     shifts=(0.1, 0.3, 0.5, 1.0, 2.0), theta: float = 2e-4) -> list[dict]:
    """Whether the flow should start from the motion (LK warps the reference by it in its
    own B-spline warp, without resampling it twice), only subtract it afterwards, or run on
    a reference resampled at the moved positions: one camera's frames moved by a known
    rigid motion, each way moved back onto the reference grid, their end-point error
    against the rendered truth (flow cells of 6 px, where the truth is)."""
    import functools

    import zarr

    from schlieren.pipeline import capture
    from schlieren.pipeline.flow import deflection_stage, prepare_reference
    from schlieren.pipeline.flow.splines import warp_image
    from schlieren.storage.frames import open_frames, read_reference
    from schlieren.storage.session import load_session
    from schlieren.pipeline.flow import window_for_voxel
    from schlieren.pipeline.geometry import pixel_footprint
    from schlieren.pipeline.stages import RunConfig, bind_flow_factor

    sess = load_session(clean / "session.yaml")
    cam, src = sess.cameras[camera], sess.sources[camera]
    flow = bind_flow_factor(RunConfig(), sess.cameras, sess.grid).flow
    grid = sess.grid  # the run's LK window (workers/tasks/deflection.py: flow_params)
    params = flow
    if flow.window_per_voxel > 0:
        px = grid.voxel_size / pixel_footprint(cam, grid.center)
        params = dataclasses.replace(flow, window=window_for_voxel(px, flow.window_per_voxel))
    f, size = params.factor, cam.image_size
    prep = prepare_reference(read_reference(src, camera_name=src.name), presmooth=params.presmooth, levels=params.levels)
    truth = zarr.open_group(str(clean / "truth.zarr"), mode="r")
    first = int(sess.frames[0])
    reader = open_frames(src, camera_name=src.name)

    def cells(d, k):  # block means onto cells of k flow cells
        h, w = d.shape[0] // k, d.shape[1] // k
        return d[:h * k, :w * k].reshape(h, k, w, k, -1).mean(axis=(1, 3))

    rows = []
    for s in (0.0,) + tuple(shifts):
        errs = {"subtract": [], "start": [], "warped": []}
        for fr in frames:
            t = cells(np.asarray(truth["deflection_rs"][camera, fr - first]), 6 // int(truth.attrs["flow_factor"]))
            img, m = rigid_motion(reader.read(fr).astype(np.float64), s, -0.6 * s, theta if s else 0.0)
            img = np.clip(np.round(img), 0, 255).astype(np.float32)
            field = functools.partial(capture.motion_displacement, m, image_size=size)
            start = deflection_stage(prep, img, params, motion=field)
            sub = deflection_stage(prep, img, params) - capture.motion_field(m, size, f)
            # the reference resampled at p + motion(p) (cubic B-spline), then the flow from zero
            yy, xx = np.mgrid[0:size[1], 0:size[0]].astype(np.float64)
            mx, my = field(xx, yy)
            ref_moved = warp_image(prep.image, np.dstack([mx, my]).astype(np.float32))
            warped = deflection_stage(prepare_reference(ref_moved, presmooth=params.presmooth, levels=params.levels), img, params)
            for key, d in (("start", start), ("subtract", sub), ("warped", warped)):
                d = capture.to_reference_grid(d, m, size, f)
                e = cells(d, 6 // f)[:t.shape[0], :t.shape[1]] - t
                errs[key].append(float(np.sqrt(np.nanmean(np.sum(e * e, axis=-1)))))
        rows.append({"shift": s, **{k: float(np.mean(v)) for k, v in errs.items()}})
    return rows


# ------------------------------------------------------------------------------ report
def markdown(result: dict) -> str:
    rows = result["runs"]
    lines = ["# Capture defects: clean vs lab vs lab with the capture corrections (issue 33)", "",
             f"Command: `python benchmarks/capture_defects.py {result['argv']}`. Clean session: "
             f"`{result['clean']}` (the realistic family's case, rendered by `schlieren bench realistic`); "
             "the lab session is the same capture with the perturbations of the benchmark's docstring "
             f"(seed {result['seed']}): {result['spec_text']}", "",
             "| run | whole box dB | in plume dB | mask fill | hull fill | motion left (median px) | "
             "motion error RMS px | gain error RMS (true) | offset error RMS grey (true) | "
             "defective pixels found / missed / false | pipeline s | deflection CPU s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        if "failures" in r:
            lines.append(f"| {r['describe']} | failed: {list(r['failures'].values())[:1]} | | | | | | | | | | |")
            continue
        d = r.get("defects", {})
        dtext = f"{d.get('found', '-')} / {d.get('missed', '-')} / {d.get('false', d.get('flagged', '-'))}"
        me = r.get("motion_error_rms")
        gtext, otext = "-", "-"
        if "gain_error_rms" in r:
            gtext = f"{r['gain_error_rms']:.4f} ({r['gain_true_rms']:.4f})"
            otext = f"{r['offset_error_rms']:.2f} ({r['offset_true_rms']:.2f})"
        lines.append(f"| {r['describe']} | {r['psnr']:.2f} | {r['psnr_plume']:.2f} | {r['mask_fill']:.3f} | "
                     f"{r['hull_fill']:.3f} | {r['motion_left_median']:.4f} | "
                     f"{'-' if me is None else f'{me:.4f}'} | {gtext} | {otext} | {dtext} | "
                     f"{r['pipeline_seconds']:.0f} | "
                     f"{r.get('cpu_seconds', {}).get('deflection', float('nan')):.1f} |")
    if result.get("lab_scores"):
        lines += ["", "## Captures rendered with lab effects", "",
                  "Stores of sessions rendered with lab effects (`schlieren synth --lab`, the family's `-lab` "
                  "cases), scored against the session's `lab.json`:", "",
                  "| store | motion error RMS px (max) | true motion RMS px | gain error RMS (true) | "
                  "offset error RMS grey (true) | defective pixels found / missed / false |",
                  "|---|---:|---:|---:|---:|---|"]
        for r in result["lab_scores"]:
            d = r["defects"]
            lines.append(f"| `{r['store']}` | {r['motion_error_rms']:.4f} ({r['motion_error_max']:.4f}) | "
                         f"{r['motion_true_rms']:.4f} | {r['gain_error_rms']:.4f} ({r['gain_true_rms']:.4f}) | "
                         f"{r['offset_error_rms']:.2f} ({r['offset_true_rms']:.2f}) | "
                         f"{d['found']} / {d['missed']} / {d['false']} |")
    if result.get("flow_start"):
        lines += ["", "## Start the flow from the motion, or subtract it afterwards", "",
                  f"One camera of the clean session (`{result['flow_start_camera']}`), its frames moved by a "
                  "known rigid motion (shift `s` along (1, -0.6) and a 2e-4 rad rotation; FFT shears), the true "
                  "motion removed either way and the result moved back onto the reference grid; end-point "
                  "error (px) against the rendered truth on 6 px cells, mean over the frames:", "",
                  "| shift s (px) | start from the motion | subtract afterwards | reference warped by the motion |",
                  "|---:|---:|---:|---:|"]
        lines += [f"| {r['shift']:.1f} | {r['start']:.4f} | {r['subtract']:.4f} | {r['warped']:.4f} |"
                  for r in result["flow_start"]]
    lines += ["", "* motion left: the largest displacement of the affine motion fitted (Tukey IRLS) to each "
              "camera-frame's stored `flow_raw` on the static cells, median over the processed camera-frames.",
              "* motion error: the stored `background_motion` against the true motion, RMS displacement over "
              "the image, RMS over the camera-frames (lab runs with motion estimated).",
              "* gain / offset error: the stored `photometric` profiles (gain, and offset in grey levels, at the "
              "row knots) against the lamp drawn, mapped onto the averaged reference (`true_photometric`), RMS over "
              "knots and processed camera-frames; in brackets the RMS of the true gain's departure from 1 and of "
              "the true offset: what there was to recover.",
              f"* Machine: {result['machine']}; timings are on a loaded machine (re-measure quiet)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--clean", type=Path, default=DEFAULT_CLEAN, help="a rendered clean session folder with truth.zarr")
    p.add_argument("--work", type=Path, default=Path("capture-defects-out"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs", default="clean,clean-off,lab,lab-off,sharp,defocus,lab-motion-only,lab-no-motion,"
                                     "lab-background")
    p.add_argument("--label", default="", help="results file suffix (capture_defects_LABEL.md)")
    p.add_argument("--score-lab", default="", metavar="STORE[,STORE...]",
                   help="also score stores of captures rendered with lab effects (the session is the store's folder, "
                        "its lab.json the truth)")
    p.add_argument("--probe", action="append", default=[], metavar="SESSION:GROUP.NAME=VALUE[;...]",
                   help="also run a session (clean, or a copy of lab_perturbation.SESSIONS) with these parameters "
                        "(values as JSON; repeatable)")
    p.add_argument("--flow-start", action="store_true", help="also measure starting the flow from the motion "
                                                              "against subtracting it (one camera)")
    args = p.parse_args(argv)
    results = []
    truths = {}
    runs = {name: RUNS[name] for name in args.runs.split(",") if name}
    runs.update(probe_run(text) for text in args.probe)
    for name, (which, params, describe) in runs.items():
        if which == "clean":
            src, truth = args.clean, (None, None, None)
        else:
            src = args.work / which
            if not (src / "motion_truth.json").exists():
                print(f"writing the {which} session {src}", file=sys.stderr)
                perturb_session(args.clean, src, SESSIONS[which], seed=args.seed)
            if which not in truths:
                lamp = src / "lamp_truth.json"
                truths[which] = (json.loads((src / "motion_truth.json").read_text()),
                                 json.loads((src / "defects_truth.json").read_text()),
                                 json.loads(lamp.read_text()) if lamp.exists() else None)
            truth = truths[which]
        print(f"{name}: running", file=sys.stderr)
        r = run_one(name, src / "session.yaml", src / "truth.zarr", args.work / f"store-{_file_name(name)}.zarr", params,
                    motion_truth=truth[0] or None, defects_truth=truth[1] or None, lamp_truth=truth[2],
                    spec=SESSIONS[which], describe=describe)
        print(f"{name}: {json.dumps({k: v for k, v in r.items() if k not in ('params', 'warnings')})}",
              file=sys.stderr)
        results.append(r)
    lab_scores = [dict(store=str(st), **score_lab_store(Path(st), Path(st).parent))
                  for st in args.score_lab.split(",") if st]
    load = os.getloadavg()[0]
    probe = flow_start_probe(args.clean) if args.flow_start else None
    spec = SESSIONS["lab"]
    result = {"flow_start": probe, "flow_start_camera": "cam00" if probe else None,
              "argv": " ".join(argv if argv is not None else sys.argv[1:]), "clean": str(args.clean),
              "seed": args.seed, "spec": dataclasses.asdict(spec),
              "spec_text": ", ".join(f"{k} {v}" for k, v in dataclasses.asdict(spec).items()),
              "machine": f"{os.cpu_count()} cores, 1-min load {load:.1f} at the end", "runs": results,
              "lab_scores": lab_scores}
    stem = "capture_defects" + (f"_{args.label}" if args.label else "")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2))
    (RESULTS / f"{stem}.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
