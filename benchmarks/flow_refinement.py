"""Where the 16-camera flow loses in the plume, and what a refined flow gains (issue 35 item 4).

    python benchmarks/flow_refinement.py decompose --case plume1-16cam-640 --label i35f_base
    python benchmarks/flow_refinement.py refine --case plume1-16cam-640 --label i35f_base --passes 2

Reads a kept store of the realistic family (``schlieren bench realistic --out WORK --label
LABEL --keep-stores``: ``WORK/<case>/store-LABEL.zarr`` with its geometry cache) and the
case's ``truth.zarr``.

``decompose`` splits the flow's error against the truth's deflections (``truth.zarr``:
area means over the truth's flow cells) on a grid common to both (cells of
``lcm(run factor, truth factor)`` pixels), inside the plume (cells whose truth deflection
exceeds a tenth of the camera-frame's largest) and where nothing flows:

* ``raw``: the deflection task's flow of each raw frame (``flow_raw``) against the truth's
  rolling-shutter deflection of that frame (``deflection_rs``): the optical flow alone;
* ``resampled``: the truth's own raw deflections resampled to the output instant as the run
  resamples, against the truth at that instant: the synchronisation alone;
* ``output``: the run's resampled flow (``flow``) against the truth at the output instant;

and each error into what a Gaussian average of the truth's deflection over the flow's
window explains (``G_s d - d``, ``s`` fitted; the remainder's RMS is the rest) and a gain
(``g d``). It also reports the errors' correlation between consecutive frames.

``refine`` measures the re-projection refinement: from the run's reconstruction ``x`` of
the nearest output frame, predict each camera's deflections (the tomography's rays ``S x``
turned into pixels by the rays' linearised exit-direction model, cubic-interpolated to
every pixel), warp the reference by the prediction (exact cubic B-splines), run the run's
flow (with its capture correction) for the residual only, add the prediction's cell means
back, resample to the output instants as the run does and solve the tomography again (from
zero, the run's parameters and weight; with and without the run's flow-window model);
``--passes`` repeats it from the new solution. Every row is integrated and scored as the
family scores: whole box / in plume dB over the case's output frames (RMS over frames).
The reference row solves the run's own flows the same way.

``window`` measures a flow with a smaller LK window inside the plume (the run's flow where
nothing flows).

Writes ``benchmarks/results/flow_refinement.json`` and ``.md`` (``--name`` to change).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

RESULTS = Path(__file__).resolve().parent / "results"
WORK = Path("/work/realistic")
PLUME_FRACTION = 0.1  # a cell is "in the plume" above this fraction of the camera-frame's largest deflection


# --------------------------------------------------------------------------------------- loading

def load(case: str, label: str, work: Path = WORK):
    """``(ctx, geom, truth, truths_on_grid, r_amb)`` of a kept family store."""
    from schlieren.pipeline import metrics
    from schlieren.storage import synthetic_io as sio
    from schlieren.workers import tasks
    from schlieren.workers.evaluate import _r_ambient, _truth_at
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key

    d = work / case
    ctx = tasks.context(str(d / f"store-{label}.zarr"))
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    truth = sio.read_truth(d / "truth.zarr")
    tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
    t_on = [metrics.resample_space(_truth_at(truth, float(t))[0], tgrid, ctx.session.grid) for t in ctx.times()]
    return ctx, geom, truth, t_on, _r_ambient(truth)


def _blocks(a: np.ndarray, b: int, shape: tuple[int, int]) -> np.ndarray:
    """Means of ``b`` x ``b`` blocks of ``a`` (..., rows, cols, 2) cropped to ``shape`` blocks (NaN-aware)."""
    rows, cols = shape
    a = a[..., : rows * b, : cols * b, :]
    s = a.shape[:-3] + (rows, b, cols, b, a.shape[-1])
    with np.errstate(invalid="ignore"):
        return np.nanmean(a.reshape(s), axis=(-4, -2))


def _gauss(d: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian of ``sigma`` cells over the last-but-one two axes of (rows, cols, 2)."""
    if sigma <= 0:
        return d
    return np.stack([ndimage.gaussian_filter(d[..., i], sigma, mode="nearest") for i in range(2)], axis=-1)


# --------------------------------------------------------------------------------------- decomposition

