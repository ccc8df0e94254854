"""CPU seconds of the re-projection refinement's flows: the whole image against the crop.

    python benchmarks/refine_roi.py --store STORE.zarr [--frames 0,1,2] [--out results/refine_roi_CASE.json]
        [--tasks]

Reads a kept run store (``schlieren bench realistic ... --keep-stores``, or a ``schlieren run``
store of the paper-scale session) and, for each output frame asked, predicts every camera's
deflections from the stored gradient (the run's last solve) and measures each camera's refined
flows as the tomography task does (:func:`schlieren.workers.tasks.refine._camera_flow`), once
on the whole image (``refine.crop: false``) and once on the crop (``refine.crop: true``),
alternating which goes first per camera; CPU seconds by ``time.process_time`` (the machine may
be loaded), after what a worker prepares once per camera (the prepared reference and the
capture's fixed inputs) and the frames: the reader keeps the two latest frames per camera and
the refinement reads three, so each mode decodes the earliest again, as a run's later passes do. Reports per frame the CPU of both, the crops' share of the image and the largest
difference between the two flows (after the resampling to the output instant).

With ``--tasks`` it times the whole tomography task of those frames instead (CPU seconds, the
variants alternated per frame): the plain solve (``refine.passes: 0``), the store's refinement
with and without the crop, and one pass with the crop (``refine.passes: 1``). The task writes
the frame's gradient into the store: use a store of your own.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def measure(store: str, frames: list[int] | None) -> dict:
    from schlieren.pipeline.residuals import predict_flows
    from schlieren.workers.tasks import context
    from schlieren.workers.tasks import refine
    from schlieren.workers.tasks.capture import camera_capture
    from schlieren.workers.tasks.deflection import flow_params
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key
    from schlieren.workers.tasks.resample import frames_read

    ctx = context(store, "refine-roi-bench")
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    frames = list(range(ctx.n_frames)) if frames is None else frames
    rows = []
    for k in frames:
        grad = np.asarray(ctx.store.read("gradient", (k,)), np.float64)
        t0 = time.process_time()
        predicted = predict_flows(geom, ctx.cameras, grad, n_ambient=ctx.session.medium.n_ambient)
        t_predict = time.process_time() - t0
        cpu = {False: 0.0, True: 0.0}
        shares, diffs, raw = [], [], 0
        for c, cam in enumerate(ctx.cameras):
            lo, hi, _, _ = frames_read(ctx, c, k)
            raw += hi - lo + 1
            # what a worker prepares once per camera, and the frames, made before timing
            camera_capture(ctx, c, None, flow_params(ctx, c))
            for f in range(lo, hi + 1):
                ctx.frame(c, f)
            region = refine._region(ctx, predicted[c], flow_params(ctx, c), cam.image_size)
            shares.append(region.share(cam.image_size))
            out = {}
            for crop in ((False, True) if c % 2 == 0 else (True, False)):
                t0 = time.process_time()
                out[crop] = refine._camera_flow(ctx, c, k, predicted[c], crop)
                cpu[crop] += time.process_time() - t0
            ok = np.isfinite(out[False]) & np.isfinite(out[True])
            diffs.append(float(np.abs(out[False][ok] - out[True][ok]).max()) if ok.any() else 0.0)
        rows.append({"frame": k, "cpu_full": cpu[False], "cpu_crop": cpu[True], "cpu_predict": t_predict,
                     "raw_flows": raw, "share_mean": float(np.mean(shares)), "share_max": float(np.max(shares)),
                     "shares": shares, "max_diff_px": float(np.max(diffs))})
        print(f"frame {k}: full {cpu[False]:.2f} s, crop {cpu[True]:.2f} s CPU ({raw} raw flows), "
              f"crop share mean {np.mean(shares):.3f} (max {np.max(shares):.3f}), max |diff| {np.max(diffs):.2e} px",
              flush=True)
    n = len(rows)
    return {"store": store, "frames": rows,
            "mean": {key: float(np.mean([r[key] for r in rows])) for key in
                     ("cpu_full", "cpu_crop", "cpu_predict", "raw_flows", "share_mean")},
            "max_diff_px": float(max(r["max_diff_px"] for r in rows)) if n else 0.0,
            "load": list(__import__("os").getloadavg())}


TASK_VARIANTS = {"plain": {"passes": 0}, "crop": {"crop": True}, "whole": {"crop": False},
                 "one pass, crop": {"passes": 1, "crop": True}}


def time_tasks(store: str, frames: list[int] | None) -> dict:
    """CPU seconds of the tomography task of each frame under :data:`TASK_VARIANTS` (changes of
    the store's ``refine`` parameters)."""
    from schlieren.workers.tasks import context
    from schlieren.workers.tasks.tomography import tomography_task

    ctx = context(store, "refine-roi-tasks")
    variants = {name: dataclasses.replace(ctx, config=dataclasses.replace(
        ctx.config, refine=dataclasses.replace(ctx.config.refine, **change))) for name, change in TASK_VARIANTS.items()}
    frames = list(range(ctx.n_frames)) if frames is None else frames
    names = list(variants)
    tomography_task(variants["plain"], frames[0])  # once-per-process preparations
    cpu = {name: [] for name in names}
    for i, k in enumerate(frames):
        for name in names[i % len(names):] + names[:i % len(names)]:
            t0 = time.process_time()
            tomography_task(variants[name], k)
            cpu[name].append(time.process_time() - t0)
        print(f"frame {k}: " + ", ".join(f"{n} {cpu[n][-1]:.2f} s" for n in names), flush=True)
    return {"store": store, "frames": frames, "refine": dataclasses.asdict(ctx.config.refine),
            "cpu": cpu, "mean": {n: float(np.mean(v)) for n, v in cpu.items()},
            "load": list(__import__("os").getloadavg())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--frames", default=None, help="comma-separated output frames (default all)")
    ap.add_argument("--out", default=None, help="JSON to write")
    ap.add_argument("--tasks", action="store_true", help="time the tomography task's variants instead")
    a = ap.parse_args(argv)
    frames = None if a.frames is None else [int(x) for x in a.frames.split(",")]
    if a.tasks:
        res = time_tasks(a.store, frames)
        print("mean CPU per frame: " + ", ".join(f"{n} {v:.2f} s" for n, v in res["mean"].items())
              + f"; load {res['load']}")
        if a.out:
            Path(a.out).write_text(json.dumps(res, indent=1))
        return 0
    res = measure(a.store, frames)
    m = res["mean"]
    print(f"mean per frame: full {m['cpu_full']:.2f} s, crop {m['cpu_crop']:.2f} s CPU "
          f"(x{m['cpu_full'] / max(m['cpu_crop'], 1e-9):.2f}), share {m['share_mean']:.3f}; "
          f"max |diff| {res['max_diff_px']:.2e} px; load {res['load']}")
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
