"""How far each realistic-family case is from what its tomography could reach (issue 14).

    python benchmarks/realistic_bounds.py [--work /work/realistic/work] [--cases a,b] [--frame 1]

Reads the stores ``schlieren bench realistic --out WORK`` keeps (``WORK/<case>/store.zarr``,
the default parameters' run, with its geometry cache, and the case's ``truth.zarr``) and, for
one output frame, reconstructs from data whose errors are known:

* ``exact gradient``: the truth's own gradient (on the run's grid) integrated through the
  run's hull: the integration's bound;
* ``consistent``: rays ``b = S x`` from the truth's gradient ``x`` with the run's own
  projection ``S`` (no optical flow, no exit-direction or window model error, no noise),
  solved converged (tol 1e-4, up to 200 iterations) at the run's weight, through the run's
  hull and through the truth's plume dilated by 2 voxels: what the prior and the views allow;
* ``consistent + noise``: the same rays plus white noise of the run's measured ``rhs_noise``,
  solved as the run solves (its iterations): the bound for the run's noise level were the
  flow's error white;
* ``consistent, via the truth's ray grid`` and ``truth's exit directions``: the consistent
  rays sampled at the truth's ray grid and interpolated back, and the curved-ray tracer's own
  exit directions (``truth.zarr``'s ``d_out - d_in``) interpolated the same way to the run's
  rays, both solved as the run solves without the window model: their difference is what the
  traced data lack against the model's rays from the scored truth, free of the
  interpolation's (mostly the tracer's central-difference gradient on the truth's grid:
  ``benchmarks/realistic_forward_model.py``);
* ``window model + quiet-ray noise``: the window model's rays ``S G x`` (``G`` the run's
  volume blur) plus noise of the RMS the run's flows have on the rays that miss the plume,
  correlated over one flow cell, solved as the run solves (with its window model): the
  bound were the flow's error the same inside the plume as outside;
* ``run``: the run's own flows with its flow-window model, as the run solves them.

It also compares the run's rays with the window model's prediction ``S G x`` (``G`` the
run's volume blur): their gain and the RMS of the residual on the rays that see the plume
(more than 10 % of the largest model ray) against the noise measured outside the masks.

Writes ``benchmarks/results/realistic_bounds.json`` and ``.md``. Scores are the family's:
relative RMS over the whole box and over the plume (|truth - ambient| > 1 % of its range),
as PSNR, on the run's grid.
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

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CASES = ("plume1-16cam-640", "plume1-8cam-960-dist", "jet3-16cam-640", "jet3-8cam-960-dist")


def load_case(case_dir: Path, frame: int):
    """A kept family store's run context, its geometry, and the truth's refractivity at
    output frame ``frame`` on the run's grid with its ambient value: ``(ctx, geom, t_on, r_amb)``."""
    from schlieren.pipeline import metrics
    from schlieren.storage import synthetic_io as sio
    from schlieren.workers import tasks
    from schlieren.workers.evaluate import _r_ambient, _truth_at
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key

    ctx = tasks.context(str(case_dir / "store.zarr"))
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    truth = sio.read_truth(case_dir / "truth.zarr")
    tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
    tv, _ = _truth_at(truth, float(ctx.times()[int(frame)]))
    return ctx, geom, metrics.resample_space(tv, tgrid, ctx.session.grid), _r_ambient(truth)


def integrate_and_score(ctx, grad, hull, t_on, r_amb) -> tuple[float, float]:
    """The run's integration of gradient ``grad`` through ``hull``, scored against ``t_on``
    as the family scores: ``(whole box dB, in plume dB)``, rounded to 0.01."""
    from schlieren.pipeline import metrics, poisson

    r, _ = poisson.integrate(grad, hull, ctx.session.grid, r_ambient=ctx.session.medium.refractivity_ambient,
                             params=ctx.config.poisson)
    e = np.asarray(r, dtype=np.float64)
    return (round(metrics.psnr(metrics.relative_rms(e, t_on)), 2),
            round(metrics.psnr(metrics.plume_rms(e, t_on, r_amb)), 2))


