"""Accuracy and throughput of the BOS deflection kernels (paper sec. 4, issue 4).

Data: synthetic captures from the project's renderer (``pipeline.synthetic``): cameras of
a half ring at 1440x1080 (``make_rig``), Wavelet Noise backgrounds (``make_background``,
finest spacing 1.5 camera pixels as ``schlieren synth`` uses), rays traced through the
phantom at each row's rolling-shutter time, pixel-area supersampled rendering, sensor noise
1.5 grey levels, 8-bit quantisation. Truth = the renderer's per-pixel mean deflection,
area-averaged to the flow grid (factor 3). "Inside the plume" = cells where the true
deflection exceeds 0.02 px.

Phantoms: ``tealights`` (three laminar plumes, peak deflection ~1.8 px), ``plume``
(buoyant smoke simulation: finer structure, up to ~3 px) and ``tealights_1px`` (the issue's
regime, deflections 0.05-1 px: the same tea-light plumes with the flame-tip temperature
lowered from 560 K to 400 K (``tealight_plumes(source_temperature=400.0)``), which scales
the peak deflection to ~1 px).

Reference images: "noisy" = one frame with 1.5 grey levels of noise like the data
(worst case); "clean" = noise-free, as ``schlieren synth`` writes it (a reference is an
average of many frames in practice, SPEC).

Rows: dense pyramidal LK (default ``FlowParams``; the same with the symmetric gradient; the
defaults before issue 4's accuracy work: 13 px box window, presmooth 0.8, flow smoothing
1 px, no texture correction, no adaptive smoothing), LK on 3x area-downsampled images (flow x 3, box window 5 ~ 13 / 3,
presmooth 0.8), Horn-Schunck, OpenCV DIS (8-bit), classic window
cross-correlation (32 px top-hat windows, 50 % overlap, 3-point Gaussian peak fit) and a
tuned correlation (Hann taper, 75 % overlap); both correlations keep the post-processing
they had before issue 4 (normalised median test, 1 px Gaussian smoothing, no adaptive
smoothing).

Throughput of ``deflection_stage`` (LK, 1440x1080 -> 360x480 flow grid) with the camera's
``PreparedReference`` cached (per worker process, as one task per camera-frame does):
(a) one process with ``cv2.setNumThreads(2)``; (b) CPU time per frame single-threaded;
(c) two single-threaded worker processes in parallel (the deployment: Dask workers with
one thread each) -> camera-frames per second per machine; (d) two threads of one process
(the numba kernels release the GIL, as OpenCV does).

Run: ``/work/main/.venv/bin/python benchmarks/flow.py [--quick]``; writes
``benchmarks/results/flow.json`` and ``flow.md``.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import os
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from schlieren.pipeline import flow as F
from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.synthetic import render as R
from schlieren.pipeline.synthetic.background import make_background, wavelet_noise_tile
from schlieren.pipeline.synthetic.phantoms import make_phantom, tealight_plumes
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.synthetic.tracer import active_box, field_stack

RESULTS = Path(__file__).resolve().parent / "results"
BOX = ((-0.075, -0.075, 0.0), (0.075, 0.075, 0.30))
FRAME_RATE = 60.0
LINE_TIME = 1.54e-5
NOISE = 1.5
FACTOR = 3
TEALIGHTS_1PX_TEMPERATURE = 400.0  # K at the flame tip (make_phantom's tealights: 560 K)
SYMMETRIC = F.FlowParams(gradient="symmetric")
# correlation baselines keep the post-processing they were benchmarked with before issue 4
# (median test, 1 px Gaussian smoothing; no adaptive smoothing)
CORR = F.FlowParams(method="correlation", smoothing_sigma=1.0, adaptive_sigma=0.0)
OLD_DEFAULTS = F.FlowParams(window=13, window_type="box", presmooth=0.8, smoothing_sigma=1.0,
                            adaptive_sigma=0.0, texture_correction=False)
log = logging.getLogger("bench.flow")


class Scene:
    """A rendered synthetic capture: phantom, rig, backgrounds, reference images."""

    def __init__(self, kind: str, *, n_cameras: int = 2, offsets=None, t_start: float = -0.05,
                 duration: float = 0.35, seed: int = 0, image_size=(1440, 1080)):
        self.kind = kind
        self.grid = Grid(*BOX, 0.0025)
        self.fine = Grid(*BOX, 0.00125)
        if kind == "tealights_1px":  # the issue's regime: peak deflection ~1 px
            knot_dt = 1.0 / 240.0
            kt = t_start + knot_dt * np.arange(int(np.ceil(duration / knot_dt - 1e-9)) + 1)
            self.phantom = tealight_plumes(self.fine, knot_times=kt, seed=seed,
                                           source_temperature=TEALIGHTS_1PX_TEMPERATURE)
        else:
            self.phantom = make_phantom(kind, self.fine, t_start=t_start, duration=duration,
                                        seed=seed, knot_dt=1.0 / 240.0)
        rig = make_rig(n_cameras, grid=self.grid, image_size=image_size, line_time=LINE_TIME, seed=seed)
        if offsets is None:
            offsets = np.zeros(n_cameras)
        self.cameras = [c.with_time_offset(float(o)) for c, o in zip(rig, offsets)]
        tile = wavelet_noise_tile(256, seed=seed)
        self.backgrounds, self.references = [], []
        for i, cam in enumerate(self.cameras):
            zbg = float(np.linalg.norm(cam.center - cam.bg_point))
            bg = make_background(cam.bg_point, cam.bg_normal, spacing=1.5 * zbg / cam.K[0, 0],
                                 tile=tile, seed=seed * 1000 + i + 1)
            self.backgrounds.append(bg)
            self.references.append(R.reference_image(cam, bg, supersample=3, stride=FACTOR))
        self.lattice = R.make_lattice(self.cameras[0].image_size, FACTOR)
        self.flow_grid = FlowGrid(self.cameras[0].image_size, FACTOR)

    def _fields(self, t0, t1):
        idx = self.phantom.knots_covering(t0, t1)
        fields = field_stack([self.phantom.knot_refractivity(int(k)) for k in idx], self.fine)
        return fields, self.phantom.knot_times[idx]

    def frame(self, i: int, f: int):
        """Noise-free rolling-shutter frame ``f`` of camera ``i`` and its per-pixel deflection."""
        cam = self.cameras[i]
        t0 = cam.time_offset + f / FRAME_RATE
        fields, kt = self._fields(t0, t0 + cam.height * cam.line_time)
        tr = R.trace_lattice(cam, self.lattice, fields, kt, self.fine, frame=f, frame_rate=FRAME_RATE,
                             clip_box=active_box(fields, self.fine, tol=1e-5))
        return R.render_image(cam, self.backgrounds[i], tr, self.lattice, self.references[i])

    def global_truth(self, i: int, t: float) -> np.ndarray:
        """Global-shutter deflection of camera ``i`` at instant ``t`` on the flow grid."""
        cam = self.cameras[i]
        fields, kt = self._fields(t, t)
        tr = R.trace_lattice(cam, self.lattice, fields, kt, self.fine, frame=None, time=float(t),
                             frame_rate=FRAME_RATE, clip_box=active_box(fields, self.fine, tol=1e-5))
        _, d = R.render_image(cam, self.backgrounds[i], tr, self.lattice, self.references[i])
        return R.cell_average(d, self.flow_grid).astype(np.float32)


def sensor(img, rng, noise=NOISE):
    return R.sensor(img, noise=noise, bit_depth=8, rng=rng).astype(np.float32)


def area_down(img, f):
    H, W = img.shape
    return cv2.resize(img[: H // f * f, : W // f * f], (W // f, H // f), interpolation=cv2.INTER_AREA)


LK = "LK (default FlowParams)"
CLASSIC = "correlation 32 px, 50 % overlap (classic)"
METHODS = {
    LK: lambda r, fr: F.deflection_stage(r, fr, F.FlowParams()),
    "LK (default, gradient='symmetric')": lambda r, fr: F.deflection_stage(r, fr, SYMMETRIC),
    "LK (defaults before issue 4 work)": lambda r, fr: F.deflection_stage(r, fr, OLD_DEFAULTS),
    "LK on 3x downsampled images": lambda r, fr: F.deflection_field(
        area_down(r, FACTOR), area_down(fr, FACTOR), window=5, window_type="box",
        presmooth=0.8) * FACTOR,
    "Horn-Schunck": lambda r, fr: F.deflection_stage(r, fr, F.FlowParams(method="hs")),
    "OpenCV DIS (medium)": lambda r, fr: F.deflection_stage(r, fr, F.FlowParams(method="dis")),
    CLASSIC: lambda r, fr: F.deflection_stage(r, fr, CORR),
    "correlation 32 px, Hann, 75 % overlap": lambda r, fr: F.deflection_stage(
        r, fr, F.FlowParams(method="correlation", corr_step=8, corr_taper=True,
                            smoothing_sigma=1.0, adaptive_sigma=0.0)),
}


def accuracy(kind: str, frames, n_cameras: int, rng) -> dict:
    t0 = time.perf_counter()
    scene = Scene(kind, n_cameras=n_cameras, offsets=-np.arange(n_cameras) * 0.0031)
    log.info("%s: scene in %.1f s", kind, time.perf_counter() - t0)
    rows = {}
    stats = {"max_true_deflection_px": 0.0, "plume_fraction": []}
    for i in range(n_cameras):
        ref_clean = sensor(scene.references[i], rng, 0.0)
        ref_noisy = sensor(scene.references[i], rng)
        for f in frames:
            t0 = time.perf_counter()
            img, dpx = scene.frame(i, f)
            log.info("%s cam %d frame %d rendered in %.1f s", kind, i, f, time.perf_counter() - t0)
            frm = sensor(img, rng)
            truth = R.cell_average(dpx, scene.flow_grid)
            mag = np.linalg.norm(truth, axis=-1)
            inside = mag > 0.02
            stats["max_true_deflection_px"] = max(stats["max_true_deflection_px"], float(mag.max()))
            stats["plume_fraction"].append(float(inside.mean()))
            for refname, ref in (("noisy", ref_noisy), ("clean", ref_clean)):
                for name, fn in METHODS.items():
                    if refname == "clean" and name not in (LK, "LK (default, gradient='symmetric')",
                                                           "LK on 3x downsampled images", CLASSIC):
                        continue
                    out = fn(ref, frm)
                    err = np.linalg.norm(out - truth, axis=-1)
                    r = rows.setdefault(f"{name} | {refname} ref", {"epe_plume": [], "epe_all": [],
                                                                     "rms_plume": []})
                    r["epe_plume"].append(float(err[inside].mean()))
                    r["epe_all"].append(float(err.mean()))
                    r["rms_plume"].append(float(np.sqrt(np.mean(err[inside] ** 2))))
    summary = {k: {m: float(np.mean(v)) for m, v in r.items()} for k, r in rows.items()}
    # like with like: classic correlation and LK on the same reference (noisy or clean)
    stats["classic_correlation_over_lk"] = {
        k: summary[f"{CLASSIC} | {k.split(' | ')[1]}"]["epe_plume"] / r["epe_plume"]
        for k, r in summary.items() if k.startswith("LK (") and f"{CLASSIC} | {k.split(' | ')[1]}" in summary}
    stats["plume_fraction"] = float(np.mean(stats["plume_fraction"]))
    return {"phantom": kind, "camera_frames": n_cameras * len(frames), "stats": stats, "rows": summary}


# ---------------------------------------------------------------------------------------
# throughput
# ---------------------------------------------------------------------------------------
_JOB = {}


def _worker(n: int) -> tuple[float, float]:
    cv2.setNumThreads(1)
    prep, frames, params = _JOB["prep"], _JOB["frames"], _JOB["params"]
    F.deflection_stage(prep, frames[0], params)  # warm (JIT cache load)
    c0, w0 = time.process_time(), time.perf_counter()
    for k in range(n):
        F.deflection_stage(prep, frames[k % len(frames)], params)
    return time.process_time() - c0, time.perf_counter() - w0


def throughput(ref: np.ndarray, frames: list, n: int) -> dict:
    params = F.FlowParams()
    out = {"image_size": list(ref.shape[::-1]), "frames_timed": n}
    cv2.setNumThreads(2)
    t = time.perf_counter()
    prep = F.prepare_reference(ref, presmooth=params.presmooth, levels=params.levels)
    out["prepare_reference_ms"] = 1e3 * (time.perf_counter() - t)
    F.deflection_stage(prep, frames[0], params)
    w0 = time.perf_counter()
    for k in range(n):
        F.deflection_stage(prep, frames[k % len(frames)], params)
    wall = time.perf_counter() - w0
    out["one_process_2_threads_fps"] = n / wall
    t = time.perf_counter()
    for k in range(max(2, n // 4)):
        F.deflection_stage(ref, frames[k % len(frames)], params)
    out["one_process_2_threads_fps_without_prepared_reference"] = max(2, n // 4) / (time.perf_counter() - t)
    _JOB.update(prep=prep, frames=frames, params=params)
    cpu, wall1 = _worker(n)
    out["single_thread_cpu_ms_per_frame"] = 1e3 * cpu / n
    acc = SYMMETRIC
    _JOB.update(prep=F.prepare_reference(ref, presmooth=acc.presmooth, levels=acc.levels), params=acc)
    cpu_acc, _ = _worker(max(2, n // 2))
    out["symmetric_single_thread_cpu_ms_per_frame"] = 1e3 * cpu_acc / max(2, n // 2)
    _JOB.update(prep=F.prepare_reference(ref, presmooth=OLD_DEFAULTS.presmooth, levels=OLD_DEFAULTS.levels),
                params=OLD_DEFAULTS)
    cpu_old, _ = _worker(max(2, n // 2))
    out["old_defaults_single_thread_cpu_ms_per_frame"] = 1e3 * cpu_old / max(2, n // 2)
    _JOB.update(prep=prep, params=params)
    out["single_thread_wall_ms_per_frame"] = 1e3 * wall1 / n
    out["machine_fps_estimate_from_cpu_time"] = 2 * n / cpu
    cv2.setNumThreads(1)
    with ThreadPoolExecutor(2) as ex:  # kernels release the GIL (numba nogil, OpenCV)
        list(ex.map(_worker, [1, 1]))
        w0 = time.perf_counter()
        list(ex.map(_worker, [n, n]))
        out["one_process_two_worker_threads_fps"] = 2 * n / (time.perf_counter() - w0)
    ctx = mp.get_context("fork")
    with ctx.Pool(2) as pool:
        pool.map(_worker, [1, 1])  # warm the workers
        w0 = time.perf_counter()
        res = pool.map(_worker, [n, n])
        wall = time.perf_counter() - w0
    out["two_worker_processes_fps"] = 2 * n / wall
    out["two_worker_processes_cpu_ms_per_frame"] = 1e3 * float(np.mean([c for c, _ in res])) / n
    cv2.setNumThreads(2)
    return out


def load_average() -> list:
    try:
        return [float(x) for x in os.getloadavg()]
    except OSError:
        return []


def write(result: dict) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "flow.json").write_text(json.dumps(result, indent=2))
    lines = ["# Deflection kernels: accuracy and throughput (benchmarks/flow.py)", "",
             f"Machine: {result['machine']}. Load average at start / end: "
             f"{result['load_start']} / {result['load_end']} (**shared machine: timings under "
             "contention; re-run on an idle machine**).", ""]
    for acc in result["accuracy"]:
        st = acc["stats"]
        lines += [f"## Accuracy, phantom `{acc['phantom']}` ({acc['camera_frames']} camera-frames, "
                  f"1440x1080, noise {NOISE} grey levels, 8-bit; max true deflection "
                  f"{st['max_true_deflection_px']:.2f} px; plume = {100 * st['plume_fraction']:.1f} % "
                  "of the cells)", "",
                  "| method | reference | EPE in plume (px) | RMS in plume (px) | EPE all cells (px) |",
                  "| --- | --- | --- | --- | --- |"]
        for k, r in acc["rows"].items():
            name, ref = k.split(" | ")
            lines.append(f"| {name} | {ref.replace(' ref', '')} | {r['epe_plume']:.4f} | "
                         f"{r['rms_plume']:.4f} | {r['epe_all']:.4f} |")
        lines += ["", "Classic correlation EPE in plume / LK EPE in plume, both with the same reference "
                  "(issue 4 target: >= 4):", ""]
        for k, ratio in st["classic_correlation_over_lk"].items():
            name, ref = k.split(" | ")
            lines.append(f"* {name}, {ref}: {ratio:.1f}x")
        lines.append("")
    tp = result["throughput"]
    lines += ["## LK throughput (`deflection_stage`, 1440x1080 -> 480x360 flow grid)", "",
              "| setting | value |", "| --- | --- |",
              f"| one process, cv2.setNumThreads(2) | {tp['one_process_2_threads_fps']:.1f} camera-frames/s |",
              f"| same, without the cached PreparedReference | "
              f"{tp['one_process_2_threads_fps_without_prepared_reference']:.1f} camera-frames/s |",
              f"| single thread: CPU time per frame | {tp['single_thread_cpu_ms_per_frame']:.1f} ms |",
              f"| single thread: wall time per frame | {tp['single_thread_wall_ms_per_frame']:.1f} ms |",
              f"| defaults before issue 4 work, single thread: CPU time per frame | "
              f"{tp['old_defaults_single_thread_cpu_ms_per_frame']:.1f} ms |",
              f"| gradient='symmetric', single thread: CPU time per frame | "
              f"{tp['symmetric_single_thread_cpu_ms_per_frame']:.1f} ms |",
              f"| 2 cores from CPU time (2 / cpu per frame) | "
              f"{tp['machine_fps_estimate_from_cpu_time']:.1f} camera-frames/s |",
              f"| one process, two worker threads (GIL released in the kernels) | "
              f"{tp['one_process_two_worker_threads_fps']:.1f} camera-frames/s |",
              f"| two single-threaded worker processes (measured wall) | "
              f"{tp['two_worker_processes_fps']:.1f} camera-frames/s |",
              f"| prepare_reference (once per camera) | {tp['prepare_reference_ms']:.1f} ms |", ""]
    (RESULTS / "flow.md").write_text("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer camera-frames")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cv2.setNumThreads(2)
    rng = np.random.default_rng(0)
    result = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
              "load_start": load_average(), "accuracy": []}
    frames = [3] if args.quick else [3, 9]
    n_cam = 1 if args.quick else 2
    for kind in ("tealights", "plume", "tealights_1px"):
        result["accuracy"].append(accuracy(kind, frames, n_cam, rng))
    # throughput on rendered tealight frames
    scene = Scene("tealights", n_cameras=1)
    ref = sensor(scene.references[0], rng)
    imgs = [sensor(scene.frame(0, f)[0], rng) for f in (2, 5)]
    result["throughput"] = throughput(ref, imgs, 10 if args.quick else 40)
    result["load_end"] = load_average()
    write(result)
    print((RESULTS / "flow.md").read_text())


if __name__ == "__main__":
    main()
