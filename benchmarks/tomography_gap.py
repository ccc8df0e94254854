"""What separates a 16-camera run's tomography from the truth, one number per effect (issue 35).

    python benchmarks/tomography_gap.py --store WORK/CASE/store-LABEL.zarr [--frame 1]
        [--fine 1.5] [--out results/tomography_gap_probe.json]

Reads a kept family store (``schlieren bench realistic ... --keep-stores``; with
``refine.passes`` > 0 in its parameters the refined rows use its flows re-measured as the
tomography task does) and the case's ``truth.zarr``, and reconstructs output frame
``--frame`` from data whose errors are known, every row integrated and scored as the family
scores (the truth trilinearly resampled to the run's grid; whole box / in plume dB):

* from the curved-ray tracer's exit directions ``n_amb (d_out - d_in)`` on the truth's own ray
  grid (no interpolation; the bench's "truth rows" geometry), solved as the run solves (its
  weight, hull and iterations, no window model): **traced**;
* the same rays from the tracer's *pixel* deflections through the run's exit-direction
  approximation: **traced, d_out approximated** (effect d: the approximation);
* the model's own rays ``S x`` from the truth's gradient on the run's grid (central
  differences of the resampled truth) and from the truth's native gradient resampled:
  **consistent** (effect a: traced against consistent is the discretisation mismatch);
* traced rays through the truth's plume dilated by 2 voxels instead of the run's hull
  (effect c); traced rays at other weights, converged (effect b without flow noise);
* traced rays solved on a grid ``--fine`` times finer (the run's hull brought there), integrated
  there and resampled to the run's grid as the truth is (what a finer solve grid buys);
* the run's flows (window model), and with ``refine.passes`` the refined flows at the run's
  weight and at other weights (effect b with the refined flows), and through the truth hull.

Writes the JSON given by ``--out`` (default ``benchmarks/results/tomography_gap_probe.json``).
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


def fine_grid(grid, factor: float):
    """The run's box on voxels ``factor`` times smaller."""
    from schlieren.pipeline.geometry import Grid

    return Grid(grid.vmin, grid.vmax, grid.voxel_size / float(factor))


def to_grid(mask: np.ndarray, src, dst) -> np.ndarray:
    """A boolean volume on ``dst``: the ``src`` voxel nearest each ``dst`` centre."""
    from schlieren.pipeline import metrics

    return metrics.resample_space(mask.astype(np.float64), src, dst) > 0.5


class Case:
    """A kept store, its truth at one output frame and the scoring."""

    def __init__(self, store: Path, frame: int):
        from scipy import ndimage

        from schlieren.pipeline import metrics
        from schlieren.storage import synthetic_io as sio
        from schlieren.workers import tasks
        from schlieren.workers.evaluate import _r_ambient, _truth_at

        self.k = int(frame)
        self.ctx = tasks.context(str(store))
        self.case_dir = store.parent
        truth = sio.read_truth(self.case_dir / "truth.zarr")
        self.truth = truth
        self.tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
        tv, _ = _truth_at(truth, float(self.ctx.times()[self.k]))
        self.tv = np.asarray(tv, np.float64)
        self.grid = self.ctx.session.grid
        self.t_on = metrics.resample_space(self.tv, self.tgrid, self.grid)
        self.r_amb = _r_ambient(truth)
        self.hull = np.asarray(self.ctx.store.read("hull", (self.k,)), bool)
        self.truth_hull = ndimage.binary_dilation(metrics.plume_mask(self.t_on, self.r_amb), iterations=2)
        self.params = tasks.tomo_params(self.ctx)

    def score(self, r: np.ndarray, grid=None) -> list[float]:
        from schlieren.pipeline import metrics

        if grid is not None and grid != self.grid:
            r = metrics.resample_space(r, grid, self.grid)
        return [round(metrics.psnr(metrics.relative_rms(r, self.t_on)), 2),
                round(metrics.psnr(metrics.plume_rms(r, self.t_on, self.r_amb)), 2)]

    def integrate(self, g: np.ndarray, hull: np.ndarray, grid=None) -> np.ndarray:
        from schlieren.pipeline import poisson

        r, _ = poisson.integrate(g, hull, grid or self.grid, r_ambient=self.ctx.session.medium.refractivity_ambient,
                                 params=self.ctx.config.poisson)
        return np.asarray(r, np.float64)

    def solve_score(self, geom, b, hull, params=None, grid=None, **kw) -> dict:
        from schlieren.pipeline import tomography

        p = params or self.params
        t0 = time.process_time()
        g, info = tomography.solve_gradient(geom, b, hull, params=p, **kw)
        cpu = time.process_time() - t0
        whole, plume = self.score(self.integrate(g, hull, grid), grid)
        return {"whole_db": whole, "plume_db": plume, "iterations": info.iterations,
                "reg_weight": p.reg_weight, "solve_cpu_s": round(cpu, 2)}


