"""CPU of one ``deflection`` task per camera-frame at paper scale, and where it goes (issue 17).

    python benchmarks/deflection_task.py [--cameras 2] [--frames 2] [--repeats 3] [--baseline REV]

1. Renders (once; cached in ``benchmarks/cache/``, which git ignores) a synthetic session
   with ``schlieren synth``'s machinery (``benchmarks/session.py``'s ``ensure_session``):
   ``--cameras`` cameras on a half ring, 1440x1080 8-bit PNG frames, the buoyant plume;
   ``--frames`` processed frames plus the flash and rolling-shutter margins.
2. Makes two result stores for it (``prepare_store``, then the sync and clock tasks) and
   runs the deflection task path twice in this one process: with the code of the working
   tree ("new") and with ``pipeline/flow.py``, ``pipeline/frame_quality.py``,
   ``storage/frames.py`` and ``workers/tasks.py`` of ``--baseline`` ("base", loaded from
   git under other module names; everything else is shared).
3. Per camera-frame, CPU time (``time.process_time``) of the pieces of the deflection
   task (``workers/tasks/deflection.py``): the frame's decode (``FrameSource.read``),
   ``deflection_stage`` (with the camera's cached ``PreparedReference``), the frame-quality
   vector (``_frame_quality``, previous frame already read), and the two store writes
   (``flow_raw``, ``frame_quality``, flushed); then the whole task (``_GLUE["deflection"]``
   over each camera's raw frames in frame order, each frame decoded once). New and base
   alternate frame by frame, ``--repeats`` times, so load on the machine hits both alike.
4. Checks that both stores hold bit-identical ``flow_raw`` and ``frame_quality``.

The process runs as a Dask worker does: OpenCV single-threaded, and glibc's allocator with
the settings the cluster gives its workers (``workers/cluster/settings.MALLOC_ENV``; the script
re-executes itself with them). Without them every large temporary is page-faulted afresh:
about 17 ms of system CPU per task on top of what is reported here.

Writes ``benchmarks/results/deflection_task.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
CACHE = HERE / "cache"
#: The commit before the issue-17 deflection work.
DEFAULT_BASELINE = "cdc8c76"
#: Modules whose baseline version is loaded (module name -> path in the repository).
BASE_MODULES = {"flow": "pipeline/flow.py", "frame_quality": "pipeline/frame_quality.py",
                "frames": "storage/frames.py", "tasks": "workers/tasks.py"}
PIECES = ("decode", "deflection_stage", "quality", "store_write")


def worker_environment() -> None:
    """Re-execute with the Dask workers' allocator and thread settings unless already set."""
    from schlieren.workers.cluster import MALLOC_ENV, THREAD_ENV

    want = {**THREAD_ENV, **MALLOC_ENV}
    if any(os.environ.get(k) != v for k, v in want.items()):
        os.execve(sys.executable, [sys.executable, __file__, *sys.argv[1:]], {**os.environ, **want})


def load_baseline(rev: str, into: Path) -> dict:
    """The baseline's modules, imported from ``git show rev:path`` under private names."""
    mods = {}
    for name, rel in BASE_MODULES.items():
        src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{rel}"], check=True,
                             capture_output=True, text=True).stdout
        path = into / f"base_{name}.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location(f"base_{name}", path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    t = mods["tasks"]  # its glue calls the baseline's kernels and readers
    t.flowmod, t.fq = mods["flow"], mods["frame_quality"]
    t.open_frames, t.read_reference = mods["frames"].open_frames, mods["frames"].read_reference
    return mods


def package_api():
    """The working tree's task package under the names of the baseline's single module
    (``workers/tasks.py`` became the package ``workers/tasks/``)."""
    from types import SimpleNamespace

    from schlieren.pipeline import flow
    from schlieren.workers import tasks
    from schlieren.workers.tasks.deflection import quality_vector

    return SimpleNamespace(context=tasks.context, flowmod=flow, flow_params=tasks.flow_params,
                           _frame_quality=quality_vector, _GLUE=tasks.STAGE_TASKS)


def make_store(session_dir: Path, out: Path) -> str:
    """A fresh result store for the session with the sync and clock tasks done; its run token."""
    from schlieren.pipeline.stages import RunConfig, bind_flow_factor, bind_medium, check_config
    from schlieren.storage.session import load_session
    from schlieren.workers import tasks
    from schlieren.workers.run import prepare_store

    shutil.rmtree(out, ignore_errors=True)
    session = load_session(session_dir)
    cfg = bind_flow_factor(bind_medium(check_config(RunConfig()), session.medium.n_ambient),
                           session.cameras, session.grid)
    _, _, token = prepare_store(session, out, cfg)
    for c in range(len(session.cameras)):
        tasks.run_task(str(out), "sync", (c,), run_token=token)
    tasks.run_task(str(out), "clock", (), run_token=token)
    return token


