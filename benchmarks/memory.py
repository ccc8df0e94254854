"""Peak memory of every kind of task, fitted per pixel, per voxel and per ray crossing.

For each configuration (cameras x image size x voxel size) a synthetic session is rendered
and reconstructed serially; then every measured task is run again, alone, by the real task
code (``workers.tasks.run_task``) in a fresh process: the process opens the run's context
(imports, session, store), its peak resident set is reset (``/proc/self/clear_refs``), the
task's marker is cleared and the task runs; the task's memory is the peak resident set
minus the resident set just before it (so a worker's first task, which also maps the
tomography geometry and compiles numba kernels, is what is measured: the worst case a
worker sees). The geometry cache's size on disk is recorded too.

Fits (non-negative least squares): per 2-D stage ``c + p * pixels``; per 3-D stage
``c + a * voxels + b * crossings + q * rays`` (integration: voxels only; ``crossings`` from
:func:`schlieren.pipeline.resources.ray_crossings`); the cache ``r * rays + x * crossings``;
the process baseline is the resident set of a process with the task code and
``distributed`` imported. The coefficients go into ``pipeline/resources.py`` (a test
checks they equal ``benchmarks/results/memory.json``), which the preflight check uses.

Run: ``.venv/bin/python benchmarks/memory.py [--quick] [--refit]``; writes
``benchmarks/results/memory.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"

STAGES_2D = {"deflection": lambda ext: (0, ext["raw_offset"]), "resample": lambda ext: (0, 0),
             "potential": lambda ext: (0, 0), "mask": lambda ext: (0, 0)}
STAGES_3D = {"geometry": lambda ext: (), "tomography": lambda ext: (0,), "integrate": lambda ext: (0,)}

#: (cameras, (width, height), voxel size in metres) on the synthetic 0.15 x 0.15 x 0.3 m box
CONFIGS = [
    (4, (192, 144), 0.010), (4, (192, 144), 0.005), (4, (384, 288), 0.010), (4, (384, 288), 0.005),
    (8, (192, 144), 0.010), (8, (192, 144), 0.005), (8, (384, 288), 0.0075), (8, (384, 288), 0.0035),
    (8, (768, 576), 0.0075), (4, (1440, 1080), 0.0100), (4, (768, 576), 0.0035), (12, (384, 288), 0.0050),
]
QUICK = [(4, (192, 144), 0.010), (4, (384, 288), 0.005), (8, (192, 144), 0.0075), (8, (384, 288), 0.0035)]

CHILD = r"""
import json, sys, os
def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
store, stage, index = sys.argv[1], sys.argv[2], tuple(json.loads(sys.argv[3]))
import distributed  # a Dask worker process has it loaded
from schlieren.workers import tasks
ctx = tasks.context(store)
from schlieren.workers.serial import single_threaded_kernels
base = status("VmRSS")
if stage == "geometry":  # the stage builds the cache only if it is not there
    from schlieren.storage.arrays_cache import remove_cache
    remove_cache(store)