def bounds(case_dir: Path, frame: int) -> dict:
    from scipy import ndimage

    from schlieren.pipeline import metrics, tomography
    from schlieren.pipeline.tomography.blur import VolumeBlur
    from schlieren.workers import tasks

    k = int(frame)
    ctx, geom, t_on, r_amb = load_case(case_dir, k)
    grid = ctx.session.grid
    gz, gy, gx = np.gradient(t_on, grid.voxel_size)
    x = np.stack([gx, gy, gz], axis=-1)
    xf = x.reshape(-1, 3)
    b = np.stack([geom.S @ xf[:, i] for i in range(3)], axis=-1).reshape(tuple(geom.flow_shape) + (3,))
    params = tasks.tomo_params(ctx)
    converged = dataclasses.replace(params, max_iter=200, tol=1e-4)
    hull = ctx.store.read("hull", (k,))
    truth_hull = ndimage.binary_dilation(metrics.plume_mask(t_on, r_amb), iterations=2)
    noise = np.asarray(ctx.store.read("rhs_noise", ()), dtype=np.float64)
    def score(grad, h) -> dict:
        whole, plume = integrate_and_score(ctx, grad, h, t_on, r_amb)
        return {"whole_db": whole, "plume_db": plume}

    rows = {"exact gradient, run hull": score(x, hull)}
    for name, h in (("consistent, run hull", hull), ("consistent, truth hull", truth_hull)):
        g, info = tomography.solve_gradient(geom, b, h, params=converged)
        rows[name] = {**score(g, h), "iterations": info.iterations}
    rng = np.random.default_rng(0)
    g, info = tomography.solve_gradient(geom, b + rng.normal(size=b.shape) * noise, hull, params=params)
    rows["consistent + white noise, run solve"] = {**score(g, hull), "iterations": info.iterations}
    # the truth's own exit directions (the curved-ray tracer's, at its ray grid's cell centres),
    # interpolated to the run's rays: no flow, no noise, no window model; and the consistent rays
    # through the same sampling and back, which prices that interpolation alone
    import zarr

    tz = zarr.open_group(str(case_dir / "truth.zarr"), mode="r")
    dd = (np.asarray(tz["d_out"][:, k], np.float32) - np.asarray(tz["d_in"][:, k], np.float32)) * params.n_ambient
    back = np.zeros_like(b)
    exact = np.zeros_like(b)
    height = ctx.cameras[0].height
    fr, ft = height / b.shape[1], height / dd.shape[1]  # pixels per run ray / per truth ray
    run_c = [(np.arange(n) * fr + (fr - 1) / 2.0) for n in b.shape[1:3]]  # run ray centres, pixels
    tru_c = [(np.arange(n) * ft + (ft - 1) / 2.0) for n in dd.shape[1:3]]
    ty, tx = np.meshgrid(*[((t - (fr - 1) / 2.0) / fr).astype(np.float32) for t in tru_c], indexing="ij")
    ry, rx = np.meshgrid(*[((r - (ft - 1) / 2.0) / ft).astype(np.float32) for r in run_c], indexing="ij")
    for c in range(b.shape[0]):
        for i in range(3):
            at_truth = cv2.remap(b[c, ..., i].astype(np.float32), tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            back[c, ..., i] = cv2.remap(at_truth, rx, ry, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            exact[c, ..., i] = cv2.remap(dd[c, ..., i], rx, ry, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    g, info = tomography.solve_gradient(geom, back, hull, params=params)
    rows["consistent, via the truth's ray grid, run solve"] = {**score(g, hull), "iterations": info.iterations}
    g, info = tomography.solve_gradient(geom, exact, hull, params=params)
    rows["truth's exit directions, run solve"] = {**score(g, hull), "iterations": info.iterations}
    flows = ctx.tomography_flows(k)
    blur = tasks.flow_blur(ctx)
    g, info = tomography.solve_gradient(geom, flows, hull, params=params, **blur)
    run = {**score(g, hull), "iterations": info.iterations}

    # the run's rays against the window model's prediction of them
    bf = tomography.rhs_from_flows(geom, flows, n_ambient=params.n_ambient).reshape(-1, 3)
    if "volume_blur" in blur:
        xg = VolumeBlur(np.ones(grid.shape, bool), blur["volume_blur"]).apply(xf)
        model = np.stack([geom.S @ xg[:, i] for i in range(3)], axis=-1)
    else:  # pragma: no cover - the family's runs use the volume model
        model = b.reshape(-1, 3)
    ok = np.all(np.isfinite(bf), axis=1)
    strength = np.abs(model).max(axis=1)
    seen = ok & (strength > 0.1 * strength.max())
    quiet = np.sqrt(np.mean(bf[ok & (strength == 0)] ** 2, axis=0))
    # the window model's own rays with noise like the run's quiet rays: its RMS, correlated
    # over one flow cell (the LK window's reach on the flow grid), solved as the run solves
    n = rng.normal(size=b.shape)
    for c in range(n.shape[0]):
        for i in range(3):
            n[c, ..., i] = cv2.GaussianBlur(n[c, ..., i], (0, 0), 1.0)
    n *= quiet / n.reshape(-1, 3).std(axis=0)
    g, info = tomography.solve_gradient(geom, model.reshape(b.shape) + n, hull, params=params, **blur)
    rows["window model + quiet-ray noise (1 cell), run solve"] = {**score(g, hull), "iterations": info.iterations}
    rows["run: flows and window model"] = run
    rays = []
    for i in range(3):
        gain = float(bf[ok, i] @ model[ok, i] / (model[ok, i] @ model[ok, i]))
        rays.append({"gain": round(gain, 3),
                     "plume_ray_signal_rms": float(np.sqrt(np.mean(model[seen, i] ** 2))),
                     "plume_ray_residual_rms": float(np.sqrt(np.mean((bf[seen, i] - model[seen, i]) ** 2))),
                     "quiet_ray_residual_rms": float(np.sqrt(np.mean((bf[ok & (strength == 0), i]) ** 2))),
                     "rhs_noise": float(noise[i])})
    return {"frame": k, "reg_weight": params.reg_weight, "rows": rows, "rays": rays}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default="/work/realistic/work", help="the family's --out folder")
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES))
    ap.add_argument("--frame", type=int, default=1, help="output frame scored (the family's middle one)")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    out: dict = {"command": "python benchmarks/realistic_bounds.py " + " ".join(argv or sys.argv[1:]),
                 "cases": {}}
    for case in [c for c in args.cases.split(",") if c]:
        d = Path(args.work) / case
        if not (d / "store.zarr").exists():
            raise SystemExit(f"{d / 'store.zarr'}: missing; run `schlieren bench realistic --out {args.work} "
                             f"--cases {case}` first")
        t0 = time.perf_counter()
        out["cases"][case] = bounds(d, args.frame)
        out["cases"][case]["seconds"] = round(time.perf_counter() - t0, 1)
        print(case, json.dumps(out["cases"][case]["rows"]), flush=True)
    res = Path(args.results)
    res.mkdir(parents=True, exist_ok=True)
    (res / "realistic_bounds.json").write_text(json.dumps(out, indent=1))
    (res / "realistic_bounds.md").write_text(render(out))
    return 0


def render(out: dict) -> str:
    names = list(next(iter(out["cases"].values()))["rows"])
    lines = ["# Realistic family: what each case's tomography could reach", "",
             f"Command: `{out['command'].strip()}` (see its docstring). One output frame per case, "
             "whole box / in plume dB on the run's grid.", "",
             "| case | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for case, r in out["cases"].items():
        cells = [f"{r['rows'][n]['whole_db']:.2f} / {r['rows'][n]['plume_db']:.2f}" for n in names]
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    lines += ["", "The run's rays against the window model's prediction `S G x` (x component; "
              "rays that see the plume: above 10 % of the largest model ray):", "",
              "| case | weight | gain | plume-ray signal RMS | plume-ray residual RMS | quiet-ray RMS | "
              "rhs_noise |", "|---|---:|---:|---:|---:|---:|---:|"]
    for case, r in out["cases"].items():
        x = r["rays"][0]
        lines.append(f"| {case} | {r['reg_weight']:.4g} | {x['gain']:.3f} | {x['plume_ray_signal_rms']:.3g} | "
                     f"{x['plume_ray_residual_rms']:.3g} | {x['quiet_ray_residual_rms']:.3g} | {x['rhs_noise']:.3g} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