def _split(err: np.ndarray, truth: np.ndarray, plume: np.ndarray, quiet: np.ndarray, sigmas_cells) -> dict:
    """RMS of ``err`` (n, rows, cols, 2) in plume and quiet cells, and how much of the plume's
    a window average of ``truth`` (``G_s d - d``, fitted scale) and a gain explain."""
    ok = np.isfinite(err).all(axis=-1)
    p, q = plume & ok, quiet & ok
    out = {"plume_rms": float(np.sqrt(np.mean(err[p] ** 2))), "quiet_rms": float(np.sqrt(np.mean(err[q] ** 2))),
           "plume_signal_rms": float(np.sqrt(np.mean(truth[p] ** 2))), "cells_plume": int(p.sum()),
           "cells_quiet": int(q.sum())}
    out["ratio"] = out["plume_rms"] / out["quiet_rms"]
    e = err[p].ravel()
    best = None
    for s in sigmas_cells:
        m = np.stack([_gauss(truth[i], s) for i in range(len(truth))]) - truth
        basis = np.stack([m[p].ravel(), truth[p].ravel()], axis=1)
        coef, *_ = np.linalg.lstsq(basis, e, rcond=None)
        r = e - basis @ coef
        only_w = e - m[p].ravel() * (m[p].ravel() @ e) / max(m[p].ravel() @ m[p].ravel(), 1e-30)
        row = {"sigma_cells": float(s), "window_coef": float(coef[0]), "gain": float(coef[1]),
               "rest_rms": float(np.sqrt(np.mean(r ** 2))), "rest_rms_window_only": float(np.sqrt(np.mean(only_w ** 2))),
               "window_term_rms": float(np.sqrt(np.mean((m[p].ravel() * coef[0]) ** 2)))}
        if best is None or row["rest_rms"] < best["rest_rms"]:
            best = row
    out["fit"] = best
    return out


def _frame_correlation(err: np.ndarray, mask: np.ndarray) -> float:
    """Correlation of the errors of consecutive frames (axis 1) on cells of ``mask`` in both."""
    a, b = err[:, :-1], err[:, 1:]
    m = mask[:, :-1] & mask[:, 1:] & np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
    x, y = a[m].ravel(), b[m].ravel()
    return float(np.corrcoef(x, y)[0, 1]) if x.size > 2 else float("nan")


