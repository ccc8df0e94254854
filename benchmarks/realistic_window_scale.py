"""The flow-window scale and the flow's in-plume error on the realistic family (issue 14).

    python benchmarks/realistic_window_scale.py [--work /work/realistic/work] [--cases a,b]
        [--scales 0.8,1,1.2,1.4,1.6] [--frame 1] [--flow-case plume1-16cam-640]

Reads the stores ``schlieren bench realistic --out WORK`` keeps (``WORK/<case>/store.zarr``
at the default parameters, its geometry cache and ``truth.zarr``) and writes
``benchmarks/results/realistic_window_scale.md`` / ``.json`` with two tables:

* **Scale scan**: one output frame of each case re-solved from the run's own flows, hull and
  weight with the modelled flow averaging (``flow_window``) times each scale
  (``tomography.flow_window_scale``), integrated and scored against the truth (whole box /
  in plume dB, as the family scores), beside the rays' signal-to-noise ratio in the masks
  (:func:`~schlieren.pipeline.tomography.rhs_snr`, the receipt's ``ray_snr``).
* **Flow error** (``--flow-case``, three cameras): the camera's averaged reference warped by
  the truth's deflection (noise-free), through the run's flow settings, against the
  Gaussian averaging the tomography models, the best 9x9 linear shift-invariant kernel
  fitted to the result, and, for plain LK (no texture correction, no smoothing), its
  texture-weighted window average ``(sum w T)^-1 sum w T d`` (``T`` the reference's
  structure tensor): how much of the flow's deterministic error any blur model could
  capture, and how much a texture-aware model would.
* **Oracle** (``--flow-case``, every camera): the run's flows minus that deterministic error
  (noise-free LK of the warped reference minus the modelled Gaussian of the truth's
  deflection at the output instant, sampled at the cell centres), solved as the run solves
  at several scales: the most an exact model of the LK response could gain.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CASES = ("plume1-16cam-640", "plume2-16cam-640", "jet3-16cam-640", "plume1-8cam-960-dist",
                 "plume2-8cam-960-dist", "jet3-8cam-960-dist", "plume1-8cam-960-dist-h264",
                 "plume1-16cam-640-h264")


def scale_scan(case_dir: Path, frame: int, scales) -> dict:
    from realistic_bounds import integrate_and_score, load_case  # this folder's sibling (run as a script)

    from schlieren.pipeline import tomography
    from schlieren.workers import tasks
    from schlieren.workers.tasks.regularisation import window_model

    ctx, geom, t_on, r_amb = load_case(case_dir, frame)
    params = tasks.tomo_params(ctx)
    window = np.asarray(ctx.store.read("flow_window", ()), dtype=np.float64)
    hull = ctx.store.read("hull", (frame,))
    flows = ctx.tomography_flows(frame)
    C = len(ctx.cameras)
    masks = np.stack([ctx.store.read("mask", (c, frame)) for c in range(C)])
    rhs = tomography.rhs_from_flows(geom, flows, n_ambient=params.n_ambient)
    quiet = tomography.bin_quiet(~masks, ctx.ray_binning)
    noise = np.asarray(ctx.store.read("rhs_noise", ()), dtype=np.float64)
    snr = tomography.rhs_snr(rhs, ~quiet, noise)
    rows = []
    for s in scales:
        blur = window_model(ctx, window * s)
        g, info = tomography.solve_gradient(geom, flows, hull, params=params, **blur)
        whole, plume = integrate_and_score(ctx, g, hull, t_on, r_amb)
        rows.append({"scale": s, "whole_db": whole, "plume_db": plume, "iterations": info.iterations})
    best = max(rows, key=lambda r: r["plume_db"])
    return {"cameras": C, "frame": frame, "ray_snr": [round(float(v), 2) for v in snr],
            "reg_weight": params.reg_weight, "rows": rows, "best_scale": best["scale"]}


def flow_error(case_dir: Path, cameras=(0, 5, 11), frame: int = 1) -> list[dict]:
    import zarr

    from schlieren.pipeline import flow as fm
    from schlieren.pipeline.flow.windows import _window_taps
    from schlieren.workers import tasks

    ctx = tasks.context(str(case_dir / "store.zarr"))
    truth = zarr.open_group(str(case_dir / "truth.zarr"), mode="r")
    out = []
    for cam in cameras:
        p = tasks.flow_params(ctx, cam)
        ref, full = _camera_truth(case_dir, truth, ctx, cam, frame)
        H, W = ref.shape
        clean = fm.warp_image(ref, full)  # frame(p) = reference(p + d(p)), no noise
        f = p.factor

        def blocks(a):
            return a[:H // f * f, :W // f * f].reshape(H // f, f, W // f, f, -1).mean(axis=(1, 3)).astype(np.float64)

        tr = blocks(full)
        est = fm.deflection_stage(ref, clean, p).astype(np.float64)
        raw = fm.deflection_stage(ref, clean, dataclasses.replace(p, texture_correction=False,
                                                                   smoothing_sigma=0.0)).astype(np.float64)
        sig = fm.measurement_sigma(p)
        gauss = blocks(np.stack([cv2.GaussianBlur(full[..., i], (0, 0), sig) for i in (0, 1)], -1))
        # the texture-weighted window average of plain LK
        presmooth = fm.resolve_presmooth(p.presmooth, ref)  # the flow's own width ("auto": from the reference)
        sm = cv2.GaussianBlur(ref, (0, 0), presmooth) if presmooth > 0 else ref
        gx = cv2.Scharr(sm, cv2.CV_32F, 1, 0) / 32.0
        gy = cv2.Scharr(sm, cv2.CV_32F, 0, 1) / 32.0
        taps = _window_taps(int(p.window), p.window_type).astype(np.float32)

        def win(a):
            return cv2.sepFilter2D(a.astype(np.float32), -1, taps, taps, borderType=cv2.BORDER_REFLECT)

        txx, txy, tyy = win(gx * gx), win(gx * gy), win(gy * gy)
        u, v = full[..., 0], full[..., 1]
        bx, by = win(gx * gx * u + gx * gy * v), win(gx * gy * u + gy * gy * v)
        det = txx * tyy - txy ** 2
        texw = blocks(np.stack([(tyy * bx - txy * by) / det, (txx * by - txy * bx) / det], -1))
        x = np.arange(len(taps)) - (len(taps) - 1) / 2.0
        raw_gauss = blocks(np.stack([cv2.GaussianBlur(full[..., i], (0, 0), float(np.sqrt(np.sum(taps * x * x) / taps.sum())))
                                     for i in (0, 1)], -1))
        mag = np.hypot(tr[..., 0], tr[..., 1])
        R = 4
        plume = mag > 0.1 * np.percentile(mag, 99.9)
        plume[:R] = plume[-R:] = False
        plume[:, :R] = plume[:, -R:] = False
        ii, jj = np.nonzero(plume)
        kern = []
        for comp in (0, 1):  # best 9x9 linear shift-invariant kernel on the flow grid
            A = np.stack([tr[ii + a, jj + b, comp] for a in range(-R, R + 1) for b in range(-R, R + 1)], axis=1)
            y = est[ii, jj, comp]
            k, *_ = np.linalg.lstsq(A, y, rcond=None)
            kern.append(y - A @ k)

        def rms(a, b):
            return round(float(np.sqrt(np.mean((a[plume] - b[plume]) ** 2))), 4)

        out.append({"camera": cam, "signal_px": round(float(np.sqrt(np.mean(tr[plume] ** 2))), 4),
                    "lk_vs_modelled_gaussian": rms(est, gauss),
                    "lk_vs_best_linear_kernel": round(float(np.sqrt(np.mean(np.concatenate(kern) ** 2))), 4),
                    "plain_lk_vs_window_gaussian": rms(raw, raw_gauss),
                    "plain_lk_vs_texture_weighted": rms(raw, texw)})
    return out


def _camera_truth(case_dir: Path, truth, ctx, cam: int, frame: int, name: str = "deflection_rs"):
    """Camera ``cam``'s averaged reference and the truth's deflection ``name`` at ``frame``,
    cubic-interpolated from the truth's flow cells to every pixel."""
    files = sorted(glob.glob(str(case_dir / f"cam{cam:02d}" / "reference" / "*.png")))
    ref = np.mean([cv2.imread(f, cv2.IMREAD_UNCHANGED).astype(np.float32) for f in files], axis=0)
    H, W = ref.shape
    d = np.asarray(truth[name][cam, frame], np.float32)  # cell means on the truth's flow grid
    tf = int(round(H / d.shape[0]))
    full = cv2.resize(d, (d.shape[1] * tf, d.shape[0] * tf), interpolation=cv2.INTER_CUBIC)
    return ref, np.pad(full, ((0, H - full.shape[0]), (0, W - full.shape[1]), (0, 0)), mode="edge")