def lever_weighted(geom):
    """A copy of ``geom`` whose projection entries are scaled by their voxel's lever arm to
    the background, ``(s_bg - s) / (s_bg - s_c)`` (``s_c`` the ray parameter of ``X_c``, the
    exit-direction approximation's pivot): the first-order model of a pixel deflection
    picked up at ``s`` (not kept in the pipeline: it moves the result by 0.03 dB)."""
    S = geom.S.copy()
    C = geom.flow_shape[0]
    rows = np.repeat(np.arange(S.shape[0]), np.diff(S.indptr))
    cam = rows // (S.shape[0] // C)
    d = geom.d_in.reshape(-1, 3)
    o = geom.centers
    s_c = np.einsum("rk,rk->r", geom.x_c.reshape(-1, 3) - np.repeat(o, S.shape[0] // C, axis=0), d)
    num = np.einsum("ck,ck->c", geom.bg_point - o, geom.bg_normal)
    s_bg = num[np.repeat(np.arange(C), S.shape[0] // C)] / np.einsum(
        "rk,rk->r", d, np.repeat(geom.bg_normal, S.shape[0] // C, axis=0))
    nz, ny, nx = geom.grid.shape
    idx = S.indices.astype(np.int64)
    pos = geom.grid.origin + geom.grid.voxel_size * np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], -1)
    s = np.einsum("ek,ek->e", pos - o[cam], d[rows])
    S.data = (S.data * (s_bg[rows] - s) / (s_bg[rows] - s_c[rows])).astype(np.float32)
    return dataclasses.replace(geom, S=S)


def traced_rows(case: Case, fine: float, weights: list[float]) -> dict:
    """Rows from the tracer's rays on the truth's ray grid (no flows, no noise)."""
    import zarr

    from schlieren.pipeline import metrics, tomography
    from schlieren.pipeline.geometry import FlowGrid

    ctx, k, p = case.ctx, case.k, case.params
    tz = zarr.open_group(str(case.case_dir / "truth.zarr"), mode="r")
    j = int(np.argmin(np.abs(np.asarray(tz["time"][:]) - float(ctx.times()[k]))))
    traced = (np.asarray(tz["d_out"][:, j], np.float64) - np.asarray(tz["d_in"][:, j], np.float64)) * p.n_ambient
    pix = np.asarray(tz["deflection"][:, j], np.float64)
    W, _H = ctx.cameras[0].image_size
    fg = FlowGrid((W, _H), max(1, W // traced.shape[2]))
    t0 = time.process_time()
    geom = tomography.build_geometry(ctx.cameras, case.grid, fg, params=p)
    print(f"run-grid geometry on the truth's rays: {time.process_time() - t0:.0f} s CPU, nnz {geom.S.nnz}",
          flush=True)
    gz, gy, gx = np.gradient(case.t_on, case.grid.voxel_size)
    x_run = np.stack([gx, gy, gz], -1).reshape(-1, 3)
    nat = np.gradient(case.tv, case.tgrid.voxel_size, edge_order=2)
    x_nat = np.stack([metrics.resample_space(a, case.tgrid, case.grid) for a in nat[::-1]], -1).reshape(-1, 3)
    shape = tuple(geom.flow_shape) + (3,)
    rows: dict = {}
    rows["integration only: truth's run-grid gradient, run hull"] = dict(zip(
        ("whole_db", "plume_db"), case.score(case.integrate(x_run.reshape(case.grid.shape + (3,)), case.hull))))
    rows["traced"] = case.solve_score(geom, traced, case.hull)
    rows["traced, d_out approximated"] = case.solve_score(geom, pix, case.hull)
    rows["traced, d_out approximated, lever-arm model"] = case.solve_score(lever_weighted(geom), pix, case.hull)
    rp = tomography.rhs_from_flows(geom, pix, n_ambient=p.n_ambient)
    mag = np.abs(traced).max(-1)
    seen = mag > 0.1 * mag.max()
    a, e = traced[..., 0][seen], rp[..., 0][seen]
    gain = float(a @ e / (a @ a))
    rows["pixel deflections against exit directions (x, plume rays)"] = {
        "gain": round(gain, 4), "residual_after_gain": round(float(np.sqrt(np.mean((e - gain * a) ** 2) / np.mean(a ** 2))), 4)}
    for name, x in (("consistent (run-grid gradient)", x_run), ("consistent (native gradient)", x_nat)):
        b = np.stack([geom.S @ x[:, i] for i in range(3)], -1).reshape(shape)
        rows[name] = case.solve_score(geom, b, case.hull)
    rows["traced, truth hull"] = case.solve_score(geom, traced, case.truth_hull)
    # the tracer's rays plus noise of the run's measured level (rhs_noise, rays outside the
    # masks), correlated over one flow cell as the flow's window correlates it: what a given
    # data error leaves of the noise-free figure
    noise = np.asarray(ctx.store.read("rhs_noise", ()), dtype=np.float64)
    rng = np.random.default_rng(0)
    n = rng.normal(size=traced.shape)
    for c in range(n.shape[0]):
        for i in range(3):
            n[c, ..., i] = cv2.GaussianBlur(n[c, ..., i], (0, 0), 1.0)
    n *= 1.0 / n.reshape(-1, 3).std(axis=0)
    for f in (0.5, 1.0, 1.5):
        rows[f"traced + correlated noise x{f:g} of the run's rhs_noise"] = case.solve_score(
            geom, traced + f * noise * n, case.hull)
    conv = dataclasses.replace(p, max_iter=200, tol=1e-4)
    for f in weights:
        rows[f"traced, converged, weight x{f:g}"] = case.solve_score(
            geom, traced, case.hull, params=dataclasses.replace(conv, reg_weight=p.reg_weight * f))
    del geom
    if fine > 1:
        fgd = fine_grid(case.grid, fine)
        hf = to_grid(case.hull, case.grid, fgd)
        t0 = time.process_time()
        gf = tomography.build_geometry(ctx.cameras, fgd, fg, params=p)
        print(f"fine geometry {fgd.shape}: {time.process_time() - t0:.0f} s CPU, nnz {gf.S.nnz}", flush=True)
        for f in weights:
            rows[f"traced, solve grid 1/{fine:g}, weight x{f:g}"] = case.solve_score(
                gf, traced, hf, params=dataclasses.replace(p, reg_weight=p.reg_weight * f), grid=fgd)
        rows[f"traced, solve grid 1/{fine:g}, converged, weight x1"] = case.solve_score(gf, traced, hf, params=conv,
                                                                                       grid=fgd)
        del gf
    return rows


def flow_rows(case: Case, weights: list[float]) -> dict:
    """Rows from the run's own flows: plain with the window model, and refined."""
    from schlieren.pipeline import tomography
    from schlieren.workers.tasks import flow_blur
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key
    from schlieren.workers.tasks.refine import refined_flows
    from schlieren.workers.tasks.regularisation import window_model

    ctx, k, p = case.ctx, case.k, case.params
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    flows = ctx.tomography_flows(k)
    blur = flow_blur(ctx)
    rows = {"run flows, window model": case.solve_score(geom, flows, case.hull, **blur)}
    rows["run flows, window model, truth hull"] = case.solve_score(geom, flows, case.truth_hull, **blur)
    passes = ctx.config.refine.passes
    if not passes:
        return rows
    grad, _ = tomography.solve_gradient(geom, flows, case.hull, params=p, **blur)
    refined, scale = None, ctx.config.refine.window_scale
    for _ in range(passes):
        refined = tomography.bin_cells(refined_flows(ctx, k, geom, grad), ctx.ray_binning)
        grad, _ = tomography.solve_gradient(geom, refined, case.hull, params=p, **flow_blur(ctx, scale))
    for f in weights:
        rows[f"refined flows, weight x{f:g}"] = case.solve_score(
            geom, refined, case.hull, params=dataclasses.replace(p, reg_weight=p.reg_weight * f))
    rows["refined flows, truth hull"] = case.solve_score(geom, refined, case.truth_hull)
    rows["refined flows, hull_dilation 0"] = case.solve_score(geom, refined, case.hull,
                                                              params=dataclasses.replace(p, hull_dilation=0))
    rows["refined flows, iterations 50"] = case.solve_score(geom, refined, case.hull,
                                                            params=dataclasses.replace(p, max_iter=50, tol=1e-4))
    window = np.asarray(ctx.store.read("flow_window", ()), dtype=np.float64)
    for scale in (0.4, 0.5, 0.6, 0.7, 1.0):
        rows[f"refined flows, window model x{scale:g}"] = case.solve_score(
            geom, refined, case.hull, **window_model(ctx, scale * window))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--store", required=True, help="a kept family store (its folder holds truth.zarr)")
    ap.add_argument("--frame", type=int, default=1)
    ap.add_argument("--fine", type=float, default=1.5, help="solve-grid refinement of the fine rows (1: none)")
    ap.add_argument("--weights", default="0.25,0.5,1,2", help="factors on the run's weight")
    ap.add_argument("--skip", default="", help="comma list of row groups to skip: traced, flows")
    ap.add_argument("--out", default=str(RESULTS / "tomography_gap_probe.json"))
    a = ap.parse_args(argv)
    weights = [float(v) for v in a.weights.split(",") if v]
    case = Case(Path(a.store), a.frame)
    out = {"command": "python benchmarks/tomography_gap.py " + " ".join(argv or sys.argv[1:]),
           "store": a.store, "frame": a.frame, "grid": list(case.grid.shape), "voxel": case.grid.voxel_size,
           "reg_weight": case.params.reg_weight, "refine_passes": case.ctx.config.refine.passes, "rows": {}}
    skip = set(a.skip.split(","))
    for name, fn in (("flows", lambda: flow_rows(case, weights)), ("traced", lambda: traced_rows(case, a.fine, weights))):
        if name in skip:
            continue
        for row, v in fn().items():
            out["rows"][row] = v
            print(f"{row}: {v}", flush=True)
        Path(a.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
