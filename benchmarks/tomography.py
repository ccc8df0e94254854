"""Accuracy (paper Table 1) and per-frame speed of tomography + Poisson integration.

Accuracy (default): the project's buoyant-plume phantom (pipeline.synthetic.phantoms),
traced with the project's curved-ray tracer (pipeline.synthetic.tracer) on a grid twice
as fine as the reconstruction grid, 8 / 16 / 32 cameras on a half ring
(pipeline.synthetic.rig). The truth is the phantom block-averaged to the reconstruction
grid; metric of SPEC sec. 4 (relative RMS over the whole box normalised by the truth's
range, PSNR = 20 log10(1 / RMS)). Rows:

* Poisson integration of the true gradient (central differences on the fine grid,
  block-averaged: an "unknown" discretisation, as in the paper),
* tomography + integration from the exact exit directions (tracer ``d_out``),
* tomography + integration from the approximate ``d_out_hat`` (deflections rendered
  from the curved rays' background points),
* the same with noisy deflections (semi-convergence / regularisation study),
* the direct refractivity reconstruction,

each with the anisotropic (alpha = 0.8) and plain (alpha = 1) integration.

Speed (``--speed``): paper scale (about 150,000 basis functions in the hull and 700,000
rays per frame), per-frame time after the per-session setup, 8 frames in warm-start blocks of
4 as the pipeline runs them (each block's first frame cold), the hull changing by a few % from
frame to frame; ``--no-support`` restricts each frame on its own instead of inside its block's
shared restriction (the A/B of ``solve_gradient(support=...)``).

Run: ``.venv/bin/python benchmarks/tomography.py [--speed] [--quick]``;
writes ``benchmarks/results/tomography.json`` and ``.md`` (or ``tomography_speed.*``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

from schlieren.pipeline.geometry import FlowGrid, Grid, Medium
from schlieren.pipeline.hull import HullParams, visual_hull
from schlieren.pipeline.poisson import PoissonParams, integrate
from schlieren.pipeline.stages import RunConfig
from schlieren.pipeline.synthetic.phantoms import buoyant_plume
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.synthetic.tracer import trace_rays
from schlieren.pipeline.tomography import (
    RefractivityParams,
    TomoParams,
    bin_cells,
    binned_sigma,
    block_support,
    build_geometry,
    ray_binning,
    ray_grid,
    rhs_from_d_out,
    solve_gradient,
    solve_refractivity,
)

RESULTS = Path(__file__).resolve().parent / "results"
MEDIUM = Medium()
R_AMB = MEDIUM.refractivity_ambient


def psnr_rms(r, truth):
    rms = float(np.sqrt(np.mean((r - truth) ** 2)) / (truth.max() - truth.min()))
    return 20 * np.log10(1 / rms), rms


def block_average(a, f=2):
    nz, ny, nx = a.shape[:3]
    return a.reshape(nz // f, f, ny // f, f, nx // f, f, *a.shape[3:]).mean(axis=(1, 3, 5))


def fine_gradient(r, h):
    gz, gy, gx = np.gradient(r, h)
    return np.stack([gx, gy, gz], axis=-1)


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def scene(n_recon_xy: int, seed: int, t: float):
    """Phantom on a 2x fine grid, truth on the reconstruction grid."""
    vmin, vmax = (-0.075, -0.075, 0.0), (0.075, 0.075, 0.3)
    h = 0.15 / n_recon_xy
    grid = Grid(vmin, vmax, h)
    fine = Grid(vmin, vmax, h / 2)
    ph = buoyant_plume(fine, duration=max(t, 1 / 240) + 1 / 240, seed=seed, medium=MEDIUM)
    r_fine = ph.refractivity(t)
    truth = block_average(r_fine)
    g_true = block_average(fine_gradient(r_fine, fine.voxel_size))
    return grid, fine, r_fine, truth, g_true


def trace_all(cams, geom, r_fine, fine, fg):
    """Exact exit directions and deflections (pixels) of every flow-grid ray."""
    C = len(cams)
    rows, cols = fg.shape
    d_out = np.empty((C, rows, cols, 3))
    flows = np.empty((C, rows, cols, 2))
    uv = fg.pixel_centres()
    for c, cam in enumerate(cams):
        dirs = geom.d_in[c].reshape(-1, 3)
        res = trace_rays(r_fine, fine, np.broadcast_to(cam.center, dirs.shape).copy(), dirs,
                         n_ambient=MEDIUM.n_ambient)
        d_out[c] = res.d_out.reshape(rows, cols, 3)
        B = cam.intersect_background(res.exit_point, res.d_out)
        flows[c] = cam.project(B.reshape(rows, cols, 3)) - uv
    return d_out, flows


def masks_from_truth(geom, truth, grid, fg, C):
    """Conservative camera masks: rays through the (dilated) support of the flow."""
    import scipy.ndimage as ndi

    support = np.abs(truth - R_AMB) > 0.01 * (truth.max() - truth.min())
    support = ndi.binary_dilation(support, iterations=2)
    hit = (geom.S @ support.ravel().astype(np.float64)) > 0
    m = hit.reshape(C, *fg.shape)
    return np.stack([ndi.binary_dilation(mc, iterations=1) for mc in m])


def accuracy(args):
    t0 = time.perf_counter()
    n_xy = 32 if args.quick else 48
    grid, fine, r_fine, truth, g_true = scene(n_xy, seed=0, t=args.t)
    image = (480, 360) if args.quick else (720, 540)
    fg = FlowGrid(image, 3)
    cams32 = make_rig(32, ring="half", grid=grid, image_size=image)
    tp = TomoParams(n_ambient=MEDIUM.n_ambient)
    geom32 = build_geometry(cams32, grid, fg, params=tp)
    t_setup = time.perf_counter() - t0
    d_out32, flows32 = trace_all(cams32, geom32, r_fine, fine, fg)
    t_trace = time.perf_counter() - t0 - t_setup
    masks32 = masks_from_truth(geom32, truth, grid, fg, 32)
    print(f"scene {grid.shape}, fine {fine.shape}, flow grid {fg.shape}; setup {t_setup:.1f}s "
          f"trace {t_trace:.1f}s; max |flow| {np.abs(flows32).max():.2f}px", flush=True)
    rows = []

    def add(name, n_cams, r, extra=None):
        p, rms = psnr_rms(r, truth)
        row = {"row": name, "cameras": n_cams, "psnr_db": round(p, 2), "rms_percent": round(100 * rms, 3)}
        row.update(extra or {})
        rows.append(row)
        print(json.dumps(row), flush=True)

    hull32 = visual_hull(masks32, cams32, grid, fg, params=HullParams())
    # Row 0: Poisson integration of the true gradient.
    for alpha in (0.8, 1.0):
        r, info = integrate(g_true, hull32, grid, r_ambient=R_AMB, params=PoissonParams(alpha=alpha))
        add(f"poisson_true_gradient_alpha{alpha}", 0, r, {"iterations": info.iterations})
    r, info = integrate(g_true, hull32, grid, r_ambient=R_AMB, params=PoissonParams(alpha=0.8, value_scale=255.0))
    add("poisson_true_gradient_alpha0.8_units255", 0, r, {"iterations": info.iterations})
    noise_px = args.noise
    rng = np.random.default_rng(1)
    for n_cams in (8, 16, 32):
        step = 32 // n_cams
        sel = np.arange(0, 32, step)
        cams = [cams32[i] for i in sel]
        geom = build_geometry(cams, grid, fg, params=tp)
        d_out, flows, masks = d_out32[sel], flows32[sel], masks32[sel]
        hull = visual_hull(masks, cams, grid, fg)
        variants = {
            "exact_d_out": rhs_from_d_out(geom, d_out, n_ambient=MEDIUM.n_ambient),
            "approx_d_out": flows,
        }
        if n_cams == 16:
            variants[f"approx_d_out_noise{noise_px}px"] = flows + rng.normal(scale=noise_px, size=flows.shape)
        for vname, data in variants.items():
            regs = [tp.reg_weight]
            if n_cams == 16 and args.sweep:
                regs = [0.0, 0.02, 0.1, 0.3]
            for reg in regs:
                p = TomoParams(n_ambient=MEDIUM.n_ambient, reg_weight=reg)
                ts = time.perf_counter()
                g, sinfo = solve_gradient(geom, data, hull, params=p)
                t_s = time.perf_counter() - ts
                for alpha in (0.8, 1.0):
                    ti = time.perf_counter()
                    r, pinfo = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(alpha=alpha))
                    add(f"{vname}_alpha{alpha}", n_cams, r,
                        {"reg_weight": reg, "iterations": sinfo.iterations, "residual": round(sinfo.residual, 4),
                         "stop": sinfo.stop_reason, "n_unknowns": sinfo.n_unknowns, "n_rays": sinfo.n_rays,
                         "tomo_s": round(t_s, 2), "poisson_s": round(time.perf_counter() - ti, 2)})
                if n_cams == 16 and vname.startswith("approx_d_out") and reg == tp.reg_weight:
                    # Anisotropic gain versus the units of the Appendix's exponent and alpha.
                    for vs in (255.0, 65535.0):
                        for alpha in (0.6, 0.8):
                            r, _ = integrate(g, hull, grid, r_ambient=R_AMB,
                                             params=PoissonParams(alpha=alpha, value_scale=vs))
                            add(f"{vname}_alpha{alpha}_units{vs:g}", n_cams, r, {"reg_weight": reg})
            if vname != "exact_d_out" or n_cams == 16:
                ts = time.perf_counter()
                rd, dinfo = solve_refractivity(geom, data, hull, grid, r_ambient=R_AMB,
                                               params=RefractivityParams(n_ambient=MEDIUM.n_ambient))
                add(f"{vname}_direct", n_cams, rd, {"iterations": dinfo.iterations,
                                                     "direct_s": round(time.perf_counter() - ts, 2)})
        if args.semiconv and n_cams == 16:
            semiconvergence(geom, variants[f"approx_d_out_noise{noise_px}px"], hull, grid, truth, rows)
    out = {
        "phantom": "pipeline.synthetic buoyant_plume (seed 0) at t = %.3f s, curved-ray tracer on a 2x fine grid" % args.t,
        "grid": list(grid.shape), "fine_grid": list(fine.shape), "flow_grid": list(fg.shape),
        "image_size": list(image), "rig": "make_rig half ring, radius 2.5 m, background 2.5 m behind the centre",
        "noise_px": noise_px, "rows": rows, "total_seconds": round(time.perf_counter() - t0, 1),
        "peak_rss_mb": round(peak_rss_mb(), 1), "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(), "note": "total_seconds depends on the machine's load; the accuracy does not",
    }
    write("tomography" + args.suffix, out, table_md(out))


def semiconvergence(geom, flows, hull, grid, truth, rows):
    """Error versus iteration count with and without the smoothness term (noisy data)."""
    for reg in (0.0, 0.02):
        for it in (5, 10, 20, 40, 80):
            p = TomoParams(n_ambient=MEDIUM.n_ambient, reg_weight=reg, max_iter=it, tol=1e-12)
            g, info = solve_gradient(geom, flows, hull, params=p)
            r, _ = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(alpha=0.8))
            psnr, rms = psnr_rms(r, truth)
            row = {"row": f"semiconvergence_reg{reg}", "cameras": 16, "iterations": info.iterations,
                   "psnr_db": round(psnr, 2), "rms_percent": round(100 * rms, 3),
                   "residual": round(info.residual, 4)}
            rows.append(row)
            print(json.dumps(row), flush=True)


def table_md(out):
    lines = [f"# Tomography accuracy ({out['phantom']})", "",
             f"Grid {out['grid']} (fine {out['fine_grid']}), flow grid {out['flow_grid']}, "
             f"image {out['image_size']}; {out['rig']}; peak RSS {out['peak_rss_mb']} MB; "
             f"{out['total_seconds']} s total. {out['note']}.", "",
             "| row | cameras | reg | iterations | PSNR dB | RMS % |", "| --- | --- | --- | --- | --- | --- |"]
    for r in out["rows"]:
        lines.append(f"| {r['row']} | {r['cameras']} | {r.get('reg_weight', '')} | {r.get('iterations', '')} | "
                     f"{r['psnr_db']} | {r['rms_percent']} |")
    return "\n".join(lines) + "\n"


def write(name, out, md):
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=1))
    (RESULTS / f"{name}.md").write_text(md)
    print(md)


def speed(args):
    """Paper scale: ~150k basis functions inside the hull, ~700k rays per frame."""
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    grid = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.0025)  # 60 x 60 x 120
    image = (810, 1440)  # portrait: the 2:1 tall box fills the frame
    fg = FlowGrid(image, 3)  # 270 x 480 flow grid, the paper's size
    cams = make_rig(16, ring="half", grid=grid, image_size=image)
    voxel_note = "manifest voxel 2.5 mm"
    if args.voxel == "auto":  # what a manifest without voxel_size gets (pipeline.geometry.auto_voxel_size)
        from schlieren.pipeline.geometry import auto_voxel_size

        v, info = auto_voxel_size(cams, grid.vmin, grid.vmax)
        grid = Grid(grid.vmin, grid.vmax, v)
        voxel_note = (f"auto voxel {1e3 * v:.2f} mm ({info['px_per_voxel']:.1f} px per voxel, limited by "
                      f"{info['limited_by']})")
    elif args.voxel:
        grid = Grid(grid.vmin, grid.vmax, float(args.voxel))
        voxel_note = f"voxel {1e3 * grid.voxel_size:.2f} mm"
    tp = TomoParams(n_ambient=MEDIUM.n_ambient)
    # the pipeline's rays: one per block of flow cells where the cells oversample the voxels
    # (TomoParams.ray_binning, pipeline.tomography.binning; --ray-binning overrides)
    b = ray_binning(cams, grid, fg, args.ray_binning)
    rays = ray_grid(fg, b)
    geom = build_geometry(cams, grid, rays, params=tp)
    t_geom = time.perf_counter() - t0
    # The flow's image averaging the pipeline models (TomoParams.model_flow_window): LK window
    # from each camera's voxel footprint, as workers.tasks.flow_blur builds it.
    from schlieren.pipeline import flow as flowmod
    from schlieren.pipeline.geometry import pixel_footprint
    from schlieren.pipeline.tomography import MeasurementBlur, volume_sigma

    fp = flowmod.FlowParams()
    windows = [flowmod.window_for_voxel(grid.voxel_size / pixel_footprint(c, np.asarray(grid.center)),
                                        fp.window_per_voxel) for c in cams]
    cell_sigmas = [flowmod.measurement_sigma(flowmod.FlowParams(window=w)) / fg.factor for w in windows]
    # the measurements are made with the image averaging; the solver models it as the
    # pipeline does (TomoParams.flow_window_space)
    blur = (MeasurementBlur((len(cams),) + tuple(fg.shape), cell_sigmas)
            if tp.model_flow_window and not args.no_blur else None)
    model = {}
    if blur is not None:
        space = args.window_space or tp.flow_window_space
        ray_sigmas = binned_sigma(cell_sigmas, b)
        model = ({"blur": MeasurementBlur(geom.flow_shape, ray_sigmas)} if space == "image"
                 else {"volume_blur": volume_sigma(ray_sigmas, cams, grid, rays.factor)})
    print(f"geometry: {t_geom:.1f}s, S {geom.S.shape} nnz {geom.S.nnz}, {geom.nbytes / 1e9:.2f} GB", flush=True)
    # A plume-like hull: a vertical cone-cylinder whose dilated basis set has ~150k voxels.
    X = grid.centres()
    rho = np.hypot(X[..., 0], X[..., 1])
    z = X[..., 2]
    radius0 = args.hull_radius * (0.55 + 0.45 * z / 0.3)
    # Smooth synthetic gradient field inside it, evolving between frames; the hull breathes
    # with it (radius +-1.5 %: consecutive hulls differ by a few %, as the realistic
    # family's do, whose warm-start blocks' unions are 2-3 % above each frame's hull).
    # The measurements: each flow cell's ray (one camera's projection at a time, so the data
    # synthesis never holds more than the solver's geometry), the flow's window average, 1 %
    # noise per cell, then the block means the pipeline's rays see.
    fields = []
    for f in range(args.frames):
        radius = radius0 * (1 + 0.015 * np.sin(2.1 * f))  # not periodic: each block its own union
        hull = rho < radius
        w = np.clip(1 - (rho / radius) ** 2, 0, None) ** 2
        ph = 2 * np.pi * (z / 0.1 + 0.15 * f)
        fields.append((R_AMB - 8e-5 * w * (0.7 + 0.3 * np.sin(ph)), hull))
    grads = [fine_gradient(rfield, grid.voxel_size).reshape(-1, 3) for rfield, _ in fields]
    cells = np.empty((args.frames, len(cams)) + tuple(fg.shape) + (3,))
    for c, cam in enumerate(cams):
        Sc = build_geometry([cam], grid, fg, params=tp).S
        for f, g in enumerate(grads):
            cells[f, c] = np.stack([Sc @ g[:, k] for k in range(3)], axis=1).reshape(*fg.shape, 3)
        del Sc
    del grads
    frames = []
    rng = np.random.default_rng(0)
    for f, (rfield, hull) in enumerate(fields):
        rhs = blur.apply(cells[f]).astype(np.float64) if blur is not None else cells[f]
        rhs = rhs + rng.normal(scale=0.01 * np.abs(rhs).max(), size=rhs.shape)
        frames.append((bin_cells(rhs, b), rfield, hull))
    del cells
    t_data = time.perf_counter() - t0 - t_geom
    # warm-start blocks as the pipeline runs them (RunConfig.warm_start_block): the first
    # frame of a block starts cold, the others from the previous frame; each frame's system
    # is selected inside the block's shared restriction (workers.tasks.tomography.tomography_task)
    B = RunConfig().warm_start_block
    results = []
    x0 = None
    r0 = None
    for f, (rhs, rtrue, hull) in enumerate(frames):
        if f % B == 0:
            x0 = r0 = None
            lo = f
            support = (None if args.no_support else
                       block_support([h for _, _, h in frames[lo:lo + B]], tp.hull_dilation))
        ts, cs = time.perf_counter(), time.process_time()
        g, sinfo = solve_gradient(geom, rhs, hull, params=tp, x0=x0, support=support, **model)
        t_tomo, c_tomo = time.perf_counter() - ts, time.process_time() - cs
        ti, ci = time.perf_counter(), time.process_time()
        r, pinfo = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(solver=args.solver), x0=r0)
        t_int, c_int = time.perf_counter() - ti, time.process_time() - ci
        x0, r0 = g, r
        psnr, _ = psnr_rms(r, rtrue)
        row = {"frame": f, "tomography_s": round(t_tomo, 3), "restrict_setup_s": round(sinfo.setup_seconds, 3),
               "cgls_s": round(sinfo.solve_seconds, 3), "iterations": sinfo.iterations,
               "n_unknowns": sinfo.n_unknowns, "n_rays": sinfo.n_rays, "nnz": sinfo.nnz,
               "integration_s": round(t_int, 3), "poisson_iterations": pinfo.iterations,
               "total_s": round(t_tomo + t_int, 3), "cpu_s": round(c_tomo + c_int, 3),
               "psnr_db": round(psnr, 2), "load_avg_1min": round(os.getloadavg()[0], 2)}
        results.append(row)
        print(json.dumps(row), flush=True)
    warm = [r for r in results if r["frame"] % B] or results
    out = {"grid": list(grid.shape), "voxel": voxel_note, "ray_binning": b, "ray_grid": list(rays.shape),
           "flow_window_model": (f"LK windows {sorted(set(windows))} px -> image sigma "
                                 f"{', '.join(f'{v:.2f}' for v in sorted(set(blur.sigmas)))} cells, modelled "
                                 + (f"in the volume (sigma {model['volume_blur']:.2f} voxels)" if "volume_blur" in model
                                    else "in image space")
                                 if blur is not None else "off (--no-blur)"), "flow_grid": list(fg.shape), "cameras": 16,
           "hull_voxels": f"{min(int(h.sum()) for _, _, h in frames)}-{max(int(h.sum()) for _, _, h in frames)}",
           "geometry_seconds": round(t_geom, 1),
           "geometry_bytes": geom.nbytes, "data_seconds": round(t_data, 1), "frames": results,
           "mean_total_s_warm": round(float(np.mean([r["total_s"] for r in warm])), 3),
           "mean_cpu_s_warm": round(float(np.mean([r["cpu_s"] for r in warm])), 3),
           "mean_total_s_all": round(float(np.mean([r["total_s"] for r in results])), 3),
           "warm_start_block": B, "shared_restriction": not args.no_support,
           "peak_rss_mb": round(peak_rss_mb(), 1), "poisson_solver": args.solver,
           "numba_threads": int(__import__("numba").get_num_threads()),
           "env": {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER", "NUMBA_NUM_THREADS")},
           "load_avg_start": [round(v, 2) for v in load0], "load_avg_end": [round(v, 2) for v in os.getloadavg()],
           "note": (f"1-min load average {load0[0]:.2f} at the start (this VM idles at about 1.0; the "
                    "average trails a job that just ended by about a minute)")}
    md = ["# Tomography + integration speed at paper scale", "",
          f"Load averages (1/5/15 min): {out['load_avg_start']} at the start, {out['load_avg_end']} at the end "
          "(2 cores; anything above ~1 means another process competed for them).", "",
          f"Grid {out['grid']} ({voxel_note}), 16 cameras, flow grid {out['flow_grid']}"
          + (f" measured by one ray per {b}x{b} cells ({out['ray_grid'][0]} x {out['ray_grid'][1]} rays per camera, "
             "`tomography.ray_binning`)" if b > 1 else "") + f", hull {out['hull_voxels']} voxels; "
          f"per-session geometry {out['geometry_seconds']} s ({geom.nbytes / 1e9:.2f} GB); peak RSS "
          f"{out['peak_rss_mb']} MB; Poisson solver {args.solver}; flow-window model "
          f"{out['flow_window_model']}. {out['note']}.", "",
          "| frame | unknowns | rays | nnz | restrict s | CG s (it) | integrate s (it) | total wall s | CPU s | load |",
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        md.append(f"| {r['frame']} | {r['n_unknowns']} | {r['n_rays']} | {r['nnz']} | {r['restrict_setup_s']} | "
                  f"{r['cgls_s']} ({r['iterations']}) | {r['integration_s']} ({r['poisson_iterations']}) | "
                  f"{r['total_s']} | {r['cpu_s']} | {r['load_avg_1min']} |")
    md.append("")
    md.append(f"Mean per warm-started frame: {out['mean_total_s_warm']} s wall, {out['mean_cpu_s_warm']} s CPU "
              f"(process time over both threads; on an idle 2-core machine the wall time is at most this); "
              f"over all frames, cold starts included: {out['mean_total_s_all']} s. Warm-start blocks of {B} "
              "frames; " + ("each frame's system selected inside its block's shared restriction "
                            "(`solve_gradient(support=...)`; restrict s of a warm frame is then its setup pass)."
                            if not args.no_support else "each frame restricted on its own (--no-support)."))
    write("tomography_speed" + args.suffix, out, "\n".join(md) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--speed", action="store_true", help="paper-scale speed run instead of accuracy")
    ap.add_argument("--no-blur", action="store_true", help="speed run: cell-centre rays only (no flow-window "
                    "model, tomography.model_flow_window: false)")
    ap.add_argument("--quick", action="store_true", help="smaller accuracy scene")
    ap.add_argument("--sweep", action="store_true", help="sweep the regularisation weight (16 cameras)")
    ap.add_argument("--semiconv", action="store_true", help="error vs iterations with noisy deflections")
    ap.add_argument("--noise", type=float, default=0.05, help="deflection noise, pixels")
    ap.add_argument("--t", type=float, default=0.0, help="phantom time, seconds")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--suffix", default="", help="appended to the results file name")
    ap.add_argument("--no-support", action="store_true",
                    help="speed run: restrict each frame on its own instead of inside its warm-start block's union")
    ap.add_argument("--hull-radius", type=float, default=0.06)
    ap.add_argument("--ray-binning", type=int, default=0,
                    help="speed run: flow cells per ray along each axis (0 = the pipeline's automatic choice)")
    ap.add_argument("--solver", default="mg")
    ap.add_argument("--window-space", choices=("volume", "image"), default="",
                    help="speed run: where the solver models the flow averaging (default: TomoParams')")
    ap.add_argument("--voxel", default="", help="speed run: voxel in metres, or 'auto' (the default a manifest "
                                                "without voxel_size gets); default 2.5 mm")
    args = ap.parse_args(argv)
    if args.speed:
        speed(args)
    else:
        accuracy(args)


if __name__ == "__main__":
    sys.exit(main())
