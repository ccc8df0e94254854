"""What space-time reconstruction could reach on each realistic-family case, and why (issue 35).

    python benchmarks/spacetime_bounds.py [--work /work/realistic] [--label i35st] [--cases a,b] [--frame 3]

Reads the stores ``schlieren bench spacetime --out WORK --label LABEL --keep-stores`` keeps
(``WORK/<case>-f7/store-st-LABEL.zarr``: the per-frame solve in ``gradient_frame``, the
space-time one in ``gradient``) and the case's ``truth.zarr``, and for one output frame
``k`` (default the middle one) scores, whole box / in plume, on the run's grid:

* ``per-frame`` and ``space-time``: the run's per-frame solve and the space-time mean of
  its window (``--window``, default the run's);
* ``space-time, the truth's motion``: the same mean, the motion estimated (by the same
  estimator) on the truth's gradients instead of the per-frame solutions: what a better
  motion estimate could add;
* ``advection model +-d``: the truth at frame ``k + d`` moved onto frame ``k`` along that
  motion, against the truth at ``k`` (in plume): how well a motion describes the flow's
  change over ``d`` frames. An averaged neighbour brings this error with it;
* ``window-model rays, no error``: the per-frame solve of frame ``k`` from the rays the
  tomography's model predicts from the truth (``S G x``: no optical flow, no noise), as the
  run solves: the ceiling of any averaging of the data's errors at the run's weight and
  iterations;
* ``... converged, weight / 100``: the same rays solved to convergence (200 iterations) at
  a hundredth of the weight: what the views and the prior allow once the data's errors are
  gone;
* ``window-model rays + quiet-ray noise / sqrt(n)``: those rays plus noise of the run's
  measured level on the rays that miss the plume (correlated over one flow cell), divided
  by ``sqrt(n)`` for ``n`` = 1 and the window's frame count: independent errors averaged
  over the window with a perfect motion.

Writes ``benchmarks/results/spacetime_bounds.json`` and ``.md``. See
``benchmarks/realistic_bounds.py`` for the per-frame bounds of the 3-frame runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from realistic_bounds import integrate_and_score  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CASES = ("plume1-16cam-640", "plume1-8cam-960-dist", "plume2-16cam-640", "plume2-8cam-960-dist",
                 "jet3-16cam-640", "jet3-8cam-960-dist")


def load(store: Path):
    """The run context of a kept store, its geometry, and the truth at every output frame
    on the run's grid with its ambient value."""
    from schlieren.pipeline import metrics
    from schlieren.storage import synthetic_io as sio
    from schlieren.workers import tasks
    from schlieren.workers.evaluate import _r_ambient, _truth_at
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key

    ctx = tasks.context(str(store))
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    truth = sio.read_truth(store.parent / "truth.zarr")
    tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
    vols = [metrics.resample_space(_truth_at(truth, float(t))[0], tgrid, ctx.session.grid) for t in ctx.times()]
    return ctx, geom, vols, _r_ambient(truth)


def _gradient(ctx, r):
    gz, gy, gx = np.gradient(r, ctx.session.grid.voxel_size)
    return np.stack([gx, gy, gz], axis=-1).astype(np.float32)