with single_threaded_kernels():
    ctx.store.unmark(stage, index)
    before = status("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset the peak resident set (VmHWM) to the current one
    tasks.run_task(store, stage, index)
    peak = status("VmHWM")
print(json.dumps({"process": base, "before": before, "peak": peak}))
"""


def _du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def measure_config(cams: int, size, voxel: float, work: Path) -> dict:
    from schlieren.pipeline.geometry import FlowGrid
    from schlieren.pipeline.resources import ray_crossings
    from schlieren.storage.arrays_cache import cache_root
    from schlieren.storage.session import load_session
    from schlieren.workers.run import run_session
    from schlieren.workers.synth import synthesize

    tag = f"c{cams}_{size[0]}x{size[1]}_v{voxel}"
    res = synthesize(work / tag / "session", cameras=cams, ring="half", phantom="plume", frames=2, size=size,
                     seed=5, recon_voxel=voxel, supersample=2)
    store = work / tag / "store.zarr"
    t0 = time.time()
    summary = run_session(res.session, store, serial=True)
    assert summary.ok, summary.failures
    seconds = time.time() - t0
    session = load_session(res.session)
    fg = FlowGrid(session.cameras[0].image_size, 3)
    crossings, rays = ray_crossings(session.cameras, session.grid, fg)
    import zarr

    from schlieren.storage.store import decode_attrs

    attrs = decode_attrs(zarr.open_group(store, mode="r").attrs)
    ext = {"raw_offset": int(attrs["run"]["frames"][0]) - int(attrs["run"]["raw_first"])}
    row = {"cameras": cams, "image": list(size), "voxel_size": voxel, "pixels": size[0] * size[1],
           "voxels": int(np.prod(session.grid.shape)), "grid_zyx": list(session.grid.shape), "rays": int(rays),
           "crossings": float(crossings), "cache_bytes": _du(cache_root(store)), "run_seconds": seconds,
           "tasks": {}}
    for stage, index in {**STAGES_2D, **STAGES_3D}.items():
        out = subprocess.run([sys.executable, "-c", CHILD, str(store), stage, json.dumps(list(index(ext)))],
                             capture_output=True, text=True, check=True)
        got = json.loads(out.stdout.strip().splitlines()[-1])
        row["tasks"][stage] = {"bytes": got["peak"] - got["before"], "process": got["process"]}
    print(f"{tag}: " + ", ".join(f"{s} {v['bytes'] / 2**20:.1f} MiB" for s, v in row["tasks"].items()),
          flush=True)
    return row


def _nnls(columns: list[np.ndarray], y: np.ndarray) -> list[float]:
    from scipy.optimize import nnls

    A = np.stack(columns, axis=1).astype(np.float64)
    scale = np.abs(A).max(axis=0)
    scale[scale == 0] = 1.0
    coef, _ = nnls(A / scale, y.astype(np.float64))
    return [float(c) for c in coef / scale]


def fit(rows: list[dict]) -> dict:
    pix = np.array([r["pixels"] for r in rows], float)
    vox = np.array([r["voxels"] for r in rows], float)
    cross = np.array([r["crossings"] for r in rows], float)
    one = np.ones(len(rows))
    model = {"pixel_model": {}, "task_model": {}}
    for s in STAGES_2D:
        y = np.array([r["tasks"][s]["bytes"] for r in rows], float)
        model["pixel_model"][s] = _nnls([one, pix], y)
    rays = np.array([r["rays"] for r in rows], float)
    for s in STAGES_3D:
        y = np.array([r["tasks"][s]["bytes"] for r in rows], float)
        if s == "integrate":  # Poisson integration never sees the rays
            c, a = _nnls([one, vox], y)
            model["task_model"][s] = [c, a, 0.0, 0.0]
        else:
            model["task_model"][s] = _nnls([one, vox, cross, rays], y)
    model["cache_model"] = _nnls([rays, cross], np.array([r["cache_bytes"] for r in rows], float))
    model["process_bytes"] = float(max(v["process"] for r in rows for v in r["tasks"].values()))
    # how well the fit predicts each measurement (the preflight's error)
    for r in rows:
        r["predicted"] = {}
        for s, (c, p) in model["pixel_model"].items():
            r["predicted"][s] = c + p * r["pixels"]
        for s, (c, a, b, q) in model["task_model"].items():
            r["predicted"][s] = c + a * r["voxels"] + b * r["crossings"] + q * r["rays"]
    # the largest under-estimate over every measurement: the preflight multiplies by it
    model["margin"] = float(max(r["tasks"][s]["bytes"] / r["predicted"][s] for r in rows for s in r["predicted"]))
    return model


def write(rows: list[dict], model: dict, quick: bool) -> None:
    RESULTS.mkdir(exist_ok=True)
    meta = {"machine": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "quick": quick, "command": "python benchmarks/memory.py" + (" --quick" if quick else "")}
    (RESULTS / "memory.json").write_text(json.dumps({"meta": meta, "model": model, "rows": rows}, indent=2))
    mib = 2.0 ** 20
    lines = ["# Peak memory per task (benchmarks/memory.py)", "",
             "Each task run alone by the real task code in a fresh process (its first task: geometry "
             "mapped, numba kernels compiled); peak resident set minus the resident set before it.", "",
             "| cameras | image | voxel (m) | voxels | rays | crossings | " + " | ".join(
                 [*STAGES_2D, *STAGES_3D]) + " | cache |",
             "|" + " --- |" * (7 + len(STAGES_2D) + len(STAGES_3D))]
    for r in rows:
        cells = [f"{r['tasks'][s]['bytes'] / mib:.1f} ({r['predicted'][s] / mib:.1f})" for s in [*STAGES_2D, *STAGES_3D]]
        lines.append(f"| {r['cameras']} | {r['image'][0]}x{r['image'][1]} | {r['voxel_size']} | {r['voxels']} | "
                     f"{r['rays']} | {r['crossings']:.3g} | " + " | ".join(cells) + f" | {r['cache_bytes'] / mib:.1f} |")
    lines += ["", "MiB measured (fitted model in parentheses).", "", "## Fitted model (pipeline/resources.py)", "",
              "| stage | bytes | per pixel | per voxel | per crossing | per ray |",
             "| --- | --- | --- | --- | --- | --- |"]
    for s, (c, p) in model["pixel_model"].items():
        lines.append(f"| {s} | {c / mib:.1f} MiB | {p:.1f} | | | |")
    for s, (c, a, b, q) in model["task_model"].items():
        lines.append(f"| {s} | {c / mib:.1f} MiB | | {a:.1f} | {b:.1f} | {q:.1f} |")
    r, x = model["cache_model"]
    lines += ["", f"The preflight multiplies every task's model by {model['margin']:.3f}, the largest "
              "under-estimate of a measurement above.",
              "", f"Geometry cache on disk: {r:.1f} bytes per flow-grid ray + {x:.1f} bytes per crossing. "
              f"Worker process baseline (task code and distributed imported): "
              f"{model['process_bytes'] / mib:.0f} MiB.", "", f"Machine: {meta['machine']}, {meta['cpus']} CPUs. "
              f"Command: `{meta['command']}`."]
    (RESULTS / "memory.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="four configurations instead of twelve")
    ap.add_argument("--workdir", default=None, help="keep the sessions and stores here")
    ap.add_argument("--refit", action="store_true",
                    help="fit the model again to the measurements in results/memory.json (no new runs)")
    args = ap.parse_args(argv)
    if args.refit:
        old = json.loads((RESULTS / "memory.json").read_text())
        rows, quick = old["rows"], old["meta"]["quick"]
    else:
        quick = args.quick
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(args.workdir or tmp)
            rows = [measure_config(c, s, v, work) for c, s, v in (QUICK if args.quick else CONFIGS)]
    model = fit(rows)
    write(rows, model, quick)
    print(json.dumps(model, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