class Variant:
    """One version of the task path on its own store and run context."""

    def __init__(self, name: str, tasks, store: Path, token: str):
        self.name, self.tasks = name, tasks
        self.ctx = tasks.context(str(store), token)
        self.flow = tasks.flowmod
        self.cpu = {k: 0.0 for k in PIECES}
        self.task_cpu = 0.0
        self.n = self.n_tasks = 0

    def pieces(self, c: int, j: int) -> None:
        """Time the pieces of ``_deflection`` for raw frame ``j`` of camera ``c``."""
        ctx, t = self.ctx, self.tasks
        f = ctx.raw_first + j
        src = ctx.frames(c)
        prev = src.read(f - 1) if f > 0 else None
        prep = ctx.prepared_reference(c, None)
        params = t.flow_params(ctx, c)
        c0 = time.process_time()
        img = src.read(f)
        c1 = time.process_time()
        d = self.flow.deflection_stage(prep, img, params)
        c2 = time.process_time()
        ctx._small[("frames", c)] = {f: img} if prev is None else {f - 1: prev, f: img}
        c3 = time.process_time()
        q = t._frame_quality(ctx, c, f, img)
        c4 = time.process_time()
        ctx.store.write("flow_raw", (c, j), d.astype(np.float32))
        ctx.store.write("frame_quality", (c, j), q)
        ctx.store.flush()
        c5 = time.process_time()
        for k, dt in zip(PIECES, (c1 - c0, c2 - c1, c4 - c3, c5 - c4)):
            self.cpu[k] += dt
        self.n += 1

    def camera_tasks(self, c: int, js) -> None:
        """The whole task, over camera ``c``'s raw frames in frame order (fresh frame cache);
        margin frames no output instant needs (cheap: flagged unused) are not counted."""
        self.ctx._small.pop(("frames", c), None)
        for j in js:
            c0 = time.process_time()
            out = self.tasks._GLUE["deflection"](self.ctx, c, j)
            self.ctx.store.flush()
            if not out.get("unused"):
                self.task_cpu += time.process_time() - c0
                self.n_tasks += 1

    def summary(self) -> dict:
        ms = {k: 1e3 * v / max(self.n, 1) for k, v in self.cpu.items()}
        ms["sum_of_pieces"] = sum(ms[k] for k in PIECES)
        ms["whole_task"] = 1e3 * self.task_cpu / max(self.n_tasks, 1)
        return {"cpu_ms_per_camera_frame": ms, "camera_frames_timed": self.n, "tasks_timed": self.n_tasks}


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and bool(np.array_equal(a.view(np.uint8), b.view(np.uint8)))


def profile_new(v: Variant, c: int, js) -> list:
    """cProfile of the new task path over camera ``c``'s frames: the tasks that computed a
    flow, and the top functions by own time per such task."""
    import cProfile
    import pstats

    v.ctx._small.pop(("frames", c), None)
    st, n = None, 0
    for j in js:
        pr = cProfile.Profile()
        pr.enable()
        out = v.tasks._GLUE["deflection"](v.ctx, c, j)
        v.ctx.store.flush()
        pr.disable()
        if not out.get("unused"):
            n += 1
            st = pstats.Stats(pr) if st is None else st.add(pr)
    total = sum(row[2] for row in st.stats.values())
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:15]
    return n, [{"function": f"{Path(fn).name}:{line}({name})" if fn != "~" else name,
                "calls_per_task": s[1] / n, "own_ms_per_task": 1e3 * s[2] / n, "share": s[2] / total}
               for (fn, line, name), s in rows]


def load_average() -> list:
    try:
        return [round(float(x), 2) for x in os.getloadavg()]
    except OSError:
        return []


