"""CPU of the capture corrections per camera-frame and per camera at paper scale (issue 35's
speed target), A/B against a baseline revision in one process.

    python benchmarks/capture_speed.py [--cameras 4] [--frames 4] [--repeats 2] [--baseline REV]
        [--session DIR] [--profile] [--out NAME]

Reads the session of ``benchmarks/session.py`` (16 cameras x 1440x1080, rendered once into
``benchmarks/cache/session-16x1440x1080-f8``; ``--session`` takes another, e.g. a ``-lab``
case of the realistic family) and times, per camera, the two kernels of the capture path as
the tasks call them:

* the ``capture`` task's kernel, :func:`~schlieren.pipeline.capture.find_defective_pixels`
  over the reference and ``defect_frames`` capture frames (decoded beforehand; the decode is
  reported apart: both versions read the same frames);
* the ``deflection`` task's kernel, :func:`~schlieren.pipeline.capture.corrected_deflection`
  with the camera's prepared reference, static region and defective pixels, over
  ``--frames`` capture frames; for the new code also the once-per-camera preparation the
  task caches (:func:`~schlieren.pipeline.capture.prepare_capture`), reported apart and
  amortised over the camera's frames of a session in the summary.

The baseline's ``pipeline/capture`` and ``pipeline/flow`` packages are loaded from git
(``git show REV:...``) under other module names; everything else is shared. Base and new
alternate frame by frame, ``--repeats`` times, so load on the machine hits both alike. The
process runs as a Dask worker does (one thread for OpenCV, BLAS and numba; the workers'
allocator settings: the script re-executes itself with them). The outputs of both are
compared: flow (largest difference, pixels), motion (largest displacement of the
difference over the image), gain and offset, flags.

Writes ``benchmarks/results/<NAME>.json`` and ``.md`` (default ``capture_speed``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
DEFAULT_SESSION = HERE / "cache" / "session-16x1440x1080-f8"
#: The revision before the speed work (main when the capture stage went on by default).
DEFAULT_BASELINE = "bbf93a8"
#: Packages loaded from the baseline: module name -> folder in the repository.
BASE_PACKAGES = {"base_flow": "pipeline/flow", "base_capture": "pipeline/capture"}


def worker_environment() -> None:
    """Re-execute with the Dask workers' allocator and thread settings unless already set."""
    from schlieren.workers.cluster import MALLOC_ENV, THREAD_ENV

    want = {**THREAD_ENV, **MALLOC_ENV}
    if any(os.environ.get(k) != v for k, v in want.items()):
        os.execve(sys.executable, [sys.executable, __file__, *sys.argv[1:]], {**os.environ, **want})


