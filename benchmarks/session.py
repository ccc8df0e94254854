"""Whole-session throughput at paper scale (issue 17 item 4), and a model of it on N workers.

    python benchmarks/session.py [--frames 8] [--workers 2] [--skip-serial] [--skip-dask] [--no-profile]

1. Renders (once; cached in ``benchmarks/cache/``, which git ignores) a synthetic session
   with ``schlieren synth``'s machinery: 16 cameras on a half ring, 1440x1080, the
   buoyant plume, ``--frames`` processed frames (plus the sync flash frames and the
   rolling-shutter margins: 4 + N + 2 raw frames). A tiny session warms the numba caches.
2. Runs the whole pipeline into a fresh store:

   * ``serial``: ``schlieren run --serial --log`` in a child process (the reference loop);
   * ``dask-N``: ``--workers`` local single-threaded worker processes (cluster start-up
     excluded, as in benchmarks/scaling.py), with Dask's task stream recorded.

   Reported per run: wall seconds per time step, seconds per time step of each stage
   (summed over its tasks), tasks, peak RSS of each worker process (psutil, sampled every
   0.2 s; ``private`` = RSS minus file-backed pages such as the memory-mapped geometry),
   store size; for dask-N also the scheduler overhead: the workers' idle gaps between two
   tasks while the next was ready (task stream) and the CPU of this process (scheduler,
   nannies, client) per task.
3. Fits :mod:`schlieren.workers.throughput` to the receipts (dask-N's when run, else
   serial's) and predicts a 16-camera x 1000-frame capture on 2, 8, 32, 128 workers,
   naming the limiting term; the same model is checked against the measured runs.
4. Profiles one warm-started tomography frame and its integration, and one camera-frame's
   deflection and resample tasks (cProfile, in a child process on the serial store) and
   lists the top costs.

Writes ``benchmarks/results/session[SUFFIX].json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import json
import os
import platform
import pstats
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SUFFIX = [""]  # --suffix: results go to session<SUFFIX>.json / .md
PARAMS = [None]  # --params: a run-parameter file both runs use (A/B of a setting)
CACHE = HERE / "cache"
IDLE_PROBE_SECONDS = 5.0
BATCHED = 4  # --frames-per-task of the model's alternative prediction
PLAN_FRAMES = (50, 100, 200)  # frame counts whose plan compilation is timed (then extrapolated)
TARGETS = {"dask2_wall_per_step_s": 2.5, "tomo_integrate_per_frame_s": 1.0, "peak_worker_gb": 4.0}


# ---------------------------------------------------------------------------------------
# session and runs
# ---------------------------------------------------------------------------------------

def ensure_session(path: Path, *, cameras: int, frames: int, size: tuple[int, int]) -> dict:
    """Render the session into ``path`` unless a matching one is there; returns timings."""
    from schlieren.storage.session import load_session
    from schlieren.workers.synth import synthesize

    manifest = path / "session.yaml"
    if manifest.exists():
        s = load_session(manifest)
        if len(s.cameras) == cameras and tuple(s.cameras[0].image_size) == size \
                and s.frames[1] - s.frames[0] == frames:
            return {"cached": True}
        print(f"{path}: cached session does not match, rendering again", file=sys.stderr)
    shutil.rmtree(path, ignore_errors=True)
    print(f"rendering {cameras} cameras x {frames} frames at {size[0]}x{size[1]} into {path} "
          f"(once; about 20-30 s per raw frame on 2 cores)", file=sys.stderr)
    res = synthesize(path, cameras=cameras, frames=frames, size=size, phantom="plume", ring="half", seed=0)
    return {"cached": False, **{k: round(v, 1) for k, v in res.timings.items()}}


class MemorySampler:
    """Peak RSS (and RSS minus file-backed pages) of a set of processes, sampled in a thread."""

    def __init__(self, pids_fn, interval: float = 0.2):
        self.pids_fn = pids_fn
        self.interval = interval
        self.peak: dict[int, dict[str, float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        import psutil

        while not self._stop.is_set():
            for pid in self.pids_fn():
                try:
                    m = psutil.Process(pid).memory_info()
                except psutil.Error:
                    continue
                p = self.peak.setdefault(pid, {"rss": 0.0, "private": 0.0})
                p["rss"] = max(p["rss"], m.rss / 2 ** 30)
                p["private"] = max(p["private"], (m.rss - m.shared) / 2 ** 30)
            self._stop.wait(self.interval)

    @property
    def native_id(self):
        return self._thread.native_id

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def read_receipts(log: Path) -> tuple[list[dict], dict]:
    """The task receipts and the closing ``run finished`` line of a ``--log`` file."""
    receipts, finished = [], {}
    for line in log.read_text().splitlines():
        d = json.loads(line)
        if d.get("message") == "task receipt":
            receipts.append(d)
        elif d.get("message") == "run finished":
            finished = d
    return receipts, finished


def store_size(path: Path) -> dict:
    """Bytes of the store's arrays, and of its cache beside it (the memory-mapped tomography
    geometry in ``<store>.cache/``; a pre-0.2 ``<store>/_cache`` counts there too)."""
    from schlieren.storage.arrays_cache import cache_root

    total = cache = 0
    arrays: dict[str, int] = {}
    for root, _dirs, files in os.walk(path):
        n = sum((Path(root) / f).stat().st_size for f in files)
        parts = Path(root).relative_to(path).parts
        if "_cache" in parts:
            cache += n
        else:
            total += n
            if parts:
                arrays[parts[0]] = arrays.get(parts[0], 0) + n
    side = cache_root(path)
    if side.is_dir():
        cache += sum(f.stat().st_size for f in side.rglob("*") if f.is_file())
    return {"bytes": total + cache, "cache_bytes": cache, "results_bytes": total,
            "arrays_bytes": dict(sorted(arrays.items(), key=lambda kv: -kv[1]))}


def fresh_store(out: Path) -> None:
    """Remove a previous run's store and its cache (so the geometry stage is timed too)."""
    from schlieren.storage.arrays_cache import remove_cache

    remove_cache(out)
    shutil.rmtree(out, ignore_errors=True)