def decompose(case: str, label: str, work: Path = WORK) -> dict:
    from schlieren.pipeline import sync
    from schlieren.workers.tasks.resample import bad_frames, raw_range, resample_window

    ctx, _, truth, _, _ = load(case, label, work)
    fr = ctx.flow_grid.factor
    tf = int(truth.attrs.get("flow_factor", 3))
    common = fr * tf // math.gcd(fr, tf)
    W, H = ctx.cameras[0].image_size
    shape = (H // common, W // common)
    C = len(ctx.cameras)
    t_first = int(truth.attrs["frames"][0])  # truth frame i <-> absolute raw frame t_first + i
    tdef = np.asarray(truth.group["deflection"][...], np.float64)          # C, K, rows, cols, 2
    trs = np.asarray(truth.group["deflection_rs"][...], np.float64)
    flow = np.asarray(ctx.store.read("flow"), np.float64)                  # C, K, h, w, 2
    raw = np.asarray(ctx.store.read("flow_raw"), np.float64)               # C, J, h, w, 2
    K = flow.shape[1]
    ct = lambda a: _blocks(a, common // tf, shape)   # noqa: E731 - truth grid -> common grid
    cr = lambda a: _blocks(a, common // fr, shape)   # noqa: E731 - run grid -> common grid
    # output instants
    out_err, out_truth = cr(flow) - ct(tdef[:, :K]), ct(tdef[:, :K])
    # raw frames that the truth has (t_first .. t_first + n - 1)
    js = [i for i in range(trs.shape[1]) if 0 <= t_first + i - ctx.raw_first < raw.shape[1]]
    raw_err = np.stack([cr(raw[:, t_first + i - ctx.raw_first]) - ct(trs[:, i]) for i in js], axis=1)
    raw_truth = np.stack([ct(trs[:, i]) for i in js], axis=1)
    # the truth's raw deflections resampled as the run resamples (where the frames it reads are the truth's)
    res_err, res_truth, done = [], [], []
    tgrid = type(ctx.flow_grid)((W, H), tf)
    for k in range(K):
        t = float(ctx.times()[k])
        row_e, row_t = [], []
        for c in range(C):
            window = resample_window(ctx, k)
            excluded = tuple(sorted(set(ctx.flash_frames(c)) | set(bad_frames(ctx, c, window[0], window[1] - 1))))
            lo, hi = raw_range(ctx, c, k, window, excluded)
            if lo < t_first or hi >= t_first + trs.shape[1]:
                break
            rs = sync.resample_flow(trs[c, lo - t_first: hi - t_first + 1], lo, t, offset=ctx.time_offset(c),
                                    frame_rate=ctx.session.frame_rate, line_time=ctx.cameras[c].line_time,
                                    flow_grid=tgrid, excluded_frames=excluded, params=ctx.config.resample)
            row_e.append(ct(rs) - ct(tdef[c, k]))
            row_t.append(ct(tdef[c, k]))
        else:
            res_err.append(np.stack(row_e))
            res_truth.append(np.stack(row_t))
            done.append(k)
    sig_px = np.asarray(ctx.store.read("flow_window", ()), np.float64) * fr   # the run's window model, pixels
    sigmas = sorted({round(s, 3) for s in np.r_[np.median(sig_px) / common * np.array([0.5, 0.75, 1, 1.25, 1.5, 2])]})

    def masks(tr):
        mag = np.hypot(tr[..., 0], tr[..., 1])
        peak = mag.reshape(mag.shape[0], mag.shape[1], -1).max(axis=-1)[..., None, None]
        busy = ndimage.maximum_filter(mag, size=(1, 1, 3, 3), mode="nearest")
        return mag > PLUME_FRACTION * peak, busy < 1e-3

    res = {"case": case, "label": label, "run_factor": fr, "truth_factor": tf, "common_cell_px": common,
           "flow_window_px": [float(x) for x in sig_px], "sigma_scan_cells": sigmas, "parts": {}}
    for name, err, tr in (("raw", raw_err, raw_truth), ("output", out_err, out_truth),
                          ("resampled", np.stack(res_err, 1) if res_err else None,
                           np.stack(res_truth, 1) if res_truth else None)):
        if err is None:
            continue
        plume, quiet = masks(tr)
        e = err.reshape((-1,) + err.shape[2:])
        t = tr.reshape((-1,) + tr.shape[2:])
        part = _split(e, t, plume.reshape(e.shape[:-1]), quiet.reshape(e.shape[:-1]), sigmas)
        part["frames"] = int(err.shape[1])
        if err.shape[1] > 1:
            part["frame_correlation_plume"] = _frame_correlation(err, plume)
            part["frame_correlation_quiet"] = _frame_correlation(err, quiet)
        res["parts"][name] = part
        print(name, json.dumps(part), flush=True)
    res["resampled_frames"] = done
    return res


# --------------------------------------------------------------------------------------- scoring

def score(ctx, grads: dict, t_on, r_amb) -> dict:
    """Integrate each frame's gradient through its hull, scored as the family scores:
    whole box / in plume dB over the frames (RMS over frames of the per-frame RMS)."""
    from schlieren.pipeline import metrics, poisson

    whole, plume = [], []
    for k, g in sorted(grads.items()):
        hull = np.asarray(ctx.store.read("hull", (k,)), bool)
        r, _ = poisson.integrate(np.asarray(g, np.float64), hull, ctx.session.grid,
                                 r_ambient=ctx.session.medium.refractivity_ambient, params=ctx.config.poisson)
        e = np.asarray(r, np.float64)
        whole.append(metrics.relative_rms(e, t_on[k]))
        plume.append(metrics.plume_rms(e, t_on[k], r_amb))
    return {"whole_db": round(metrics.summarise(whole)["psnr"], 2), "plume_db": round(metrics.summarise(plume)["psnr"], 2),
            "frames_plume_db": [round(metrics.psnr(x), 2) for x in plume]}


def solve(ctx, geom, flows_out: dict, *, window_model: bool = True) -> dict:
    """Each output frame's gradient from its flows (C, h, w, 2) on the flow grid, solved as the
    run solves (its parameters, weight and support; from zero)."""
    from schlieren.pipeline import tomography
    from schlieren.workers import tasks
    from schlieren.workers.tasks.tomography import _block_support

    params = tasks.tomo_params(ctx)
    blur = tasks.flow_blur(ctx) if window_model else {}
    out = {}
    for k, fl in sorted(flows_out.items()):
        hull = ctx.store.read("hull", (k,))
        b = tomography.bin_cells(np.asarray(fl, np.float64), ctx.ray_binning)
        g, info = tomography.solve_gradient(geom, b, hull, params=params,
                                            support=_block_support(ctx, k, params.hull_dilation), **blur)
        out[k] = np.asarray(g, np.float32)
    return out


# --------------------------------------------------------------------------------------- refinement

def predict_pixels(ctx, geom, grad: np.ndarray) -> np.ndarray:
    """Each camera's deflection (pixels, (C, H, W, 2)) that the gradient ``grad`` (nz, ny, nx, 3)
    predicts (:func:`~schlieren.pipeline.residuals.predict_flows` on the ray grid), cubic from
    the rays' cells to every pixel (:func:`~schlieren.pipeline.flow.cells_to_pixels`)."""
    from schlieren.pipeline.flow import cells_to_pixels
    from schlieren.pipeline.residuals import predict_flows

    d = predict_flows(geom, ctx.cameras, np.asarray(grad, np.float64), n_ambient=ctx.session.medium.n_ambient)
    return np.stack([cells_to_pixels(d[c], ctx.ray_grid.factor, ctx.cameras[0].image_size) for c in range(len(d))])


def refined_raw_flow(ctx, c: int, f: int, pred: np.ndarray | None, **override) -> np.ndarray:
    """Camera ``c``'s flow at raw frame ``f`` as the deflection task computes it (its capture
    correction), plain or around the prediction ``pred`` (pixels, (H, W, 2);
    :func:`~schlieren.pipeline.flow.refined_deflection`)."""
    from schlieren.pipeline import capture
    from schlieren.pipeline.flow import refined_deflection
    from schlieren.workers.tasks.capture import defective_pixels, static_region
    from schlieren.workers.tasks.deflection import flow_params

    params = dataclasses.replace(flow_params(ctx, c), **override)

    def flow(prep, img, p):
        return capture.corrected_deflection(prep, img, p, ctx.config.capture, static=static_region(ctx, c),
                                            defects=defective_pixels(ctx, c))[0]

    prep = ctx.prepared_reference(c, None)
    if pred is None:
        return flow(prep, ctx.frame(c, f), params)
    return refined_deflection(prep, ctx.frame(c, f), pred, params, deflection=flow)


def resampled(ctx, c: int, k: int, raw_of) -> np.ndarray:
    """Camera ``c``'s flow at output instant ``k`` from the raw flows ``raw_of(f)``, as
    :func:`~schlieren.workers.tasks.resample.resample_task` resamples."""
    from schlieren.pipeline import sync
    from schlieren.workers.tasks.resample import bad_frames, raw_range, resample_window

    window = resample_window(ctx, k)
    excluded = tuple(sorted(set(ctx.flash_frames(c)) | set(bad_frames(ctx, c, window[0], window[1] - 1))))
    lo, hi = raw_range(ctx, c, k, window, excluded)
    raw = np.stack([raw_of(f) for f in range(lo, hi + 1)])
    return sync.resample_flow(raw, lo, float(ctx.times()[k]), offset=ctx.time_offset(c),
                              frame_rate=ctx.session.frame_rate, line_time=ctx.cameras[c].line_time,
                              flow_grid=ctx.flow_grid, excluded_frames=excluded, params=ctx.config.resample)


def flow_errors(ctx, truth, flows_out: dict) -> dict:
    """RMS of output flows against the truth's deflections (common grid), in plume / quiet."""
    fr = ctx.flow_grid.factor
    tf = int(truth.attrs.get("flow_factor", 3))
    common = fr * tf // math.gcd(fr, tf)
    W, H = ctx.cameras[0].image_size
    shape = (H // common, W // common)
    tdef = np.asarray(truth.group["deflection"][...], np.float64)
    e, t = [], []
    for k, fl in sorted(flows_out.items()):
        e.append(_blocks(np.asarray(fl, np.float64), common // fr, shape) - _blocks(tdef[:, k], common // tf, shape))
        t.append(_blocks(tdef[:, k], common // tf, shape))
    e, t = np.concatenate(e), np.concatenate(t)
    mag = np.hypot(t[..., 0], t[..., 1])
    peak = mag.reshape(mag.shape[0], -1).max(axis=1)[:, None, None]
    plume = mag > PLUME_FRACTION * peak
    quiet = ndimage.maximum_filter(mag, size=(1, 3, 3), mode="nearest") < 1e-3
    ok = np.isfinite(e).all(-1)
    return {"plume_rms": float(np.sqrt(np.mean(e[plume & ok] ** 2))),
            "quiet_rms": float(np.sqrt(np.mean(e[quiet & ok] ** 2)))}


def residual_data(ctx, geom, flows: dict, grads: dict) -> dict:
    """Refined flows made consistent with the flow-window model: ``refined - S x + S G x``
    (``x`` the gradient predicted from, ``G`` the run's volume blur), on the flow grid (ray
    binning 1) so that the window model blurs the prediction and leaves the residual as measured."""
    from schlieren.pipeline.residuals import predict_flows
    from schlieren.pipeline.tomography.blur import VolumeBlur
    from schlieren.workers import tasks

    assert ctx.ray_binning == 1, "residual_data works on the flow grid"
    sigma = tasks.flow_blur(ctx)["volume_blur"]
    n = ctx.session.medium.n_ambient
    out = {}
    for k, fl in flows.items():
        x = np.asarray(grads[k], np.float64)
        gx = VolumeBlur(np.ones(x.shape[:3], bool), sigma).apply(x.reshape(-1, 3)).reshape(x.shape)
        p = np.nan_to_num(predict_flows(geom, ctx.cameras, x, n_ambient=n))
        pg = np.nan_to_num(predict_flows(geom, ctx.cameras, gx, n_ambient=n))
        out[k] = np.asarray(fl, np.float64) - p + pg
    return out


def refine(case: str, label: str, work: Path = WORK, passes: int = 1, window_model: bool = True,
           variant: str = "plain") -> dict:
    ctx, geom, truth, t_on, r_amb = load(case, label, work)
    C, K = len(ctx.cameras), len(ctx.times())
    run_flows = {k: np.stack([np.asarray(ctx.store.read("flow", (c, k)), np.float64) for c in range(C)])
                 for k in range(K)}
    rows = {}
    run_grads = {k: np.asarray(ctx.store.read("gradient", (k,)), np.float64) for k in range(K)}
    rows["run (stored solve)"] = score(ctx, run_grads, t_on, r_amb)
    rows["run flows, solved here"] = {**score(ctx, solve(ctx, geom, run_flows), t_on, r_amb),
                                      "flow": flow_errors(ctx, truth, run_flows)}
    rows["run flows, solved here, no window model"] = score(ctx, solve(ctx, geom, run_flows, window_model=False),
                                                            t_on, r_amb)
    print(rows, flush=True)
    grads = run_grads
    for p in range(1, passes + 1):
        preds = {k: predict_pixels(ctx, geom, grads[k]) for k in range(K)}
        pc = {k: np.stack([_blocks(preds[k][c][None], ctx.flow_grid.factor, tuple(ctx.flow_grid.shape))[0]
                           for c in range(C)]) for k in range(K)}
        rows[f"prediction pass {p} (no flow)"] = {"flow": flow_errors(ctx, truth, pc)}
        print(rows[f"prediction pass {p} (no flow)"], flush=True)
        cache: dict = {}

        def raw_of(c, f, k):  # as one frame's task computes them: every raw frame from frame k's prediction
            if (c, f, k) not in cache:
                cache[(c, f, k)] = refined_raw_flow(ctx, c, f, preds[k][c])
            return cache[(c, f, k)]

        t0 = time.process_time()
        flows = {k: np.stack([resampled(ctx, c, k, lambda f, c=c, k=k: raw_of(c, f, k)) for c in range(C)])
                 for k in range(K)}
        cpu = time.process_time() - t0
        fe = flow_errors(ctx, truth, flows)
        if variant == "residual":  # the window model on the residual only: b = refined - S x + S G x
            g = solve(ctx, geom, residual_data(ctx, geom, flows, grads), window_model=True)
            name = f"refined pass {p}, window model on the residual"
            rows[name] = {**score(ctx, g, t_on, r_amb), "flow": fe, "flows": len(cache),
                          "flow_cpu_s_per_raw_flow": round(cpu / max(len(cache), 1), 3)}
            print(name, rows[name], flush=True)
            grads = g
            continue
        for wm in ((True, False) if window_model else (False,)):
            g = solve(ctx, geom, flows, window_model=wm)
            name = f"refined pass {p}" + ("" if wm else ", no window model")
            rows[name] = {**score(ctx, g, t_on, r_amb), "flow": fe, "flows": len(cache),
                          "flow_cpu_s_per_raw_flow": round(cpu / max(len(cache), 1), 3)}
            if not wm:  # the next pass predicts from the solve without the window model (the better one)
                grads_next = g
            print(name, rows[name], flush=True)
        grads = grads_next
    return {"case": case, "label": label, "rows": rows}


# --------------------------------------------------------------------------------------- synthetic frames

def synthetic(case: str, label: str, work: Path = WORK, frame: int = 1, noise: float = 1.5, seed: int = 0,
              cameras: int = 16) -> dict:
    """The run's flow on frames made by warping each camera's reference by the truth's
    deflection (cubic from its cells to the pixels; exact B-spline warp), without and with
    sensor noise (8-bit rounding): its error against that field's cell means splits into the
    flow's own bias (noise-free) and noise, in plume and where nothing flows; and the
    refined flow (reference warped by a prediction, residual flow, prediction added back)
    with the exact field and with the field blurred (a reconstruction's resolution)."""
    from schlieren.pipeline.flow import cells_to_pixels
    from schlieren.pipeline.flow.post import _block_mean
    from schlieren.pipeline.flow.splines import warp_image

    ctx, _, truth, _, _ = load(case, label, work)
    rng = np.random.default_rng(seed)
    fr = ctx.flow_grid.factor
    tf = int(truth.attrs.get("flow_factor", 3))
    size = ctx.cameras[0].image_size
    tdef = np.asarray(truth.group["deflection"][:, frame], np.float64)
    rows, cols = ctx.flow_grid.shape
    sig_px = [1.0, 1.5, 2.0, 2.5, 3.0]
    acc: dict = {}

    def cells(px):
        return np.stack([_block_mean(np.ascontiguousarray(px[..., i], dtype=np.float32), fr, (rows, cols))
                         for i in range(2)], axis=-1).astype(np.float64)

    for c in range(min(cameras, len(ctx.cameras))):
        d = cells_to_pixels(tdef[c], tf, size)
        target = cells(d)
        prep = ctx.prepared_reference(c, None)
        ref = np.where(np.isfinite(prep.image), prep.image, np.float32(prep.mean)).astype(np.float32)
        clean = warp_image(ref, d)
        noisy = np.clip(np.round(clean + rng.normal(scale=noise, size=clean.shape)), 0, 255).astype(np.float32)
        mag = np.hypot(target[..., 0], target[..., 1])
        plume = mag > PLUME_FRACTION * mag.max()
        quiet = ndimage.maximum_filter(mag, size=3, mode="nearest") < 1e-3
        win = {s: cells(np.stack([cv2.GaussianBlur(d[..., i], (0, 0), s) for i in range(2)], -1)) - target
               for s in sig_px}
        plain = {}
        variants = ((("clean", clean, None), ("noisy", noisy, None), ("clean, refined exact", clean, d),
                     ("noisy, refined exact", noisy, d))
                    + tuple((f"{n}, refined blurred {b:g} px", img, cv2.GaussianBlur(d, (0, 0), b))
                            for b in (1.0, 2.0, 4.0) for n, img in (("clean", clean), ("noisy", noisy)))
                    + (("clean, refined by itself", clean, "clean"), ("noisy, refined by itself", noisy, "noisy"))
                    + tuple((f"{n}, window {w} px", img, {"window": w}) for w in (5, 7)
                            for n, img in (("clean", clean), ("noisy", noisy))))
        for name, img, pred in variants:
            override = {}
            if isinstance(pred, str):  # the plain flow of the same frame, cubic to the pixels
                pred = cells_to_pixels(plain[pred], fr, size)
            elif isinstance(pred, dict):
                override, pred = pred, None
            f = _flow_against(ctx, c, img, pred, **override)
            if name in ("clean", "noisy"):
                plain[name] = f
            e = f - target
            a = acc.setdefault(name, {"e_p": [], "e_q": [], "t_p": [], "w_p": {s: [] for s in sig_px}})
            ok = np.isfinite(e).all(-1)
            a["e_p"].append(e[plume & ok])
            a["e_q"].append(e[quiet & ok])
            a["t_p"].append(target[plume & ok])
            for s in sig_px:
                a["w_p"][s].append(win[s][plume & ok])
    out = {"case": case, "frame": frame, "noise": noise, "cameras": min(cameras, len(ctx.cameras)), "rows": {}}
    for name, a in acc.items():
        ep, eq, tp = (np.concatenate(a[k]).ravel() for k in ("e_p", "e_q", "t_p"))
        row = {"plume_rms": float(np.sqrt(np.mean(ep ** 2))), "quiet_rms": float(np.sqrt(np.mean(eq ** 2))),
               "gain": float(ep @ tp / (tp @ tp)), "signal_rms": float(np.sqrt(np.mean(tp ** 2)))}
        best = None
        for s in sig_px:
            m = np.concatenate(a["w_p"][s]).ravel()
            basis = np.stack([m, tp], 1)
            coef, *_ = np.linalg.lstsq(basis, ep, rcond=None)
            r = float(np.sqrt(np.mean((ep - basis @ coef) ** 2)))
            corr = float(np.corrcoef(m, ep)[0, 1])
            if best is None or r < best["rest_rms"]:
                best = {"sigma_px": s, "window_coef": float(coef[0]), "gain_coef": float(coef[1]), "rest_rms": r,
                        "corr_window_term": corr, "window_term_rms": float(np.sqrt(np.mean(m ** 2)))}
        row["fit"] = best
        out["rows"][name] = row
        print(name, json.dumps(row), flush=True)
    return out


def _flow_against(ctx, c: int, frame: np.ndarray, pred, **override) -> np.ndarray:
    """:func:`refined_raw_flow` on a given frame image instead of a raw frame."""
    orig = ctx.frame
    try:
        ctx.frame = lambda cc, ff: frame
        return refined_raw_flow(ctx, c, -1, pred, **override).astype(np.float64)
    finally:
        ctx.frame = orig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("decompose", "refine", "window", "synthetic"))
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--case", default="plume1-16cam-640")
    ap.add_argument("--label", default="i35f_base")
    ap.add_argument("--work", default=str(WORK))
    ap.add_argument("--passes", type=int, default=1)
    ap.add_argument("--variant", choices=("plain", "residual"), default="plain",
                    help="refine: solve the refined flows without the window model (plain; with --no-window-model) "
                         "or with it on the residual only (refined - S x + S G x)")
    ap.add_argument("--no-window-model", action="store_true",
                    help="refine: solve the refined flows without the flow-window model only")
    ap.add_argument("--name", default="flow_refinement")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    res_dir = Path(args.results)
    path = res_dir / f"{args.name}.json"
    db = json.loads(path.read_text()) if path.exists() else {"runs": {}}
    t0 = time.perf_counter()
    if args.what == "decompose":
        out = decompose(args.case, args.label, Path(args.work))
    elif args.what == "refine":
        out = refine(args.case, args.label, Path(args.work), args.passes, window_model=not args.no_window_model,
                     variant=args.variant)
    elif args.what == "synthetic":
        out = synthetic(args.case, args.label, Path(args.work), cameras=args.cameras)
    else:
        raise SystemExit("not yet")
    out["seconds"] = round(time.perf_counter() - t0, 1)
    out["command"] = "python benchmarks/flow_refinement.py " + " ".join(argv if argv is not None else sys.argv[1:])
    key = f"{args.what}:{args.case}:{args.label}"
    if args.what == "refine":
        key += f":p{args.passes}" + (":residual" if args.variant == "residual" else "")
    db["runs"][key] = out
    res_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(db, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