def write(result: dict) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "deflection_task.json").write_text(json.dumps(result, indent=2))
    b, n = (result[k]["cpu_ms_per_camera_frame"] for k in ("base", "new"))
    lines = ["# Deflection task: CPU per camera-frame (benchmarks/deflection_task.py)", "",
             f"Machine: {result['machine']}; load average at start / end {result['load_start']} / "
             f"{result['load_end']} (shared machine: CPU time, base and new alternating in one "
             "process). OpenCV single-threaded, glibc allocator as in the Dask workers.", "",
             f"Session: {result['cameras']} cameras x {result['raw_frames']} raw frames, "
             f"{result['image_size'][0]}x{result['image_size'][1]} 8-bit PNG, flow window "
             f"{result['window']} px, factor {result['flow_factor']}; {result['repeats']} repeats. "
             f"Base = `{result['baseline']}`, new = `{result['head']}`"
             f"{' + uncommitted changes' if result['dirty'] else ''}.", "",
             "| CPU ms per camera-frame | base | new | saved |", "| --- | ---: | ---: | ---: |"]
    names = {"decode": "frame decode (PNG -> float32)", "deflection_stage": "deflection_stage",
             "quality": "frame-quality flags", "store_write": "store writes (flow_raw, frame_quality)",
             "sum_of_pieces": "sum of the pieces", "whole_task": "whole task (`_deflection`, frame order)"}
    for k, label in names.items():
        lines.append(f"| {label} | {b[k]:.2f} | {n[k]:.2f} | {b[k] - n[k]:.2f} ({100 * (b[k] - n[k]) / b[k]:.0f} %) |")
    lines += ["", f"Stored `flow_raw` and `frame_quality` of the two stores bit-identical: "
              f"**{result['bit_identical']}** ({result['camera_frames_compared']} camera-frames).", "",
              f"Top functions of the new task path by own time (cProfile, camera 0's {result['profile_tasks']} "
              "tasks that computed a flow; the unused margin frames' tasks are left out of the task rows):", "",
              "| function | calls per task | own ms per task | share |", "| --- | ---: | ---: | ---: |"]
    for r in result["profile_new"]:
        lines.append(f"| `{r['function']}` | {r['calls_per_task']:.1f} | "
                     f"{r['own_ms_per_task']:.2f} | {100 * r['share']:.1f} % |")
    lines += ["", "Notes (issue 17):", "",
              "* The numbers above are for a worker's allocator settings. In a process without them "
              "(the serial loop, `schlieren run --serial`) the same task also spends about 17 ms of "
              "system CPU page-faulting fresh temporaries (about 10,000 minor faults per task).",
              "* In frame order each frame is decoded once. With 2 frames per deflection task (the "
              "default at 1440x1080) the first frame of a task compares itself with the frame before "
              "it, which the worker has not read unless it ran that camera's previous task just before: "
              "then one more PNG decode (about 9 ms) per task.",
              "* Tried without a gain, not kept: fusing the LK residual with the per-cell moments "
              "(bit-identical, 0.5 ms of 11 ms saved), the cell moments accumulated across a row "
              "(bit-identical, twice as slow), a (W, 4) layout of the B-spline weights (no change), "
              "Pillow instead of cv2.imread for the PNG decode (the same 9 ms: zlib and the PNG "
              "filters).", ""]
    (RESULTS / "deflection_task.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=2)
    ap.add_argument("--frames", type=int, default=2, help="processed frames (plus the margins)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default=DEFAULT_BASELINE, help="git revision of the 'base' code")
    args = ap.parse_args(argv)
    worker_environment()
    import cv2

    cv2.setNumThreads(1)
    sys.path.insert(0, str(HERE))
    from session import ensure_session

    new_tasks = package_api()

    session_dir = CACHE / f"deflection_{args.cameras}cam_{args.frames}f"
    ensure_session(session_dir, cameras=args.cameras, frames=args.frames, size=(1440, 1080))
    work = Path(tempfile.mkdtemp(prefix="deflection_task_"))
    try:
        base_mods = load_baseline(args.baseline, work)
        token = make_store(session_dir, work / "new.zarr")
        shutil.copytree(work / "new.zarr", work / "base.zarr")
        new = Variant("new", new_tasks, work / "new.zarr", token)
        base = Variant("base", base_mods["tasks"], work / "base.zarr", token)
        ctx = new.ctx
        C, js = len(ctx.cameras), list(range(ctx.n_raw))
        load_start = load_average()
        for v in (new, base):  # warm: numba caches, prepared references, the reference means
            for c in range(C):
                v.pieces(c, js[-1])
        for v in (new, base):
            v.cpu = dict.fromkeys(PIECES, 0.0)
            v.n = 0
        for rep in range(args.repeats):
            order = (new, base) if rep % 2 == 0 else (base, new)
            for c in range(C):
                for j in js:
                    for v in order:
                        v.pieces(c, j)
                for v in order:
                    v.camera_tasks(c, js)
        identical = True
        for name in ("flow_raw", "frame_quality"):
            for c in range(C):
                for j in js:
                    identical &= same_bits(new.ctx.store.read(name, (c, j)), base.ctx.store.read(name, (c, j)))
        n_prof, prof = profile_new(new, 0, js)
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--"]
                                    + ["pipeline/flow", "pipeline/frame_quality.py", "storage/frames.py", "storage/readers",
                                       "workers/tasks"], capture_output=True, text=True).stdout.strip())
        params = new_tasks.flow_params(ctx, 0)
        result = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
                  "load_start": load_start, "load_end": load_average(), "baseline": args.baseline,
                  "head": head, "dirty": dirty, "cameras": C, "raw_frames": len(js),
                  "image_size": list(ctx.cameras[0].image_size), "window": params.window,
                  "flow_factor": params.factor, "repeats": args.repeats,
                  "base": base.summary(), "new": new.summary(), "bit_identical": bool(identical),
                  "camera_frames_compared": C * len(js), "profile_new": prof, "profile_tasks": n_prof}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    write(result)
    print((RESULTS / "deflection_task.md").read_text())
    if not identical:
        sys.exit("the stored flow or frame quality differs from the baseline's")


if __name__ == "__main__":
    main()
