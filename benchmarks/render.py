"""Render time of one raw frame of 16 cameras at 1440x1080 of the buoyant plume (issue 3).

Setup (not timed as "frame"): the smoke simulation, the rig (16 cameras, half ring), the
Wavelet Noise backgrounds and the 16 noise-free reference images (rendered once per camera
and reused by every frame; timed separately). Numba kernels are compiled (and cached)
before timing.

Timed, for one raw frame (rolling shutter, every lattice row at its own time):

* ``fields``: refractivity + gradient of the phantom's time knots that the frame's rows span
  (all cameras share them);
* ``trace``: RK4 through the phantom for the lattice rays (stride 3 px) that cross the active
  part of the volume, per camera;
* ``render``: supersampled (3x3) pixel-area rendering of the region the flow touches;
* ``sensor``: noise + 8-bit quantisation;
* total = fields + trace + render + sensor (the issue's target: <= 60 s on 2 cores);
* separately: PNG encoding, and the ground-truth traces of one output instant
  (global-shutter d_out + area-mean deflection) which ``schlieren synth`` adds per frame.

Also measured: the error of the lattice interpolation (stride 3) against rays traced at
every pixel centre, on a band of rows through the plume of one camera.

Run: ``/work/main/.venv/bin/python benchmarks/render.py``; writes
``benchmarks/results/render.json`` and ``render.md``.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.synthetic import render as R
from schlieren.pipeline.synthetic.background import make_background, wavelet_noise_tile
from schlieren.pipeline.synthetic.phantoms import buoyant_plume
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.synthetic.tracer import active_box, field_stack

OUT = Path(__file__).parent / "results"
N_CAM, W, H = 16, 1440, 1080
FRAME_RATE, LINE_TIME = 60.0, 1.54e-5


def main() -> None:
    grid = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.00125)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    offsets = -1 / FRAME_RATE - rng.uniform(0.25 * H, 0.75 * H, N_CAM) * LINE_TIME
    frame = 4
    t_lo = offsets.min() + frame / FRAME_RATE - 0.01
    ph = buoyant_plume(grid, duration=0.04, seed=0, t_start=t_lo)
    t_sim = time.perf_counter() - t0
    cams = [c.with_time_offset(o) for c, o in
            zip(make_rig(N_CAM, grid=grid, image_size=(W, H), line_time=LINE_TIME), offsets)]
    tile = wavelet_noise_tile(256, seed=0)
    bgs = []
    for i, c in enumerate(cams):
        zbg = float(np.linalg.norm(c.center - c.bg_point))
        bgs.append(make_background(c.bg_point, c.bg_normal, spacing=1.5 * zbg / c.K[0, 0], tile=tile, seed=i + 1))
    lat = R.make_lattice((W, H), 3)

    # warm-up: compile / load the numba caches on a small case
    small = make_rig(2, grid=grid, image_size=(96, 72), line_time=0.0)[0].with_time_offset(0.0)
    f_small = field_stack([ph.knot_refractivity(0)], grid)
    ref_small = R.reference_image(small, bgs[0], supersample=3)
    tr = R.trace_lattice(small, R.make_lattice((96, 72), 3), f_small, ph.knot_times[:1], grid, frame=0,
                         frame_rate=FRAME_RATE, clip_box=active_box(f_small, grid, tol=1e-5))
    R.render_image(small, bgs[0], tr, R.make_lattice((96, 72), 3), ref_small)

    t0 = time.perf_counter()
    refs = [R.reference_image(c, bg, supersample=3) for c, bg in zip(cams, bgs)]
    t_refs = time.perf_counter() - t0

    timing = {"fields": 0.0, "trace": 0.0, "render": 0.0, "sensor": 0.0, "png": 0.0, "truth": 0.0}
    t0 = time.perf_counter()
    idx = ph.knots_covering(offsets.min() + frame / FRAME_RATE, offsets.max() + frame / FRAME_RATE + H * LINE_TIME)
    fields = field_stack([ph.knot_refractivity(int(k)) for k in idx], grid)
    kt = ph.knot_times[idx]
    box = active_box(fields, grid, tol=1e-5)
    timing["fields"] = time.perf_counter() - t0
    marched = []
    max_delta = 0.0
    out_png = Path("/tmp/schlieren_bench_render")
    out_png.mkdir(exist_ok=True)
    t_out = float(frame / FRAME_RATE + offsets.mean() + 0.5 * H * LINE_TIME)
    for c, bg, ref in zip(cams, bgs, refs):
        t1 = time.perf_counter()
        tr = R.trace_lattice(c, lat, fields, kt, grid, frame=frame, frame_rate=FRAME_RATE, clip_box=box)
        t2 = time.perf_counter()
        img, dpx = R.render_image(c, bg, tr, lat, ref, supersample=3)
        t3 = time.perf_counter()
        u8 = R.sensor(img, noise=1.5, bit_depth=8, rng=rng)
        t4 = time.perf_counter()
        cv2.imwrite(str(out_png / f"{c.name}.png"), u8)
        t5 = time.perf_counter()
        gs = R.trace_lattice(c, lat, fields, kt, grid, frame=None, time=t_out, frame_rate=FRAME_RATE, clip_box=box)
        R.render_image(c, bg, gs, lat, ref, supersample=3)
        t6 = time.perf_counter()
        timing["trace"] += t2 - t1
        timing["render"] += t3 - t2
        timing["sensor"] += t4 - t3
        timing["png"] += t5 - t4
        timing["truth"] += t6 - t5
        marched.append(int(tr.marched.sum()))
        max_delta = max(max_delta, float(np.abs(dpx).max()))
    total = timing["fields"] + timing["trace"] + timing["render"] + timing["sensor"]

    # lattice interpolation error: direct rays at every pixel centre of a band through the plume
    c = cams[0]
    tr = R.trace_lattice(c, lat, fields, kt, grid, frame=frame, frame_rate=FRAME_RATE, clip_box=box)
    _, dpx = R.render_image(c, bgs[0], tr, lat, refs[0], supersample=1)
    # a band of 60 rows centred on the lattice row with the largest deflection
    _, lv = lat.coords()
    peak_row = int(lv[np.argmax(np.abs(tr.delta).max(axis=(1, 2)))])
    r0 = int(np.clip(peak_row - 30, 0, H - 60))
    rows = slice(r0, r0 + 60)
    u = np.arange(W, dtype=float)
    v = np.arange(rows.start, rows.stop, dtype=float)
    uu, vv = np.meshgrid(u, v)
    from schlieren.pipeline.synthetic.render import _trace_points
    direct = _trace_points(c, np.stack([uu, vv], -1), R.row_times(c, frame, vv, frame_rate=FRAME_RATE),
                           fields, kt, grid, step=grid.voxel_size, n_ambient=1.00029, clip_box=box)
    err = np.abs(dpx[rows] - direct.delta)
    sig = np.abs(direct.delta).max(-1) > 0.02
    interp = {"max_px": float(err.max()), "rms_px": float(np.sqrt(np.mean(err[sig] ** 2))),
              "signal_rms_px": float(np.sqrt(np.mean(direct.delta[sig] ** 2))), "rows": [rows.start, rows.stop]}

    res = {
        "what": "one raw frame, 16 cameras, 1440x1080, buoyant plume, 8-bit, supersample 3, lattice stride 3",
        "seconds_frame_total": total,
        "seconds": timing,
        "seconds_references_once": t_refs,
        "seconds_smoke_simulation_setup": t_sim,
        "phantom_grid": list(grid.shape),
        "knots_in_frame": int(len(idx)),
        "active_box": [list(map(float, box[0])), list(map(float, box[1]))],
        "marched_rays_per_camera": marched,
        "max_deflection_px": max_delta,
        "lattice_interpolation_error": interp,
        "target_seconds": 60.0,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average_at_end": list(os.getloadavg())},
        "note": "measured on a 2-core machine shared with other jobs (see load average): an upper bound",
    }
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "render.json").write_text(json.dumps(res, indent=2))
    md = [
        "# Render benchmark (issue 3)",
        "",
        f"One raw frame of {N_CAM} cameras at {W}x{H}, buoyant plume on a {grid.shape} grid "
        f"({grid.voxel_size * 1e3:.2f} mm), rolling shutter, 3x3 supersampling, lattice stride 3.",
        "",
        "| phase | seconds |",
        "| --- | --- |",
        f"| phantom fields ({len(idx)} knots) | {timing['fields']:.1f} |",
        f"| ray tracing (16 cameras) | {timing['trace']:.1f} |",
        f"| rendering (16 cameras) | {timing['render']:.1f} |",
        f"| sensor noise + quantisation | {timing['sensor']:.1f} |",
        f"| **frame total (target <= 60 s)** | **{total:.1f}** |",
        f"| PNG encoding (16 frames) | {timing['png']:.1f} |",
        f"| ground-truth traces of one output instant (16 cameras) | {timing['truth']:.1f} |",
        f"| reference images, once per camera (16) | {t_refs:.1f} |",
        f"| smoke simulation (setup) | {t_sim:.1f} |",
        "",
        f"Marched lattice rays per camera: {min(marched)}-{max(marched)}; max deflection {max_delta:.2f} px.",
        "",
        f"Lattice interpolation (stride 3) against rays traced at every pixel, rows {rows.start}-{rows.stop} "
        f"of cam00: max error {interp['max_px']:.4f} px, RMS {interp['rms_px']:.4f} px where the deflection "
        f"exceeds 0.02 px (signal RMS {interp['signal_rms_px']:.3f} px).",
        "",
        f"Machine: {os.cpu_count()} CPUs, shared with other jobs (load average at the end "
        f"{os.getloadavg()[0]:.1f}); timings are upper bounds.",
    ]
    (OUT / "render.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