def run_cli_serial(session: Path, out: Path, log: Path) -> dict:
    """``schlieren run --serial --log`` in a child process; peak memory sampled from outside."""
    import psutil

    fresh_store(out)
    log.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "schlieren.workers.cli", "run", str(session), "--out", str(out), "--serial",
           "--log", str(log), "--no-progress"] + (["--params", PARAMS[0]] if PARAMS[0] else [])
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)

    def pids():
        try:
            return [proc.pid] + [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
        except psutil.Error:
            return []

    with MemorySampler(pids) as mem:
        rc = proc.wait()
    wall = time.perf_counter() - t0
    if rc != 0:
        raise SystemExit(f"serial run failed (exit {rc}): {' '.join(cmd)}")
    receipts, finished = read_receipts(log)
    peak = mem.peak.get(proc.pid, {"rss": 0.0, "private": 0.0})
    return {"receipts": receipts, "seconds": float(finished["seconds"]), "process_seconds": wall,
            "tasks": int(finished["tasks"]), "peak_gb": {"process": peak}}


def run_dask(session: Path, out: Path, log: Path, workers: int) -> dict:
    """The pipeline on a local cluster of ``workers`` processes, with its task stream."""
    import psutil
    from distributed import get_task_stream

    from schlieren.storage.session import load_session
    from schlieren.workers.cluster import ClusterOptions, open_client
    from schlieren.workers.commands.run import load_params
    from schlieren.workers.monitoring import RunLog
    from schlieren.workers.run import run_session
    from schlieren.workers.throughput import ready_gaps

    fresh_store(out)
    log.unlink(missing_ok=True)
    loaded = load_session(session)
    plans = []
    with open_client(ClusterOptions(workers=workers)) as (client, _info):
        pid_of = client.run(os.getpid)  # worker address -> pid
        me = psutil.Process()
        # the scheduler's idle CPU rate (heartbeats, monitors), to tell it from the per-task cost
        main_id = threading.main_thread().native_id
        i0 = _thread_cpu(me)
        time.sleep(IDLE_PROBE_SECONDS)
        i1 = _thread_cpu(me)
        idle_rate = sum(v - i0.get(t, 0.0) for t, v in i1.items() if t != main_id) / IDLE_PROBE_SECONDS
        with RunLog(log, session=loaded.name) as run_log, MemorySampler(lambda: list(pid_of.values())) as mem, \
                get_task_stream(client) as ts:
            cpu0 = _thread_cpu(me)
            t0 = time.perf_counter()
            summary = run_session(loaded, out, client=client, on_receipt=run_log.receipt, on_plan=plans.append,
                                  config=load_params(PARAMS[0]))
            wall = time.perf_counter() - t0
            cpu1 = _thread_cpu(me)
            run_log.finished(store=str(out), executor="dask", tasks=summary.tasks, skipped=summary.skipped,
                             seconds=round(summary.seconds, 3), failed=len(summary.failures), not_run=0)
        stream = ts.data
    # CPU of this process's threads during the run: the main thread is the client's polling
    # loop; the others (event loop, offload) run the scheduler, the nannies and the client's
    # messages; the memory sampler's own thread is left out
    per_thread = {tid: cpu1[tid] - cpu0.get(tid, 0.0) for tid in cpu1}
    main_cpu = per_thread.pop(main_id, 0.0)
    per_thread.pop(mem.native_id, None)
    cpu = sum(per_thread.values())
    if not summary.ok:
        raise SystemExit(f"dask-{workers} run failed: {summary.root_failures()}")
    spans = []
    for rec in stream:
        for ss in rec.get("startstops", ()):
            if ss.get("action") == "compute":
                spans.append((rec["key"], rec["worker"], ss["start"], ss["stop"]))
    deps = {t.key: t.deps for t in plans[0].tasks}
    gaps = sorted(ready_gaps(spans, deps))
    busy = sum(s1 - s0 for _k, _w, s0, s1 in spans)
    idle = idle_breakdown(spans, wall)
    peak = {addr: mem.peak.get(pid, {"rss": 0.0, "private": 0.0}) for addr, pid in pid_of.items()}
    return {"receipts": summary.receipts, "seconds": wall, "tasks": summary.tasks, "peak_gb": peak,
            "task_stream_busy_seconds": busy, "task_stream_records": len(spans),
            "ready_gaps": {"n": len(gaps), "mean": sum(gaps) / len(gaps) if gaps else 0.0,
                           "median": gaps[len(gaps) // 2] if gaps else 0.0,
                           "p90": gaps[int(0.9 * (len(gaps) - 1))] if gaps else 0.0,
                           "total": sum(gaps)},
            "idle_seconds": workers * wall - busy, "idle": idle,
            "scheduler_cpu_seconds": cpu, "scheduler_idle_cpu_rate": idle_rate,
            "scheduler_cpu_per_task": max(0.0, cpu - idle_rate * wall) / max(1, summary.tasks),
            "client_main_thread_cpu_seconds": main_cpu}


def idle_breakdown(spans, wall: float) -> dict:
    """Where the workers' idle time lies: before their first task (start-up, the plan and
    the first dispatch), between tasks (split by the stage that ran next: the waits that
    dependencies impose show up as long gaps before the tasks that waited), and after
    their last task (the run's tail, while other workers finish)."""
    by_worker: dict[str, list] = {}
    for key, w, s0, s1 in spans:
        by_worker.setdefault(w, []).append((s0, s1, key.split("-")[0]))
    first = min(s0 for _k, _w, s0, _s1 in spans)
    last = max(s1 for _k, _w, _s0, s1 in spans)
    before = after = 0.0
    between: dict[str, float] = {}
    for runs in by_worker.values():
        runs.sort()
        before += runs[0][0] - first
        after += last - runs[-1][1]
        for (_a0, a1, _sa), (b0, _b1, sb) in zip(runs, runs[1:]):
            if b0 > a1:
                between[sb] = between.get(sb, 0.0) + (b0 - a1)
    return {"stream_seconds": last - first, "outside_stream_seconds": wall - (last - first),
            "before_first_task": before, "after_last_task": after,
            "between_tasks_by_next_stage": dict(sorted(between.items(), key=lambda kv: -kv[1]))}


def _thread_cpu(proc) -> dict[int, float]:
    """CPU seconds (user + system) of each thread of ``proc`` by native thread id."""
    return {t.id: t.user_time + t.system_time for t in proc.threads()}


def _batching(name: str) -> str:
    return "the default batching" if name == "default" else f"--frames-per-task {name}"


def planning_seconds(cameras: int, frames_list, *, fpt, raw_margin: int, block: int) -> dict[int, float]:
    """Seconds the client takes to compile the plan and its priorities for each frame count."""
    from schlieren.workers.plan import Extents, critical_path_priorities, make_plan

    out = {}
    for f in frames_list:
        t0 = time.perf_counter()
        plan = make_plan(Extents(camera=cameras, frame=f, raw_frame=f + 2 * raw_margin, raw_offset=raw_margin,
                                 warm_start_block=block), "bench", frames_per_task=fpt)
        critical_path_priorities(plan)
        out[f] = time.perf_counter() - t0
    return out


def extrapolate_quadratic(points: dict[int, float], x: float) -> float:
    """Least-squares a + b x + c x^2 through ``points``, evaluated at ``x`` (planning grows
    with the square of the frames: window and same-frame edges are found by scanning)."""
    import numpy as np

    xs = np.array(list(points), dtype=float)
    coef = np.polyfit(xs, np.array(list(points.values())), 2)
    return float(max(0.0, np.polyval(coef, x)))


def per_stage(receipts: list[dict], field: str = "seconds") -> dict[str, float]:
    out: dict[str, float] = {}
    for r in receipts:
        out[r["stage"]] = out.get(r["stage"], 0.0) + float(r.get(field, 0.0))
    return out


# ---------------------------------------------------------------------------------------
# profile of one tomography frame (child process: the serial store's geometry is 1.7 GB)
# ---------------------------------------------------------------------------------------

def profile_tomography(store: str, frame: int, out_json: str) -> None:
    """cProfile of one warm-started tomography solve and its integration (the kernels, inputs
    read beforehand), and of one camera-frame's deflection and resample tasks (their glue,
    chunk reads and writes included: it rewrites the same bytes into the serial store)."""
    import numpy as np

    from schlieren.pipeline import poisson, tomography
    from schlieren.storage import arrays_cache
    from schlieren.storage.store import ResultStore
    from schlieren.workers import tasks
    from schlieren.workers.serial import single_threaded_kernels

    ctx = tasks.context(store, "profile")
    cfg = ctx.config
    key = tomography.content_hash(ctx.cameras, ctx.session.grid, ctx.ray_grid, cfg.tomography)
    t0 = time.perf_counter()
    geom = tomography.load_geometry(arrays_cache.load_arrays(arrays_cache.cache_dir(store, "geometry", key)))
    t_load = time.perf_counter() - t0
    st = ResultStore.open(store)
    flows = ctx.tomography_flows(frame)  # on the tomography's ray grid, as the task reads them
    hull = st.read("hull", (frame,))
    x0 = st.read("gradient", (frame - 1,)) if frame % cfg.warm_start_block else None
    grad = np.asarray(st.read("gradient", (frame,)), dtype=np.float64)
    out = {"frame": frame, "warm_started": x0 is not None, "geometry_load_seconds": t_load}
    raw_j = ctx.first_frame + frame - ctx.raw_first
    calls = (
        ("deflection (camera 0, one frame)", lambda: tasks.STAGE_TASKS["deflection"](ctx, 0, raw_j)),
        ("resample (camera 0, one frame)", lambda: tasks.STAGE_TASKS["resample"](ctx, 0, frame)),
        ("tomography", lambda: tomography.solve_gradient(geom, flows, hull, params=cfg.tomography, x0=x0)[1]),
        ("integrate", lambda: poisson.integrate(grad, hull, ctx.session.grid,
                                                r_ambient=ctx.session.medium.refractivity_ambient,
                                                params=cfg.poisson)[1]),
    )
    with single_threaded_kernels():
        for _name, call in calls:  # warm: page the geometry in, fill the per-process caches
            call()
        for name, call in calls:
            prof = cProfile.Profile()
            t0, c0 = time.perf_counter(), time.thread_time()
            prof.enable()
            info = call()
            prof.disable()
            wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
            stats = pstats.Stats(prof, stream=io.StringIO())
            rows = []
            for (fname, line, func), (_cc, ncalls, tt, ct, _callers) in stats.stats.items():
                rows.append({"function": f"{Path(fname).name}:{line}({func})", "calls": ncalls,
                             "tottime": tt, "cumtime": ct})
            rows.sort(key=lambda r: -r["tottime"])
            out[name] = {"seconds": wall, "cpu_seconds": cpu, "iterations": getattr(info, "iterations", None),
                         "top_tottime": rows[:15],
                         "top_cumtime": sorted(rows, key=lambda r: -r["cumtime"])[:15]}
    Path(out_json).write_text(json.dumps(out, indent=2, default=str))


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------

def _gb(x: float) -> str:
    return f"{x:.2f}"


def write_report(res: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"session{SUFFIX[0]}.json").write_text(json.dumps(res, indent=2))
    s = res["session"]
    F = s["frames"]
    runs = res["runs"]
    md = ["# Whole-session throughput at paper scale (benchmarks/session.py)", "",
          f"Session: {s['cameras']} cameras x {F} processed frames ({s['raw_frames']} raw) at "
          f"{s['size'][0]}x{s['size'][1]}, buoyant plume, half ring; grid {s['grid']} "
          f"({s['voxels']} voxels); rendered once into `{s['path']}` (git-ignored).", "",
          f"Command: `{res['command']}`", "",
          f"Machine: {res['machine']['cpus']} CPUs, {res['machine']['memory_gb']:.0f} GB, shared with other "
          f"sessions while this ran: load averages {res['machine']['load_before']} before, "
          f"{res['machine']['load_after']} after (anything above ~1 means other processes took the cores). "
          "**The times below are upper bounds from a noisy machine; re-run on a quiet one.**", "",
          "## Measured runs", "",
          "| run | wall s | wall s / time step | tasks | peak RSS per worker GB (private) | store GB (results + geometry cache) |",
          "| --- | ---: | ---: | ---: | --- | --- |"]
    for name, r in runs.items():
        peaks = ", ".join(f"{_gb(p['rss'])} ({_gb(p['private'])})" for p in r["peak_gb"].values())
        st = r["store"]
        md.append(f"| {name} | {r['seconds']:.1f} | {r['seconds'] / F:.2f} | {r['tasks']} | {peaks} | "
                  f"{st['bytes'] / 1e9:.2f} ({st['results_bytes'] / 1e9:.2f} + {st['cache_bytes'] / 1e9:.2f}) |")
    st = next(iter(runs.values()))["store"]
    md += ["", f"Store per time step: {st['results_bytes'] / F / 1e6:.1f} MB of results ("
           + ", ".join(f"{k} {v / F / 1e6:.1f}" for k, v in st["arrays_bytes"].items() if v / F >= 1e5)
           + f" MB; flow_raw holds F + 4 raw frames), plus the once-per-session geometry cache {st['cache_bytes'] / 1e9:.2f} GB "
           "(memory-mapped by the tomography tasks)."]
    md += ["", "Seconds per time step of each stage (summed over its tasks / processed frames; CPU of "
           "the task threads in brackets; the once-per-session geometry and sync are spread over "
           f"only {F} frames here):", "",
           "| stage | tasks | " + " | ".join(runs) + " |", "| --- | ---: |" + " ---: |" * len(runs)]
    stages = list(next(iter(runs.values()))["stage_seconds"])
    counts = res["tasks_by_stage"]
    for st in stages:
        cells = [f"{r['stage_seconds'].get(st, 0.0) / F:.3f} ({r['stage_cpu_seconds'].get(st, 0.0) / F:.3f})"
                 for r in runs.values()]
        md.append(f"| {st} | {counts.get(st, '')} | " + " | ".join(cells) + " |")
    md.append("| total | " + str(sum(counts.values())) + " | " + " | ".join(
        f"{sum(r['stage_seconds'].values()) / F:.2f} ({sum(r['stage_cpu_seconds'].values()) / F:.2f})"
        for r in runs.values()) + " |")
    dk = [k for k in runs if k.startswith("dask")]
    if dk:
        d = runs[dk[0]]
        g = d["ready_gaps"]
        md += ["", f"Scheduler overhead ({dk[0]}): the workers were idle {d['idle_seconds']:.1f} worker-seconds "
               f"of {res['session']['workers'] * d['seconds']:.1f} (task stream: {d['task_stream_busy_seconds']:.1f} s "
               f"busy); between two tasks with the next one already ready they waited {1e3 * g['mean']:.1f} ms "
               f"on average (median {1e3 * g['median']:.1f} ms, 90th percentile {1e3 * g['p90']:.1f} ms, "
               f"{g['n']} gaps, {g['total']:.2f} s in all). The scheduler's threads in this process (event loop "
               f"with the scheduler, nannies and client messages) used {d['scheduler_cpu_seconds']:.1f} s CPU; "
               f"idle, they use {d['scheduler_idle_cpu_rate']:.3f} s CPU per second (heartbeats, monitors), so "
               f"{1e3 * d['scheduler_cpu_per_task']:.1f} ms per task beyond that; the client's polling loop (main thread) "
               f"{d['client_main_thread_cpu_seconds']:.1f} s."]
        idle = d.get("idle")
        if idle:
            top = ", ".join(f"{k} {v:.1f}" for k, v in list(idle["between_tasks_by_next_stage"].items())[:5])
            md += ["", f"Where that idle time lies (worker-seconds): {idle['outside_stream_seconds']:.1f} s of the "
                   f"wall before the first task started or after the last one ended (start-up, planning, "
                   f"the store's template, the final gathering; x {res['session']['workers']} workers), "
                   f"{idle['before_first_task']:.1f} before a worker's first task once another had started, "
                   f"{idle['after_last_task']:.1f} after its last task while another still ran (the run's tail), "
                   f"and between tasks, by the stage of the task that came next: {top}."]
    t = res["targets"]
    md += ["", "## Targets (issue 17)", "", "| target | measured | model (16 x 1000 frames) | met |",
           "| --- | ---: | ---: | --- |"]
    for row in t:
        md.append(f"| {row['what']} | {row['measured']} | {row.get('model', '')} | {row['met']} |")
    m = res["model"]
    cs = m["costs"]["seconds"]
    md += ["", f"## Model: a {s['cameras']}-camera x {m['predict_frames']}-frame capture on N workers", "",
           "The model (`workers/throughput.py`, its docstring has the derivation): the threshold task is "
           "the run's one global barrier, so a run is phase A (sync, clock, deflection, "
           "resample, potential, and the geometry task), then the barrier, then phase C (mask, hull, "
           "tomography, integrate). A greedy scheduler takes between max(W/N, L) and W/N + (1 - 1/N) L for a "
           "phase of work W whose longest chain is L (Graham's bound for list scheduling), so", "",
           "    T(N) = P + W_A/N + (1-1/N) L_A  +  T_threshold  +  W_C/N + (1-1/N) L_C  +  G  +  o (tasks/N + chain tasks)",
           "    T(N) >= P + max(max(W_A'/N, L_A) + T_threshold + max(W_C/N, L_C),  W/N,  geometry + block chain,  tasks x s)", "",
           "where W = tasks x seconds per task summed over the phase's stages (seconds per task fitted to "
           "the receipts: the mean per stage; W_A' leaves out the geometry, which "
           "may run after the barrier), L_A = max(sync + clock, deflection) + resample + potential, "
           "T_threshold = cameras x frames x its seconds per summary (it pools every camera-frame's summary), "
           "L_C = mask + hull + cold solve + (B-1) warm solves + integrate (B = 4, the warm-start block), "
           "G = how long the single geometry task outlasts phases A and B, o = measured per-task overhead "
           "(mean ready gap), s = scheduler CPU per task (one scheduler process handles every task: a floor "
           "whatever N; if tasks x s exceeds the sum, T(N) = tasks x s). Assumes one core per worker, "
           "no memory-bandwidth contention, and a filesystem as fast as here; "
           "tests/workers/test_session_model.py checks the arithmetic and that greedy schedules of the real "
           "task graph fall between the bounds.", "",
           f"Fitted to the receipts of `{m['fitted_to']}` ({cs['source']['receipts']} receipts); "
           f"o = {1e3 * cs['overhead_per_task']:.1f} ms (mean ready gap; the CPU-based fit takes the median, "
           f"{1e3 * m['costs']['cpu_seconds']['overhead_per_task']:.1f} ms), "
           f"s = {1e3 * cs['scheduler_per_task']:.1f} ms per task (an upper bound: the client shares the "
           "scheduler's event loop here). "
           "Seconds per task (task wall / task CPU): "
           + ", ".join(f"{k} {v:.3f} / {m['costs']['cpu_seconds']['per_index'][k]:.3f}"
                       for k, v in cs["per_index"].items())
           + f"; tomography cold {cs['tomography_cold']:.2f} / {m['costs']['cpu_seconds']['tomography_cold']:.2f}, "
           f"warm {cs['tomography_warm']:.2f} / {m['costs']['cpu_seconds']['tomography_warm']:.2f}; "
           f"threshold {1e3 * cs['threshold_per_summary']:.3f} ms per summary.", "",
           "P, planning: the client compiles the plan (make_plan + critical-path priorities) before the first "
           "task; timed here at " + "; ".join(
               f"{_batching(k)}: " + ", ".join(f"{f} frames {t:.2f} s" for f, t in v.items())
               for k, v in m["planning_measured"].items())
           + f" and extrapolated (a + b F + c F^2) to {m['predict_frames']} frames: "
           + ", ".join(f"{v:.0f} s ({_batching(k)})" for k, v in m["planning_extrapolated"].items())
           + ". It does not shrink with N.", ""]
    for f, label in (("seconds", "task wall seconds as measured on this machine"),
                     ("cpu_seconds", "task CPU seconds: what a quiet dedicated core would take")):
        ps = m["predictions"][f]
        md += [f"Fitted to {label}:", "",
               "| N workers | predicted s | s per time step | lower bound s | limited by | tasks | "
               f"with --frames-per-task {m['batched_frames_per_task']}: s (tasks, limited by) |",
               "| ---: | ---: | ---: | ---: | --- | ---: | --- |"]
        for p, q in zip(ps, m["predictions_batched"][f]):
            md.append(f"| {p['workers']} | {p['seconds']:.0f} | {p['seconds_per_frame']:.3f} | {p['lower_bound']:.0f} | "
                      f"{p['limiting']} | {p['tasks']} | {q['seconds']:.0f} ({q['tasks']}, {q['limiting']}) |")
        md += ["", "Terms of each prediction (seconds):", "",
               "| term | " + " | ".join(f"N={p['workers']}" for p in ps) + " |",
               "| --- |" + " ---: |" * len(ps)]
        for term in ps[0]["terms"]:
            md.append(f"| {term} | " + " | ".join(f"{p['terms'][term]:.1f}" for p in ps) + " |")
        md.append("")
    p2 = next((p for p in m["predictions"]["cpu_seconds"] if p["workers"] == 2), None)
    if p2:
        work = p2["work_by_stage"]
        total = sum(work.values())
        md += [f"Where the work goes at {m['predict_frames']} frames (task CPU seconds per time step, all "
               "workers together; share of the total): "
               + ", ".join(f"{k} {v / p2['frames']:.2f} ({100 * v / total:.0f} %)"
                           for k, v in sorted(work.items(), key=lambda kv: -kv[1]) if v / total >= 0.005)
               + f"; total {total / p2['frames']:.2f} s per time step, so 2 workers need at least "
               f"{total / p2['frames'] / 2:.2f} s per time step whatever the scheduling.", ""]
    md += ["Check against the measured runs (the model on this session, with each run's own task seconds):", "",
           "| run | measured s | predicted s | lower bound s | limited by |", "| --- | ---: | ---: | ---: | --- |"]
    for c in m["checks"]:
        md.append(f"| {c['run']} | {c['measured']:.1f} | {c['seconds']:.1f} | {c['lower_bound']:.1f} | {c['limiting']} |")
    if res.get("profile"):
        pr = res["profile"]
        md += ["", f"## Profile of one frame (frame index {pr['frame']}, tomography warm-started: "
               f"{pr['warm_started']}; cProfile, single-threaded kernels as in the workers, second call)", ""]
        for name, p in pr.items():
            if not isinstance(p, dict):
                continue
            its = f", {p['iterations']} iterations" if p.get("iterations") is not None else ""
            md += [f"{name}: {p['seconds']:.2f} s under the profiler (CPU {p['cpu_seconds']:.2f} s{its}). "
                   "Top functions by own time:", "", "| function | calls | own s | cumulative s |",
                   "| --- | ---: | ---: | ---: |"]
            md += [f"| `{r['function']}` | {r['calls']} | {r['tottime']:.3f} | {r['cumtime']:.3f} |"
                   for r in p["top_tottime"][:10]]
            md.append("")
    if res.get("notes"):
        md += ["## Notes", ""] + [f"* {n}" for n in res["notes"]]
    md.append("")
    (RESULTS / f"session{SUFFIX[0]}.md").write_text("\n".join(md))
    print("\n".join(md))


# ---------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=8, help="processed frames of the rendered session")
    ap.add_argument("--workers", type=int, default=2, help="local worker processes of the Dask run")
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--size", default="1440x1080")
    ap.add_argument("--skip-serial", action="store_true", help="no serial run")
    ap.add_argument("--skip-dask", action="store_true", help="no Dask run")
    ap.add_argument("--no-profile", action="store_true", help="no cProfile of a tomography frame")
    ap.add_argument("--cache", default=str(CACHE), help="where the session and the stores go (git-ignored)")
    ap.add_argument("--predict-frames", type=int, default=1000)
    ap.add_argument("--suffix", default="", help="results go to session<SUFFIX>.json / .md (e.g. _f32)")
    ap.add_argument("--predict-workers", default="2,8,32,128")
    ap.add_argument("--params", default=None, help="run-parameter file (YAML/JSON) for both runs (A/B of a setting)")
    ap.add_argument("--profile-store", default=None, help=argparse.SUPPRESS)  # internal: child process
    ap.add_argument("--profile-frame", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--profile-out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    SUFFIX[0] = args.suffix
    PARAMS[0] = str(Path(args.params).resolve()) if args.params else None
    if args.profile_store:
        profile_tomography(args.profile_store, args.profile_frame, args.profile_out)
        return 0
    import psutil

    from schlieren.storage.session import load_session
    from schlieren.workers.run import RAW_MARGIN, default_frames_per_task
    from schlieren.workers.throughput import fit_costs, predict, task_counts

    w, h = (int(v) for v in args.size.split("x"))
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    load_before = [round(x, 2) for x in os.getloadavg()]
    session = cache / f"session-{args.cameras}x{w}x{h}-f{args.frames}"
    render = ensure_session(session, cameras=args.cameras, frames=args.frames, size=(w, h))
    warm = cache / "session-warmup"
    ensure_session(warm, cameras=2, frames=2, size=(96, 72))
    fresh_store(cache / "warmup.zarr")
    subprocess.run([sys.executable, "-m", "schlieren.workers.cli", "run", str(warm), "--out",
                    str(cache / "warmup.zarr"), "--serial", "--no-progress"], check=True)
    fresh_store(cache / "warmup.zarr")

    loaded = load_session(session)
    F = args.frames
    B = 4
    runs: dict[str, dict] = {}
    if not args.skip_serial:
        print("serial run ...", file=sys.stderr)
        runs["serial"] = run_cli_serial(session, cache / "serial.zarr", cache / "serial.jsonl")
        runs["serial"]["store"] = store_size(cache / "serial.zarr")
    if not args.skip_dask:
        name = f"dask-{args.workers}"
        print(f"{name} run ...", file=sys.stderr)
        runs[name] = run_dask(session, cache / f"{name}.zarr", cache / f"{name}.jsonl", args.workers)
        runs[name]["store"] = store_size(cache / f"{name}.zarr")
    if not runs:
        raise SystemExit("nothing to run: --skip-serial and --skip-dask")
    for r in runs.values():
        r["stage_seconds"] = per_stage(r["receipts"])
        r["stage_cpu_seconds"] = per_stage(r["receipts"], "cpu_seconds")

    from schlieren.pipeline.stages import RunConfig, bind_flow_factor
    from schlieren.storage.session import load_session

    sess = load_session(session)
    bound = bind_flow_factor(RunConfig(), sess.cameras, sess.grid)
    fpt = default_frames_per_task((w, h), bound.flow_factor)  # what the runs above used
    fit_name = f"dask-{args.workers}" if not args.skip_dask else "serial"
    kw = dict(warm_start_block=B, raw_margin=RAW_MARGIN, frames_per_task=fpt)

    def fitted(name: str, field_name: str):
        c = fit_costs(runs[name]["receipts"], cameras=args.cameras, frames=F, warm_start_block=B,
                      field_name=field_name)
        if name.startswith("dask"):
            # the mean gap includes other processes' preemptions; a quiet core is nearer the median
            gap = runs[name]["ready_gaps"]["mean" if field_name == "seconds" else "median"]
            c = c.with_overheads(gap, runs[name]["scheduler_cpu_per_task"])
        return c

    # task wall seconds as measured here, and task CPU seconds: what a quiet dedicated core takes
    costs = {f: fitted(fit_name, f) for f in ("seconds", "cpu_seconds")}
    print("timing the plan's compilation ...", file=sys.stderr)
    plan_points = {name: planning_seconds(args.cameras, PLAN_FRAMES, fpt=fpt_, raw_margin=RAW_MARGIN, block=B)
                   for name, fpt_ in (("default", fpt), (str(BATCHED), BATCHED))}
    planning = {name: extrapolate_quadratic(pts, args.predict_frames) for name, pts in plan_points.items()}
    kw = kw | {"planning": planning["default"]}
    predictions = {f: [predict(c, cameras=args.cameras, frames=args.predict_frames, workers=int(n), **kw).as_dict()
                       for n in args.predict_workers.split(",")] for f, c in costs.items()}
    # the same with BATCHED frames of one camera per task in the 2D stages: fewer tasks
    batched = {f: [predict(c, cameras=args.cameras, frames=args.predict_frames, workers=int(n),
                           **(kw | {"frames_per_task": BATCHED, "planning": planning[str(BATCHED)]})).as_dict()
                   for n in args.predict_workers.split(",")] for f, c in costs.items()}
    # the model's structure checked on each measured run, with that run's own task costs
    checks = []
    for name, r in runs.items():
        n = 1 if name == "serial" else args.workers
        p = predict(fitted(name, "seconds"), cameras=args.cameras, frames=F, workers=n,
                    **(kw | {"planning": 0.0})).as_dict()
        checks.append({"run": name, "measured": r["seconds"], **p})

    profile = None
    if not args.no_profile and "serial" in runs:
        print("profiling one tomography frame ...", file=sys.stderr)
        out_json = cache / "profile.json"
        subprocess.run([sys.executable, __file__, "--profile-store", str(cache / "serial.zarr"),
                        "--profile-frame", "1", "--profile-out", str(out_json)], check=True)
        profile = json.loads(out_json.read_text())

    # targets
    targets = []
    p2 = {f: next((p for p in ps if p["workers"] == 2), None) for f, ps in predictions.items()}
    if not args.skip_dask:
        d = runs[f"dask-{args.workers}"]
        v = d["seconds"] / F
        targets.append({"what": f"{args.workers} workers: wall s per time step <= {TARGETS['dask2_wall_per_step_s']}",
                        "measured": f"{v:.2f} ({F} frames, incl. once-per-session geometry)",
                        "model": (f"{p2['seconds']['seconds_per_frame']:.2f} (CPU-based {p2['cpu_seconds']['seconds_per_frame']:.2f})"
                                  if p2["seconds"] else ""),
                        "met": "yes" if v <= TARGETS["dask2_wall_per_step_s"] else "no"})
        peak = max(p["rss"] for p in d["peak_gb"].values())
        targets.append({"what": f"peak RSS per worker <= {TARGETS['peak_worker_gb']} GB",
                        "measured": f"{peak:.2f} GB",
                        "met": "yes" if peak <= TARGETS["peak_worker_gb"] else "no"})
    ref = runs.get("serial") or runs[fit_name]
    ti = (ref["stage_seconds"]["tomography"] + ref["stage_seconds"]["integrate"]) / F
    ti_cpu = (ref["stage_cpu_seconds"]["tomography"] + ref["stage_cpu_seconds"]["integrate"]) / F
    targets.append({"what": f"tomography + integration s per frame <= {TARGETS['tomo_integrate_per_frame_s']} "
                            f"({'serial' if 'serial' in runs else fit_name}, single-threaded kernels)",
                    "measured": f"{ti:.2f} (CPU {ti_cpu:.2f})",
                    "met": "yes" if ti <= TARGETS["tomo_integrate_per_frame_s"] else "no"})

    grid = loaded.grid
    res = {
        "command": " ".join(["python benchmarks/session.py"] + list(argv if argv is not None else sys.argv[1:])),
        "session": {"cameras": args.cameras, "frames": F, "raw_frames": loaded.n_frames_available,
                    "size": [w, h], "grid": list(grid.shape), "voxels": int(grid.shape[0] * grid.shape[1] * grid.shape[2]),
                    "path": os.path.relpath(session, HERE.parent), "render": render, "workers": args.workers,
                    "frames_per_task": fpt},
        "machine": {"cpus": os.cpu_count(), "memory_gb": psutil.virtual_memory().total / 2 ** 30,
                    "python": platform.python_version(), "load_before": load_before,
                    "load_after": [round(x, 2) for x in os.getloadavg()]},
        "tasks_by_stage": task_counts(args.cameras, F, raw_margin=RAW_MARGIN, frames_per_task=fpt),
        "runs": {k: {kk: vv for kk, vv in v.items() if kk != "receipts"} for k, v in runs.items()},
        "targets": targets,
        "model": {"fitted_to": fit_name, "predict_frames": args.predict_frames,
                  "costs": {f: dataclasses.asdict(c) for f, c in costs.items()},
                  "predictions": predictions, "checks": checks,
                  "batched_frames_per_task": BATCHED, "predictions_batched": batched,
                  "planning_measured": {str(k): {str(f): t for f, t in v.items()} for k, v in plan_points.items()},
                  "planning_extrapolated": {str(k): v for k, v in planning.items()}},
        "profile": profile,
        "notes": [],
    }
    write_report(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
