"""Strobe sync, rolling-shutter resampling and flow masks on rendered captures (issue 4).

Uses the project's renderer (``pipeline.synthetic``) through the ``Scene`` helper of
``benchmarks/flow.py`` (1440x1080, Wavelet Noise, sensor noise 1.5 grey levels, 8 bit).

1. Sync: random camera offsets and exposures (1-15 ms); a strobe flash at t = 0 (+100 grey
   levels, the renderer's ``flash_rows`` / ``apply_flash``) on real rendered frames;
   ``detect_flash`` on the frames' row means, ``offset_from_flash``; error in line times
   (target: within 2) and whether ``flash_frames`` covers every lit frame.
2. Resampling: the buoyant-plume phantom (non-stationary), two cameras with different
   sub-frame offsets. For each output instant ``time[k]`` (``output_times``) the
   resampled flow of each camera is compared with the renderer's *global-shutter*
   deflection at that instant: unresampled (the raw frame ``A + k``), nearest,
   per-row linear blend, and motion-compensated warping (``resample_flow``, the paper's
   method), from the renderer's exact raw rolling-shutter deflections and from the LK
   flows of the rendered frames.
3. Masks: LK flows of a sequence of camera-frames -> ``flow_potential`` ->
   ``potential_summary`` -> one ``threshold_from_summaries`` over all camera-frames ->
   ``make_mask`` (spatio-temporal dilation). Support = cells whose true deflection exceeds
   0.02 px; reported: fraction of the support inside the mask (target >= 99.5 %) and
   mask area / support area (target <= 3), for the default and other percentiles.

Run: ``/work/main/.venv/bin/python benchmarks/sync_masks.py [--quick]``; writes
``benchmarks/results/sync_masks.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np

from schlieren.pipeline import flow as F
from schlieren.pipeline import masks as M
from schlieren.pipeline import sync as S
from schlieren.pipeline.synthetic import render as R

_spec = importlib.util.spec_from_file_location("bench_flow", Path(__file__).with_name("flow.py"))
bench_flow = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_flow)
Scene, sensor = bench_flow.Scene, bench_flow.sensor
FRAME_RATE, LINE_TIME = bench_flow.FRAME_RATE, bench_flow.LINE_TIME
RESULTS = bench_flow.RESULTS
log = logging.getLogger("bench.sync_masks")


def bench_sync(n_trials: int, rng) -> dict:
    scene = Scene("tealights", n_cameras=1)
    cam0 = scene.cameras[0]
    ref = scene.references[0]
    H = cam0.height
    gain = R.RenderParams().flash_gain
    errors, cut, covered = [], 0, 0
    window = 8
    for _ in range(n_trials):
        offset = -rng.uniform(1.0, window - 2.0) / FRAME_RATE - rng.uniform(0.0, H * LINE_TIME)
        exposure = rng.uniform(1e-3, 15e-3)
        cam = cam0.with_time_offset(offset)
        rows, lit_frames = [], set()
        for f in range(window):
            lit = R.flash_rows(cam, f, frame_rate=FRAME_RATE, exposure=exposure)
            img = R.apply_flash(ref, lit, gain) if lit.any() else ref
            if lit.any():
                lit_frames.add(f)
            rows.append(sensor(img, rng).mean(axis=1))
        det = S.detect_flash(np.stack(rows))
        est = S.offset_from_flash(det, first_frame=0, frame_rate=FRAME_RATE, line_time=LINE_TIME)
        errors.append(abs(est - offset) / LINE_TIME)
        cut += int(len(det.lit_frames) > 1 or det.cut_top or det.cut_bottom)
        covered += int(lit_frames <= S.flash_frames(det, first_frame=0))
    e = np.array(errors)
    return {"trials": n_trials, "max_error_lines": float(e.max()), "p95_error_lines": float(np.percentile(e, 95)),
            "median_error_lines": float(np.median(e)), "within_2_lines": float(np.mean(e <= 2.0)),
            "bands_cut_by_frame_edge_or_split": cut, "flash_frames_cover_lit_frames": covered / n_trials}


def bench_resample_and_masks(n_out: int, rng) -> tuple[dict, dict]:
    offsets = np.array([-0.0043, -0.0117])
    scene = Scene("plume", n_cameras=2, offsets=offsets, t_start=-0.05, duration=0.25)
    fg = scene.flow_grid
    H = scene.cameras[0].height
    A = 4
    times = S.output_times(A, n_out, offsets=offsets, frame_rate=FRAME_RATE, height=H, line_time=LINE_TIME)
    params = F.FlowParams()
    raw_true, raw_lk = {}, {}
    per = {m: {"true raw": [], "LK raw": []} for m in ("unresampled", "nearest", "linear", "motion")}
    per_all = {m: {"true raw": [], "LK raw": []} for m in per}
    for i in range(2):
        prep = F.prepare_reference(sensor(scene.references[i], rng, 0.0), presmooth=params.presmooth,
                                   levels=params.levels)
        need = [S.frames_needed(t, offset=offsets[i], frame_rate=FRAME_RATE, line_time=LINE_TIME, height=H)
                for t in times]
        lo = min(a for a, _ in need)
        hi = max(max(b for _, b in need), A + n_out)
        for f in range(lo, hi):
            t0 = time.perf_counter()
            img, dpx = scene.frame(i, f)
            raw_true[i, f] = R.cell_average(dpx, fg).astype(np.float32)
            raw_lk[i, f] = F.deflection_stage(prep, sensor(img, rng), params)
            log.info("plume cam %d frame %d in %.1f s", i, f, time.perf_counter() - t0)
        for k, T in enumerate(times):
            gs = scene.global_truth(i, T)
            inside = np.linalg.norm(gs, axis=-1) > 0.02
            a, b = need[k]
            for src, raw in (("true raw", raw_true), ("LK raw", raw_lk)):
                stack = np.stack([raw[i, f] for f in range(a, b)])
                res = {"unresampled": raw[i, A + k]}
                for m in ("nearest", "linear", "motion"):
                    res[m] = S.resample_flow(stack, a, T, offset=offsets[i], frame_rate=FRAME_RATE,
                                             line_time=LINE_TIME, flow_grid=fg,
                                             params=S.ResampleParams(method=m))
                for m, out in res.items():
                    err = np.linalg.norm(out - gs, axis=-1)
                    per[m][src].append(float(np.sqrt(np.mean(err[inside] ** 2))))
                    per_all[m][src].append(float(np.sqrt(np.mean(err ** 2))))
    resample = {"instants": [float(t) for t in times], "offsets": offsets.tolist(),
                "rms_in_plume": {m: {s: float(np.mean(v)) for s, v in d.items()} for m, d in per.items()},
                "rms_all_cells": {m: {s: float(np.mean(v)) for s, v in d.items()} for m, d in per_all.items()}}
    masks = {"plume": evaluate_masks(raw_lk, raw_true)}
    return resample, masks


def evaluate_masks(raw_lk: dict, raw_true: dict) -> dict:
    """Masks for every camera-frame of the sequence, one global threshold per percentile."""
    keys = sorted(raw_lk)
    pots = {k: M.flow_potential(raw_lk[k]) for k in keys}
    out = {}
    variants = [(pct, dt) for dt in (M.MaskParams().deflection_threshold, 0.0)
                for pct in (70.0, 80.0, 85.0, 90.0, 95.0)]
    for pct, dt in variants:
        p = M.MaskParams(percentile=pct, deflection_threshold=dt)
        thr = M.threshold_from_summaries([M.potential_summary(pots[k], smooth_sigma=p.smooth_sigma,
                                                              n_quantiles=p.n_quantiles)
                                          for k in keys], percentile=p.percentile)
        contain, ratio = [], []
        for cam in sorted({c for c, _ in keys}):
            frames = sorted(f for c, f in keys if c == cam)
            stack = np.stack([pots[cam, f] for f in frames])
            flows = np.stack([raw_lk[cam, f] for f in frames])
            for j, f in enumerate(frames):
                m = M.make_mask(stack, j, thr, flows=flows, smooth_sigma=p.smooth_sigma,
                                dilation_radius=p.dilation_radius, temporal_radius=p.temporal_radius,
                                deflection_threshold=p.deflection_threshold, flow_sigma=p.flow_sigma,
                                noise_factor=p.noise_factor, grow_factor=p.grow_factor)
                s = np.linalg.norm(raw_true[cam, f], axis=-1) > 0.02
                contain.append(float(m[s].mean()))
                ratio.append(float(m.sum() / max(s.sum(), 1)))
        out[f"{pct:g} | {dt:g}"] = {"threshold": thr, "min_contained": float(np.min(contain)),
                           "mean_contained": float(np.mean(contain)),
                           "max_area_ratio": float(np.max(ratio)), "mean_area_ratio": float(np.mean(ratio))}
    return out


def tealight_masks(n_frames: int, rng) -> dict:
    scene = Scene("tealights", n_cameras=2, offsets=[-0.002, -0.009])
    params = F.FlowParams()
    raw_lk, raw_true = {}, {}
    for i in range(2):
        prep = F.prepare_reference(sensor(scene.references[i], rng, 0.0), presmooth=params.presmooth,
                                   levels=params.levels)
        for f in range(3, 3 + n_frames):
            img, dpx = scene.frame(i, f)
            raw_true[i, f] = R.cell_average(dpx, scene.flow_grid).astype(np.float32)
            raw_lk[i, f] = F.deflection_stage(prep, sensor(img, rng), params)
            log.info("tealights cam %d frame %d", i, f)
    return evaluate_masks(raw_lk, raw_true)


def write(result: dict) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "sync_masks.json").write_text(json.dumps(result, indent=2))
    sy = result["sync"]
    lines = ["# Strobe sync, rolling-shutter resampling, masks (benchmarks/sync_masks.py)", "",
             "## Strobe sync (rendered 1440x1080 frames, flash at t = 0, exposures 1-15 ms, noise 1.5)", "",
             "| trials | max error | p95 | median | within 2 line times | bands cut by a frame edge "
             "(split over 2 frames) | flash frames all excluded |", "| --- | --- | --- | --- | --- | --- | --- |",
             f"| {sy['trials']} | {sy['max_error_lines']:.2f} lines | {sy['p95_error_lines']:.2f} | "
             f"{sy['median_error_lines']:.2f} | {100 * sy['within_2_lines']:.0f} % | "
             f"{sy['bands_cut_by_frame_edge_or_split']} | {100 * sy['flash_frames_cover_lit_frames']:.0f} % |", ""]
    rs = result["resample"]
    lines += ["## Resampling to common instants (buoyant plume, 2 cameras, offsets "
              f"{rs['offsets']} s, instants {[round(t, 5) for t in rs['instants']]} s)", "",
              "RMS end-point error (px) against the renderer's global-shutter deflection at the instant.", "",
              "| method | from true raw flows, in plume | all cells | from LK raw flows, in plume | all cells |",
              "| --- | --- | --- | --- | --- |"]
    for m in rs["rms_in_plume"]:
        a, b = rs["rms_in_plume"][m], rs["rms_all_cells"][m]
        lines.append(f"| {m} | {a['true raw']:.4f} | {b['true raw']:.4f} | {a['LK raw']:.4f} | {b['LK raw']:.4f} |")
    lines.append("")
    for name, res in result["masks"].items():
        lines += [f"## Masks, phantom `{name}` (LK flows, one global threshold, default dilation "
                  f"{M.MaskParams().dilation_radius} cells, temporal radius {M.MaskParams().temporal_radius})", "",
                  "| percentile | deflection threshold (px) | min support contained | mean contained | "
                  "max area / support | mean area / support |",
                  "| --- | --- | --- | --- | --- | --- |"]
        d = M.MaskParams()
        for key, r in res.items():
            pct, dt = key.split(" | ")
            mark = " (default)" if (float(pct), float(dt)) == (d.percentile, d.deflection_threshold) else ""
            dts = "off (paper)" if float(dt) == 0 else dt
            lines.append(f"| {pct}{mark} | {dts} | {100 * r['min_contained']:.2f} % | "
                         f"{100 * r['mean_contained']:.2f} % | {r['max_area_ratio']:.2f} | "
                         f"{r['mean_area_ratio']:.2f} |")
        lines.append("")
    lines.append(f"Load average at start / end: {result['load_start']} / {result['load_end']} (shared machine).")
    (RESULTS / "sync_masks.md").write_text("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cv2.setNumThreads(2)
    rng = np.random.default_rng(1)
    result = {"load_start": bench_flow.load_average()}
    result["sync"] = bench_sync(10 if args.quick else 40, rng)
    log.info("sync: %s", result["sync"])
    result["resample"], result["masks"] = bench_resample_and_masks(1 if args.quick else 3, rng)
    result["masks"]["tealights"] = tealight_masks(3 if args.quick else 4, rng)
    result["load_end"] = bench_flow.load_average()
    write(result)
    print((RESULTS / "sync_masks.md").read_text())


if __name__ == "__main__":
    main()