def oracle(case_dir: Path, frame: int, scales=(1.0, 1.15, 1.3)) -> list[dict]:
    import zarr
    from realistic_bounds import integrate_and_score, load_case

    from schlieren.pipeline import flow as fm
    from schlieren.pipeline import tomography
    from schlieren.workers import tasks
    from schlieren.workers.tasks.regularisation import window_model

    ctx, geom, t_on, r_amb = load_case(case_dir, frame)
    truth = zarr.open_group(str(case_dir / "truth.zarr"), mode="r")
    flows = np.array(ctx.tomography_flows(frame), dtype=np.float32)
    corr = np.zeros_like(flows)
    for c in range(flows.shape[0]):
        p = tasks.flow_params(ctx, c)
        ref, full = _camera_truth(case_dir, truth, ctx, c, frame, "deflection")  # at the output instant
        H, W = ref.shape
        f = p.factor
        g = [cv2.GaussianBlur(full[..., i], (0, 0), fm.measurement_sigma(p)) for i in (0, 1)]
        mx, my = np.meshgrid((np.arange(W // f) * f + (f - 1) / 2.0).astype(np.float32),
                             (np.arange(H // f) * f + (f - 1) / 2.0).astype(np.float32))
        model = np.stack([cv2.remap(gi, mx, my, cv2.INTER_LINEAR) for gi in g], -1)
        corr[c] = fm.deflection_stage(ref, fm.warp_image(ref, full), p) - model
    window = np.asarray(ctx.store.read("flow_window", ()), dtype=np.float64)
    hull = ctx.store.read("hull", (frame,))
    params = tasks.tomo_params(ctx)

    def score(fl, s):
        g, _ = tomography.solve_gradient(geom, fl, hull, params=params, **window_model(ctx, window * s))
        return list(integrate_and_score(ctx, g, hull, t_on, r_amb))

    return [{"scale": s, "run": score(flows, s), "minus_deterministic_error": score(flows - corr, s)} for s in scales]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default="/work/realistic/work", help="the family's --out folder")
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES))
    ap.add_argument("--scales", default="0.8,1,1.2,1.4,1.6")
    ap.add_argument("--frame", type=int, default=1)
    ap.add_argument("--flow-case", default="plume1-16cam-640", help="case of the flow-error table ('' skips it)")
    ap.add_argument("--results", default=str(RESULTS))
    a = ap.parse_args(argv)
    work = Path(a.work)
    scales = [float(s) for s in a.scales.split(",")]
    t0 = time.perf_counter()
    out = {"command": "python benchmarks/realistic_window_scale.py " + " ".join(argv or sys.argv[1:]),
           "scan": {}, "flow_error": []}
    for case in [c for c in a.cases.split(",") if c]:
        if not (work / case / "store.zarr").exists():
            print(f"{case}: no store under {work} (run `schlieren bench realistic --out {work}` first)",
                  file=sys.stderr)
            return 2
        out["scan"][case] = scale_scan(work / case, a.frame, scales)
        print(case, out["scan"][case]["rows"], flush=True)
    if a.flow_case:
        out["flow_error"] = flow_error(work / a.flow_case, frame=a.frame)
        out["oracle"] = oracle(work / a.flow_case, a.frame)
        out["flow_case"] = a.flow_case
    out["seconds"] = round(time.perf_counter() - t0, 1)
    res = Path(a.results)
    res.mkdir(parents=True, exist_ok=True)
    (res / "realistic_window_scale.json").write_text(json.dumps(out, indent=1))
    (res / "realistic_window_scale.md").write_text(render(out, scales))
    print(f"wrote {res / 'realistic_window_scale.md'} ({out['seconds']} s)")
    return 0


def render(out: dict, scales) -> str:
    lines = ["# Flow-window scale and the flow's in-plume error (benchmarks/realistic_window_scale.py)", "",
             f"Command: `{out['command'].strip()}`", "",
             "One frame per case re-solved from the run's stored flows, hull and weight with the modelled flow "
             "averaging times each scale (`tomography.flow_window_scale`); whole box / in plume dB. `ray_snr`: the "
             "rays' signal-to-noise ratio in the masks (x / y / z).", "",
             "| case | cameras | ray_snr | " + " | ".join(f"scale {s:g}" for s in scales) + " | best |",
             "| --- | ---: | --- | " + " | ".join("---:" for _ in scales) + " | ---: |"]
    for case, r in out["scan"].items():
        cells = [f"{x['whole_db']:.2f} / {x['plume_db']:.2f}" for x in r["rows"]]
        lines.append(f"| {case} | {r['cameras']} | {' / '.join(f'{v:g}' for v in r['ray_snr'])} | "
                     + " | ".join(cells) + f" | {r['best_scale']:g} |")
    if out["flow_error"]:
        lines += ["", f"Flow error inside the plume ({out['flow_case']}, the reference warped by the truth's deflection, "
                  "noise-free; px on the flow grid):", "",
                  "| camera | signal RMS | LK vs modelled Gaussian | LK vs best 9x9 linear kernel | plain LK vs window "
                  "Gaussian | plain LK vs texture-weighted window |", "| ---: | ---: | ---: | ---: | ---: | ---: |"]
        for r in out["flow_error"]:
            lines.append(f"| {r['camera']} | {r['signal_px']} | {r['lk_vs_modelled_gaussian']} | "
                         f"{r['lk_vs_best_linear_kernel']} | {r['plain_lk_vs_window_gaussian']} | "
                         f"{r['plain_lk_vs_texture_weighted']} |")
    if out.get("oracle"):
        lines += ["", f"Oracle ({out['flow_case']}): the run's flows and the same minus LK's noise-free deterministic "
                  "error against the modelled Gaussian (every camera), solved as the run solves; whole box / in plume dB:",
                  "", "| scale | run | minus the deterministic error |", "| ---: | ---: | ---: |"]
        for r in out["oracle"]:
            lines.append(f"| {r['scale']:g} | {r['run'][0]:.2f} / {r['run'][1]:.2f} | "
                         f"{r['minus_deterministic_error'][0]:.2f} / {r['minus_deterministic_error'][1]:.2f} |")
    lines += ["", f"Wall time {out['seconds']} s.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