def load_baseline(rev: str, into: Path) -> dict:
    """The baseline's flow and capture packages, imported from ``git show`` under private
    names (the capture package's imports of the flow package point at the baseline's)."""
    mods = {}
    for name, rel in BASE_PACKAGES.items():
        files = subprocess.run(["git", "-C", str(ROOT), "ls-tree", "--name-only", f"{rev}:{rel}"], check=True,
                               capture_output=True, text=True).stdout.split()
        pkg = into / name
        pkg.mkdir()
        for f in files:
            if not f.endswith(".py"):
                continue
            src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{rel}/{f}"], check=True,
                                 capture_output=True, text=True).stdout
            (pkg / f).write_text(src.replace("schlieren.pipeline.flow", "base_flow"))
        spec = importlib.util.spec_from_file_location(name, pkg / "__init__.py", submodule_search_locations=[str(pkg)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    return mods


class Variant:
    """One version of the capture path: its prepared references and CPU totals."""

    def __init__(self, name: str, capture, flow):
        self.name, self.capture, self.flow = name, capture, flow
        self.prep, self.camera = {}, {}
        self.cpu = {"defects": 0.0, "deflection": 0.0, "prepare": 0.0}
        self.n = {"defects": 0, "deflection": 0, "prepare": 0}
        self.out = {}

    def defects(self, c: int, frames, params) -> np.ndarray:
        c0 = time.process_time()
        d = self.capture.find_defective_pixels(frames, threshold=params.defect_threshold,
                                               stuck_ratio=params.stuck_ratio)
        self.cpu["defects"] += time.process_time() - c0
        self.n["defects"] += 1
        return d

    def deflection(self, c: int, f: int, img, ref, fp, cfg, static, defects) -> None:
        if c not in self.prep:
            self.prep[c] = self.flow.prepare_reference(ref, presmooth=fp.presmooth, levels=fp.levels)
        kw = {}
        if hasattr(self.capture, "prepare_capture"):
            if c not in self.camera:
                c0 = time.process_time()
                self.camera[c] = self.capture.prepare_capture(self.prep[c], fp, cfg.capture, static=static,
                                                              defects=defects)
                self.cpu["prepare"] += time.process_time() - c0
                self.n["prepare"] += 1
            kw["camera"] = self.camera[c]
        c0 = time.process_time()
        d, corr = self.capture.corrected_deflection(self.prep[c], img, fp, cfg.capture, static=static,
                                                    defects=defects, **kw)
        self.cpu["deflection"] += time.process_time() - c0
        self.n["deflection"] += 1
        self.out[c, f] = (d, corr)

    def ms(self) -> dict:
        return {k: 1e3 * self.cpu[k] / max(self.n[k], 1) for k in self.cpu}


def camera_setup(sess, cfg, c: int):
    """Camera ``c``'s flow parameters, reference, static region and the frames its capture
    task reads (decoded; with the decode's CPU)."""
    import dataclasses

    from schlieren.pipeline import capture
    from schlieren.pipeline.flow import camera_window
    from schlieren.storage.frames import open_frames, read_reference

    cam, src = sess.cameras[c], sess.sources[c]
    fp = cfg.flow
    if fp.window_per_voxel > 0:
        fp = dataclasses.replace(fp, window=camera_window(cam, sess.grid, window=fp.window,
                                                          window_per_voxel=fp.window_per_voxel))
    ref = read_reference(src, camera_name=src.name)
    static = capture.static_region(cam, sess.grid.vmin, sess.grid.vmax, margin=cfg.capture.static_margin)
    reader = open_frames(src.frames, camera_name=src.name)
    first, last = sess.frames
    n = cfg.capture.defect_frames
    picks = np.unique(np.linspace(first, last - 1, n).round().astype(int))
    c0 = time.process_time()
    frames = [ref] + [reader.read(int(f)) for f in picks]
    decode = (time.process_time() - c0) / len(frames)
    return fp, ref, static, reader, frames, decode


def compare(base: Variant, new: Variant, size) -> dict:
    """Largest differences of the new outputs from the base's over the timed camera-frames."""
    from schlieren.pipeline.capture import motion_extent

    out = {"flow_max_px": 0.0, "flow_rms_px": 0.0, "motion_max_px": 0.0, "gain_max": 0.0, "offset_max": 0.0,
           "flags_differ": 0, "base_flags": [], "new_flags": [], "residual_max_px": 0.0}
    sq, n = 0.0, 0
    for key, (db, cb) in base.out.items():
        dn, cn = new.out[key]
        both = np.isfinite(db) & np.isfinite(dn)
        diff = np.abs(dn[both] - db[both])
        out["flow_max_px"] = max(out["flow_max_px"], float(diff.max()) if diff.size else 0.0)
        sq += float(np.sum(diff ** 2))
        n += diff.size
        out["motion_max_px"] = max(out["motion_max_px"], motion_extent(cn.motion - cb.motion, size))
        out["gain_max"] = max(out["gain_max"], float(np.max(np.abs(cn.fit.photometric.gain - cb.fit.photometric.gain))))
        out["offset_max"] = max(out["offset_max"],
                                float(np.max(np.abs(cn.fit.photometric.offset - cb.fit.photometric.offset))))
        out["residual_max_px"] = max(out["residual_max_px"], abs(cn.residual - cb.residual))
        out["flags_differ"] += int(cn.flags != cb.flags)
        out["base_flags"].append(int(cb.flags))
        out["new_flags"].append(int(cn.flags))
    out["flow_rms_px"] = float(np.sqrt(sq / max(n, 1)))
    out["base_flags"] = sorted(set(out["base_flags"]))
    out["new_flags"] = sorted(set(out["new_flags"]))
    return out


def profile(variant: Variant, jobs) -> list:
    """cProfile of the variant's deflection kernel over ``jobs``: top functions by own time."""
    import cProfile
    import pstats

    pr = cProfile.Profile()
    pr.enable()
    for job in jobs:
        variant.deflection(*job)
    pr.disable()
    st = pstats.Stats(pr)
    total = sum(row[2] for row in st.stats.values())
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:20]
    return [{"function": f"{Path(fn).name}:{line}({name})" if fn != "~" else name,
             "own_ms_per_frame": 1e3 * s[2] / len(jobs), "share": s[2] / total} for (fn, line, name), s in rows]


def _relative(path: Path) -> str:
    """``path`` relative to the repository when inside it."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def load_average() -> list:
    try:
        return [round(float(x), 2) for x in os.getloadavg()]
    except OSError:
        return []


def write(result: dict, name: str) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2))
    b, n = result["base_ms"], result["new_ms"]
    per_cam = result["camera_frames_per_camera"]
    lines = [f"# Capture corrections: CPU per camera-frame and per camera (benchmarks/capture_speed.py)", "",
             f"Command: `{result['command']}`", "",
             f"Machine: {result['machine']}; load average at start / end {result['load_start']} / "
             f"{result['load_end']} (shared machine: CPU time, base and new alternating in one process; "
             "OpenCV, BLAS and numba single-threaded, glibc allocator as in the Dask workers).", "",
             f"Session: `{result['session']}`, cameras {result['cameras']}, {result['frames']} capture frames each, "
             f"{result['image_size'][0]}x{result['image_size'][1]}, flow window {result['window']} px, factor "
             f"{result['flow_factor']}; {result['repeats']} repeats. Base = `{result['baseline']}`, new = "
             f"`{result['head']}`{' + uncommitted changes' if result['dirty'] else ''}.", "",
             "| CPU ms | base | new | saved |", "| --- | ---: | ---: | ---: |"]
    rows = [("`corrected_deflection` per camera-frame (the deflection task's kernel)", b["deflection"],
             n["deflection"]),
            (f"the same plus the per-camera preparation amortised over {per_cam} camera-frames (a camera's "
             "raw frames of benchmarks/session.py on 2 workers)", b["deflection"], n["deflection"] + n["prepare"] / per_cam),
            ("`find_defective_pixels` per camera (the capture task's kernel)", b["defects"], n["defects"])]
    for label, x, y in rows:
        lines.append(f"| {label} | {x:.1f} | {y:.1f} | {x - y:.1f} ({100 * (x - y) / max(x, 1e-9):.0f} %) |")
    lines += ["", f"Once per camera (new): `prepare_capture` {n['prepare']:.1f} ms. Frame decode (both, not in the "
              f"rows above): {result['decode_ms']:.1f} ms per frame; the capture task decodes "
              f"{result['defect_frames_read']} frames per camera.", "",
              f"Plain flow (`deflection_stage` without the capture corrections and without defective pixels, "
              f"new code, timed in the same loop): {result['plain_flow_ms']:.1f} ms per camera-frame.", ""]
    d = result["differences"]
    lines += ["Outputs, new against base, over the timed camera-frames:", "",
              f"* flow: largest difference {d['flow_max_px']:.3g} px, RMS {d['flow_rms_px']:.3g} px;",
              f"* motion: largest displacement of the difference {d['motion_max_px']:.3g} px; gain {d['gain_max']:.3g},"
              f" offset {d['offset_max']:.3g} grey levels; residual motion {d['residual_max_px']:.3g} px;",
              f"* flags: {d['flags_differ']} camera-frames differ (base {d['base_flags']}, new {d['new_flags']});",
              f"* defective pixels: maps identical **{result['defects_identical']}**.", ""]
    if result.get("profile_new"):
        lines += ["Top functions of the new `corrected_deflection` by own time (cProfile):", "",
                  "| function | own ms per camera-frame | share |", "| --- | ---: | ---: |"]
        for r in result["profile_new"]:
            lines.append(f"| `{r['function']}` | {r['own_ms_per_frame']:.2f} | {100 * r['share']:.1f} % |")
        lines.append("")
    (RESULTS / f"{name}.md").write_text("\n".join(lines) + "\n")


def time_defects(sess, cfg, cams, base: Variant, new: Variant, args):
    """Each camera's capture-task kernel, base and new alternating; the cameras' inputs of the
    deflection kernel, the decode's CPU per frame, and whether the maps agree."""
    setups, decode, identical = {}, [], True
    for c in cams:
        fp, ref, static, reader, frames, dec = camera_setup(sess, cfg, c)
        decode.append(dec)
        maps = {}
        if c == cams[0]:  # warm: numba, the allocator
            for v in (base, new):
                v.defects(c, frames, cfg.capture)
                v.cpu["defects"], v.n["defects"] = 0.0, 0
        for rep in range(args.repeats):
            for v in ((new, base) if rep % 2 == 0 else (base, new)):
                maps[v.name] = v.defects(c, frames, cfg.capture)
        identical &= bool(np.array_equal(maps["base"], maps["new"]))
        first, last = sess.frames
        imgs = {f: reader.read(f) for f in list(range(first, last))[:args.frames]}
        setups[c] = (fp, ref, static, maps["new"], imgs)
    return setups, decode, identical


def time_deflection(cfg, cams, setups, base: Variant, new: Variant, flowmod, repeats: int) -> float:
    """The deflection kernel of every camera-frame, base and new alternating, and the plain
    flow in the same loop (its CPU ms per camera-frame is returned)."""
    for v in (base, new):  # warm: numba, the prepared references; then restart the clocks
        c = cams[0]
        fp, ref, static, defects, imgs = setups[c]
        f = next(iter(imgs))
        v.deflection(c, f, imgs[f], ref, fp, cfg, static, defects)
        v.cpu["deflection"], v.n["deflection"] = 0.0, 0
    plain, k = 0.0, 0
    for rep in range(repeats):
        for c in cams:
            fp, ref, static, defects, imgs = setups[c]
            for f, img in imgs.items():
                for v in ((new, base) if rep % 2 == 0 else (base, new)):
                    v.deflection(c, f, img, ref, fp, cfg, static, defects)
                c0 = time.process_time()  # the flow alone, without the corrections
                flowmod.deflection_stage(new.prep[c], img, fp)
                plain += time.process_time() - c0
                k += 1
    return 1e3 * plain / k


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, default=DEFAULT_SESSION)
    ap.add_argument("--cameras", type=int, default=4, help="cameras timed (spread over the rig)")
    ap.add_argument("--frames", type=int, default=4, help="capture frames per camera")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--baseline", default=DEFAULT_BASELINE, help="git revision of the 'base' code")
    ap.add_argument("--profile", action="store_true", help="also profile the new deflection kernel")
    ap.add_argument("--out", default="capture_speed", help="results file name (without extension)")
    args = ap.parse_args(argv)
    worker_environment()
    import cv2

    cv2.setNumThreads(1)
    from schlieren.pipeline import capture
    from schlieren.pipeline import flow as flowmod
    from schlieren.pipeline.stages import RunConfig, bind_flow_factor, bind_medium, check_config
    from schlieren.storage.session import load_session

    if args.session == DEFAULT_SESSION:
        sys.path.insert(0, str(HERE))
        from session import ensure_session

        ensure_session(DEFAULT_SESSION, cameras=16, frames=8, size=(1440, 1080))
    sess = load_session(args.session / "session.yaml")
    cfg = bind_flow_factor(bind_medium(check_config(RunConfig()), sess.medium.n_ambient), sess.cameras, sess.grid)
    C = len(sess.cameras)
    cams = sorted(set(np.linspace(0, C - 1, min(args.cameras, C)).round().astype(int).tolist()))
    with tempfile.TemporaryDirectory(prefix="capture_speed_") as tmp:
        mods = load_baseline(args.baseline, Path(tmp))
        base = Variant("base", mods["base_capture"], mods["base_flow"])
        new = Variant("new", capture, flowmod)
        load_start = load_average()
        setups, decode, identical = time_defects(sess, cfg, cams, base, new, args)
        plain = time_deflection(cfg, cams, setups, base, new, flowmod, args.repeats)
        prof = None
        if args.profile:
            c = cams[0]
            fp, ref, static, defects, imgs = setups[c]
            prof = profile(new, [(c, f, img, ref, fp, cfg, static, defects) for f, img in imgs.items()])
        size = sess.cameras[cams[0]].image_size
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--", "pipeline",
                                     "workers"], capture_output=True, text=True).stdout.strip())
        # a camera's raw frames in the benchmark's session (the flash and rolling-shutter margins
        # too), over 2 workers that each prepare every camera
        raw = (len(range(*sess.frames)) + 6) // 2
        result = {"command": "python benchmarks/capture_speed.py " + " ".join(argv if argv is not None
                                                                              else sys.argv[1:]),
                  "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
                  "load_start": load_start, "load_end": load_average(), "baseline": args.baseline, "head": head,
                  "dirty": dirty, "session": _relative(args.session), "cameras": cams, "frames": args.frames,
                  "image_size": list(size), "window": setups[cams[0]][0].window,
                  "flow_factor": setups[cams[0]][0].factor, "repeats": args.repeats,
                  "base_ms": base.ms(), "new_ms": new.ms(), "decode_ms": 1e3 * float(np.mean(decode)),
                  "defect_frames_read": len(setups[cams[0]]) and 1 + cfg.capture.defect_frames,
                  "camera_frames_per_camera": raw, "plain_flow_ms": plain,
                  "differences": compare(base, new, size), "defects_identical": identical, "profile_new": prof}
    write(result, args.out)
    print((RESULTS / f"{args.out}.md").read_text())


if __name__ == "__main__":
    main()