def bounds(store: Path, k: int | None, window: int | None = None) -> dict:
    from schlieren.pipeline import metrics, spacetime, tomography
    from schlieren.pipeline.spacetime.average import _motion
    from schlieren.pipeline.tomography.blur import VolumeBlur
    from schlieren.pipeline.tomography.solve import basis_set
    from schlieren.workers import tasks

    ctx, geom, truth, r_amb = load(store)
    F = ctx.n_frames
    k = F // 2 if k is None else int(k)
    st = ctx.config.spacetime if window is None else dataclasses.replace(ctx.config.spacetime, window=int(window))
    frames = list(spacetime.window_frames(k, F, st.window))
    hull = ctx.store.read("hull", (k,))
    support = basis_set(hull, ctx.config.tomography.hull_dilation)
    params = tasks.tomo_params(ctx)
    blur = tasks.flow_blur(ctx)

    def score(grad) -> dict:
        whole, plume = integrate_and_score(ctx, grad, hull, truth[k], r_amb)
        return {"whole_db": whole, "plume_db": plume}

    per = [ctx.store.read("gradient_frame", (j,)) for j in frames]
    offsets = [j - k for j in frames]
    region = tomography.block_support([ctx.store.read("hull", (j,)) for j in frames], ctx.config.tomography.hull_dilation)
    rows = {"per-frame": score(per[frames.index(k)]),
            "space-time": score(spacetime.motion_compensated_mean(per, offsets, support, params=st, region=region)[0])}
    tg = {j: _gradient(ctx, truth[j]) for j in frames}
    # the same mean with the motion estimated on the truth
    box = spacetime.support_box(region | support)
    acc = np.zeros(support.shape + (3,), np.float32)
    w = spacetime.window_weights([j - k for j in frames], st.neighbour_weight)
    advection = {}
    for wj, j, v in zip(w, frames, per):
        if j == k:
            acc[box] += wj * v[box]
            continue
        u = _motion(np.ascontiguousarray(tg[k][box]), np.ascontiguousarray(tg[j][box]), st)
        acc[box] += wj * spacetime.warp_volume(np.asarray(v)[box], u, order=3, scale=st.motion_scale)
        moved = truth[k].copy()
        moved[box] = spacetime.warp_volume(truth[j][box], u, order=3, scale=st.motion_scale)
        advection[f"advection model {j - k:+d}"] = round(metrics.psnr(metrics.plume_rms(moved, truth[k], r_amb)), 2)
    acc[~support] = 0.0
    rows["space-time, the truth's motion"] = score(acc)
    # the tomography's model rays from the truth
    x = tg[k].reshape(-1, 3)
    xg = VolumeBlur(np.ones(ctx.session.grid.shape, bool), blur["volume_blur"]).apply(x) if "volume_blur" in blur else x
    model = np.stack([geom.S @ xg[:, i] for i in range(3)], axis=-1).reshape(tuple(geom.flow_shape) + (3,))
    g, _ = tomography.solve_gradient(geom, model, hull, params=params, **blur)
    rows["window-model rays, no error, run solve"] = score(g)
    converged = dataclasses.replace(params, reg_weight=params.reg_weight / 100, max_iter=200, tol=1e-5)
    g, _ = tomography.solve_gradient(geom, model, hull, params=converged, **blur)
    rows["window-model rays, no error, converged, weight / 100"] = score(g)
    # independent noise of the run's quiet-ray level, averaged over n frames
    bf = tomography.rhs_from_flows(geom, ctx.tomography_flows(k), n_ambient=params.n_ambient).reshape(-1, 3)
    ok = np.all(np.isfinite(bf), axis=1)
    quiet = ok & (np.abs(model.reshape(-1, 3)).max(axis=1) == 0)
    q = np.sqrt(np.mean(bf[quiet] ** 2, axis=0))
    rng = np.random.default_rng(0)
    n = rng.normal(size=model.shape)
    for c in range(n.shape[0]):
        for i in range(3):
            n[c, ..., i] = cv2.GaussianBlur(n[c, ..., i], (0, 0), 1.0)
    n *= q / n.reshape(-1, 3).std(axis=0)
    for m in sorted({1, len(frames)}):
        g, _ = tomography.solve_gradient(geom, model + n / np.sqrt(m), hull, params=params, **blur)
        rows[f"window-model rays + quiet-ray noise / sqrt({m}), run solve"] = score(g)
    return {"frame": k, "frames": frames, "window": st.window, "reg_weight": params.reg_weight, "rows": rows,
            "advection_plume_db": advection}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default="/work/realistic", help="the family's --out folder")
    ap.add_argument("--label", default="", help="the spacetime bench's --label (store-st-LABEL.zarr)")
    ap.add_argument("--frames", type=int, default=7, help="frames of the cases (<case>-f<frames>)")
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES))
    ap.add_argument("--frame", type=int, default=None, help="output frame scored (default the middle one)")
    ap.add_argument("--window", type=int, default=None, help="space-time window (default the run's)")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    out: dict = {"command": "python benchmarks/spacetime_bounds.py " + " ".join(argv or sys.argv[1:]), "cases": {}}
    name = f"store-st{('-' + args.label) if args.label else ''}.zarr"
    for case in [c for c in args.cases.split(",") if c]:
        store = Path(args.work) / f"{case}-f{args.frames}" / name
        if not store.exists():
            print(f"{store}: missing (schlieren bench spacetime --out {args.work} --cases {case} --keep-stores); "
                  "skipped", flush=True)
            continue
        t0 = time.perf_counter()
        out["cases"][case] = bounds(store, args.frame, args.window)
        out["cases"][case]["seconds"] = round(time.perf_counter() - t0, 1)
        print(case, json.dumps(out["cases"][case]["rows"]), flush=True)
    res = Path(args.results)
    res.mkdir(parents=True, exist_ok=True)
    (res / "spacetime_bounds.json").write_text(json.dumps(out, indent=1))
    (res / "spacetime_bounds.md").write_text(render(out))
    return 0


def render(out: dict) -> str:
    if not out["cases"]:
        return "# Space-time bounds\n\nNo case measured.\n"
    names = list(next(iter(out["cases"].values()))["rows"])
    lines = ["# Realistic family: what space-time reconstruction could reach", "",
             f"Command: `{out['command'].strip()}` (see its docstring). The middle output frame of each case's "
             "7-frame run, whole box / in plume dB on the run's grid.", "",
             "| case | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for case, r in out["cases"].items():
        lines.append(f"| {case} | " + " | ".join(f"{r['rows'][n]['whole_db']:.2f} / {r['rows'][n]['plume_db']:.2f}"
                                              for n in names) + " |")
    lines += ["", "How well the truth's motion describes its change (the truth at frame k + d moved onto frame k "
              "along the motion estimated on the truth, against the truth at k; in plume dB):", "",
              "| case | " + " | ".join(next(iter(out["cases"].values()))["advection_plume_db"]) + " |",
              "|---|" + "---:|" * len(next(iter(out["cases"].values()))["advection_plume_db"])]
    for case, r in out["cases"].items():
        lines.append(f"| {case} | " + " | ".join(f"{v:.2f}" for v in r["advection_plume_db"].values()) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
