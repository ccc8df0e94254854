"""The tomography's forward model against the curved-ray tracer, on the realistic family.

    python benchmarks/realistic_forward_model.py [--work /work/realistic/work] [--cases a,b]
        [--frame 1] [--prune P]

For each case, builds the projection ``S`` for rays through the truth's own ray grid (the
flow-cell centres at which ``truth.zarr`` stores the tracer's exit directions), so nothing
is interpolated, and compares, on the rays that see the plume (above 10 % of the largest):

* the model's rays ``S x`` with ``x`` the gradient of the truth resampled to the run's grid
  (as ``realistic_bounds.py``'s consistent rays), and with ``x`` the truth's own
  central-difference gradient on its native grid, resampled (what the tracer interpolates);
* the tracer's ``n_amb (d_out - d_in)``.

It reports their gain and the relative residual per component, and solves both right-hand
sides as the run solves (the run's hull and weight, no window model): the dB between them is
the forward model's error. Writes ``benchmarks/results/realistic_forward_model.md`` / ``.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def compare(case_dir: Path, frame: int, prune: float | None) -> dict:
    import zarr
    from realistic_bounds import integrate_and_score, load_case  # this folder's sibling (run as a script)

    from schlieren.pipeline import metrics, tomography
    from schlieren.pipeline.geometry import FlowGrid
    from schlieren.storage import synthetic_io as sio
    from schlieren.workers import tasks
    from schlieren.workers.evaluate import _truth_at

    ctx, _geom, t_on, r_amb = load_case(case_dir, frame)
    grid = ctx.session.grid
    params = tasks.tomo_params(ctx)
    tz = zarr.open_group(str(case_dir / "truth.zarr"), mode="r")
    traced = (np.asarray(tz["d_out"][:, frame], np.float64)
              - np.asarray(tz["d_in"][:, frame], np.float64)) * params.n_ambient
    f = int(round(ctx.cameras[0].height / traced.shape[1]))
    gp = params if prune is None else dataclasses.replace(params, prune=prune)
    geom = tomography.build_geometry(ctx.cameras, grid, FlowGrid(ctx.cameras[0].image_size, f), params=gp)
    shape = tuple(geom.flow_shape)
    rhs = np.zeros(shape + (3,))
    rhs[:, :traced.shape[1], :traced.shape[2]] = traced

    truth = sio.read_truth(case_dir / "truth.zarr")
    tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
    tv, _ = _truth_at(truth, float(ctx.times()[frame]))
    gz, gy, gx = np.gradient(t_on, grid.voxel_size)
    native = np.gradient(np.asarray(tv, np.float64), tgrid.voxel_size, edge_order=2)
    xs = {"run-grid gradient": np.stack([gx, gy, gz], -1).reshape(-1, 3),
          "native gradient, resampled": np.stack([metrics.resample_space(a, tgrid, grid) for a in native[::-1]],
                                                 -1).reshape(-1, 3)}
    mag = np.abs(traced).max(-1)
    seen = np.zeros(shape, bool)
    seen[:, :traced.shape[1], :traced.shape[2]] = mag > 0.1 * mag.max()
    out = {"frame": frame, "ray_factor": f, "prune": gp.prune, "rays_seen": int(seen.sum()), "model": {}}
    hull = ctx.store.read("hull", (frame,))

    def score(b):
        g, _ = tomography.solve_gradient(geom, b, hull, params=params)
        return list(integrate_and_score(ctx, g, hull, t_on, r_amb))

    for name, x in xs.items():
        b = np.stack([geom.S @ x[:, i] for i in range(3)], -1).reshape(shape + (3,))
        comp = []
        for i in range(3):
            a, e = b[..., i][seen], rhs[..., i][seen]
            g = float(a @ e / (a @ a))
            comp.append({"gain": round(g, 3), "residual": round(float(np.sqrt(np.mean((e - a) ** 2) / np.mean(e ** 2))), 3),
                         "residual_after_gain": round(float(np.sqrt(np.mean((e - g * a) ** 2) / np.mean(e ** 2))), 3)})
        out["model"][name] = {"components": comp, "db": score(b)}
    out["traced_db"] = score(rhs)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default="/work/realistic/work", help="the family's --out folder")
    ap.add_argument("--cases", default="plume1-16cam-640,jet3-16cam-640,plume1-8cam-960-dist")
    ap.add_argument("--frame", type=int, default=1)
    ap.add_argument("--prune", type=float, default=None, help="projection pruning (default: the run's)")
    ap.add_argument("--results", default=str(RESULTS))
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = {"command": "python benchmarks/realistic_forward_model.py " + " ".join(argv or sys.argv[1:]), "cases": {}}
    for case in [c for c in a.cases.split(",") if c]:
        if not (Path(a.work) / case / "store.zarr").exists():
            print(f"{case}: no store under {a.work} (run `schlieren bench realistic --out {a.work}` first)",
                  file=sys.stderr)
            return 2
        out["cases"][case] = compare(Path(a.work) / case, a.frame, a.prune)
        print(case, json.dumps(out["cases"][case]), flush=True)
    out["seconds"] = round(time.perf_counter() - t0, 1)
    res = Path(a.results)
    res.mkdir(parents=True, exist_ok=True)
    (res / "realistic_forward_model.json").write_text(json.dumps(out, indent=1))
    lines = ["# The tomography's forward model against the curved-ray tracer (benchmarks/realistic_forward_model.py)",
             "", f"Command: `{out['command'].strip()}`", "",
             "Rays through the truth's own ray grid (no interpolation); on the rays that see the plume: the model's "
             "`S x` against the tracer's `n_amb (d_out - d_in)`, gain and relative residual (x / y / z), and both "
             "solved as the run solves (no window model), whole box / in plume dB.", "",
             "| case | x | gain | residual | residual after gain | model rays dB | traced rays dB |",
             "|---|---|---|---|---|---:|---:|"]
    for case, r in out["cases"].items():
        for name, m in r["model"].items():
            c = m["components"]
            lines.append(f"| {case} | {name} | {' / '.join(str(v['gain']) for v in c)} | "
                         f"{' / '.join(str(v['residual']) for v in c)} | "
                         f"{' / '.join(str(v['residual_after_gain']) for v in c)} | "
                         f"{m['db'][0]:.2f} / {m['db'][1]:.2f} | {r['traced_db'][0]:.2f} / {r['traced_db'][1]:.2f} |")
    lines += ["", f"Wall time {out['seconds']} s.", ""]
    (res / "realistic_forward_model.md").write_text("\n".join(lines))
    print(f"wrote {res / 'realistic_forward_model.md'} ({out['seconds']} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
