"""A weaker spatial prior for the space-time mean, measured offline on kept stores (issue 35).

    python benchmarks/spacetime_prior.py [--work /work/realistic] [--label i35_st] [--cases a,b]
        [--scales 1,0.3,0.1,0.03] [--iters 25,50] [--window 2]

The per-frame solve's error on the 8-camera cases is the prior's bias, not noise
(``benchmarks/results/spacetime_bounds.md``); averaging neighbours removes noise only. So
solve every frame of the window around the middle frame ``k`` from the run's own rays at
the run's weight times ``scale`` (the run's other settings, warm-started from the run's
per-frame solve, ``iters`` iterations at most), move the neighbours onto frame ``k`` along
the motion the space-time stage estimates (between the run's per-frame solves,
``gradient_frame``) and average; integrate and score whole box / in plume on the run's
grid. Rows: the single frame at that prior (``alone``) and the means over windows
1 .. ``--window``. Reads the stores ``schlieren bench spacetime --keep-stores`` keeps
(``WORK/<case>-f7/store-st-LABEL.zarr``) and the case's ``truth.zarr``.

Writes ``spacetime_prior.json`` / ``.md`` under ``--results``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from realistic_bounds import integrate_and_score  # noqa: E402
from spacetime_bounds import load  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def _window(store: Path, window: int, k: int | None):
    """The run's context around output frame ``k`` (default the middle one): its window's
    hulls, the run's per-frame solves and the stage's motion between them (onto frame ``k``)."""
    from types import SimpleNamespace

    from schlieren.pipeline import spacetime, tomography
    from schlieren.pipeline.spacetime.average import _motion
    from schlieren.pipeline.tomography.solve import basis_set
    from schlieren.workers import tasks

    ctx, geom, truth, r_amb = load(store)
    k = ctx.n_frames // 2 if k is None else int(k)
    st = ctx.config.spacetime
    frames = list(spacetime.window_frames(k, ctx.n_frames, window))
    dil = ctx.config.tomography.hull_dilation
    hulls = {j: ctx.store.read("hull", (j,)) for j in frames}
    support = basis_set(hulls[k], dil)
    per = {j: np.asarray(ctx.store.read("gradient_frame", (j,)), dtype=np.float32) for j in frames}
    box = spacetime.support_box(tomography.block_support([hulls[j] for j in frames], dil) | support)
    t0 = time.perf_counter()
    motion = {j: _motion(np.ascontiguousarray(per[k][box]), np.ascontiguousarray(per[j][box]), st)
              for j in frames if j != k}
    return SimpleNamespace(ctx=ctx, geom=geom, truth=truth, r_amb=r_amb, k=k, st=st, frames=frames, hulls=hulls,
                           support=support, per=per, box=box, motion=motion, params=tasks.tomo_params(ctx),
                           blur=tasks.flow_blur(ctx), motion_s=(time.perf_counter() - t0) / max(len(motion), 1))


def measure(store: Path, scales, iters, window: int, k: int | None = None) -> dict:
    from schlieren.pipeline import spacetime, tomography

    w_ = _window(store, window, k)
    ctx, geom, truth, r_amb, k, st = w_.ctx, w_.geom, w_.truth, w_.r_amb, w_.k, w_.st
    frames, hulls, support, per, box, motion = w_.frames, w_.hulls, w_.support, w_.per, w_.box, w_.motion
    params, blur, motion_s = w_.params, w_.blur, w_.motion_s

    def score(g) -> dict:
        whole, plume = integrate_and_score(ctx, g, hulls[k], truth[k], r_amb)
        return {"whole_db": whole, "plume_db": plume}

    def mean(vols, w) -> np.ndarray:
        sel = [j for j in frames if abs(j - k) <= w]
        acc = np.zeros(support.shape + (3,), np.float32)
        for j in sel:
            v = vols[j][box]
            acc[box] += (v if j == k else spacetime.warp_volume(np.ascontiguousarray(v), motion[j], order=3,
                                                                 scale=st.motion_scale)) / len(sel)
        acc[~support] = 0.0
        return acc

    rows: dict = {"run per-frame": {"alone": score(per[k])}}
    for w in range(1, window + 1):
        rows["run per-frame"][f"mean W{w}"] = score(mean(per, w))
    secs = {}
    for s in scales:
        for it in iters:
            p = dataclasses.replace(params, reg_weight=params.reg_weight * s, max_iter=int(it), tol=1e-6)
            vols, t, n_it = {}, 0.0, []
            for j in frames:
                t1 = time.perf_counter()
                g, info = tomography.solve_gradient(geom, ctx.tomography_flows(j), hulls[j], params=p, x0=per[j],
                                                    **blur)
                t += time.perf_counter() - t1
                n_it.append(int(info.iterations))
                vols[j] = np.asarray(g, dtype=np.float32)
            name = f"scale {s:g}, {it} it"
            rows[name] = {"alone": score(vols[k])}
            for w in range(1, window + 1):
                rows[name][f"mean W{w}"] = score(mean(vols, w))
            secs[name] = round(t / len(frames), 2)
            print(store.parent.name, name, json.dumps(rows[name]), "s/solve", secs[name], "iterations", n_it,
                  flush=True)
    # the run's own solve, timed alike, for the cost ratio
    t1 = time.perf_counter()
    tomography.solve_gradient(geom, ctx.tomography_flows(k), hulls[k], params=params, **blur)
    run_s = time.perf_counter() - t1
    return {"frame": k, "frames": frames, "reg_weight": params.reg_weight, "run_max_iter": params.max_iter,
            "rows": rows, "seconds_per_solve": secs, "run_solve_seconds": round(run_s, 2),
            "motion_seconds_per_neighbour": round(motion_s, 2)}


def diagnose(store: Path, scale: float, iters: int, window: int, k: int | None = None) -> dict:
    """Is the error of the weak-prior solves noise (averaged down by the mean) or shared by the
    frames? For every frame ``j`` of the window, the error ``d_j`` of the solve from the run's rays
    against the same solve from the tomography's model rays of the truth (``S G x``); the
    neighbours' ``d_j`` moved onto frame ``k`` (the stage's motion) and averaged. Independent
    errors would shrink by ``sqrt(n)``; also the ray errors' frame-to-frame correlation."""
    from schlieren.pipeline import metrics, spacetime, tomography
    from schlieren.pipeline.tomography.blur import VolumeBlur

    w_ = _window(store, window, k)
    ctx, geom, truth, r_amb, k, st = w_.ctx, w_.geom, w_.truth, w_.r_amb, w_.k, w_.st
    frames, hulls, per, box, motion, params, blur = w_.frames, w_.hulls, w_.per, w_.box, w_.motion, w_.params, w_.blur
    p = dataclasses.replace(params, reg_weight=params.reg_weight * scale, max_iter=int(iters), tol=1e-6)
    plume = metrics.plume_mask(truth[k], r_amb)
    d, e, sig = {}, {}, {}
    for j in frames:
        gz, gy, gx = np.gradient(truth[j], ctx.session.grid.voxel_size)
        x = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
        xg = VolumeBlur(np.ones(ctx.session.grid.shape, bool), blur["volume_blur"]).apply(x) \
            if "volume_blur" in blur else x
        model = np.stack([geom.S @ xg[:, i] for i in range(3)], axis=-1).reshape(tuple(geom.flow_shape) + (3,))
        run = tomography.rhs_from_flows(geom, ctx.tomography_flows(j), n_ambient=params.n_ambient)
        e[j] = np.where(np.isfinite(run), run - model, 0.0).reshape(-1, 3)
        if j == k:
            hit = np.abs(model.reshape(-1, 3)).max(axis=1) > 0
        g_run, _ = tomography.solve_gradient(geom, run, hulls[j], params=p, x0=per[j], **blur)
        g_mod, _ = tomography.solve_gradient(geom, model, hulls[j], params=p, x0=per[j], **blur)
        sig[j] = np.asarray(g_mod, np.float32)
        d[j] = np.asarray(g_run, np.float32) - sig[j]
    rms = lambda v: float(np.sqrt(np.mean(v[plume] ** 2)))  # noqa: E731

    def score(g) -> str:
        return "%.2f / %.2f" % integrate_and_score(ctx, g, hulls[k], truth[k], r_amb)

    out = {"scale": scale, "iters": iters, "rms_error_alone": rms(d[k]),
           "score model rays alone (bias only)": score(sig[k]), "score run rays alone": score(sig[k] + d[k])}
    def mean(vols, sel):
        acc = np.zeros_like(vols[k])
        for j in sel:
            v = vols[j] if j == k else np.zeros_like(vols[j])
            if j != k:
                v[box] = spacetime.warp_volume(np.ascontiguousarray(vols[j][box]), motion[j], order=3,
                                               scale=st.motion_scale)
            acc += v / len(sel)
        return acc

    for w in range(1, window + 1):
        sel = [j for j in frames if abs(j - k) <= w]
        dm, sm = mean(d, sel), mean(sig, sel)
        out[f"rms_error_mean_W{w}"] = rms(dm)
        out[f"independent_W{w}"] = rms(d[k]) / np.sqrt(len(sel))
        out[f"score W{w}: model rays alone + mean data error"] = score(sig[k] + dm)
        out[f"score W{w}: mean of model-ray solves (bias + motion)"] = score(sm)
        out[f"score W{w}: mean of run-ray solves"] = score(sm + dm)
    ek = e[k]
    for j in frames:
        if j != k:
            for name, m in (("plume rays", hit), ("quiet rays", ~hit)):
                a, b = ek[m].ravel(), e[j][m].ravel()
                out[f"ray_error_corr_{j - k:+d} {name}"] = round(
                    float(np.dot(a, b) / np.sqrt(np.dot(a, a) * np.dot(b, b))), 3)
    out["ray_error_rms plume / quiet"] = round(float(np.sqrt(np.mean(ek[hit] ** 2)) /
                                                     np.sqrt(np.mean(ek[~hit] ** 2))), 2)
    return out


def render(out: dict) -> str:
    lines = ["# Space-time mean of solves at a weaker prior (offline, kept stores)", "",
             f"Command: `{out['command'].strip()}` (see its docstring). The middle output frame of each case's "
             "7-frame run, whole box / in plume dB on the run's grid. `scale s, N it`: every frame of the window "
             "solved from the run's rays at the run's weight times s, warm-started from the run's per-frame "
             "solve, N iterations; `alone`: that frame by itself; `mean Ww`: the motion-compensated mean over "
             "frames k-w .. k+w (the motion between the run's per-frame solves).", ""]
    for case, r in out["cases"].items():
        cols = list(next(iter(r["rows"].values())))
        lines += [f"## {case} (run weight {r['reg_weight']:.3g}, {r['run_max_iter']} iterations; run solve "
                  f"{r['run_solve_seconds']} s, motion {r['motion_seconds_per_neighbour']} s per neighbour; "
                  f"load-affected timings)", "",
                  "| solve | " + " | ".join(cols) + " | s/solve |", "|---|" + "---:|" * (len(cols) + 1)]
        for name, row in r["rows"].items():
            lines.append(f"| {name} | " + " | ".join(f"{row[c]['whole_db']:.2f} / {row[c]['plume_db']:.2f}"
                                                     for c in cols) +
                         f" | {r['seconds_per_solve'].get(name, '')} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default="/work/realistic")
    ap.add_argument("--label", default="i35_st", help="the spacetime bench's --label (store-st-LABEL.zarr)")
    ap.add_argument("--frames", type=int, default=7)
    ap.add_argument("--cases", default="plume1-8cam-960-dist")
    ap.add_argument("--scales", default="1,0.3,0.1,0.03")
    ap.add_argument("--iters", default="25,50")
    ap.add_argument("--window", type=int, default=2, help="largest half-width of the means scored")
    ap.add_argument("--name", default="spacetime_prior", help="results file name")
    ap.add_argument("--diagnose", default="", help="scale,iters: the error decomposition (diagnose) instead")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    if args.diagnose:
        s, it = args.diagnose.split(",")
        for case in [c for c in args.cases.split(",") if c]:
            store = Path(args.work) / f"{case}-f{args.frames}" / f"store-st-{args.label}.zarr"
            r = diagnose(store, float(s), int(it), args.window)
            print(case, json.dumps(r), flush=True)
            Path(args.results).mkdir(parents=True, exist_ok=True)
            (Path(args.results) / f"{args.name}_{case}.json").write_text(json.dumps(r, indent=1))
        return 0
    out: dict = {"command": "python benchmarks/spacetime_prior.py " + " ".join(argv or sys.argv[1:]), "cases": {}}
    for case in [c for c in args.cases.split(",") if c]:
        store = Path(args.work) / f"{case}-f{args.frames}" / f"store-st-{args.label}.zarr"
        if not store.exists():
            print(f"{store}: missing; skipped", flush=True)
            continue
        out["cases"][case] = measure(store, [float(s) for s in args.scales.split(",")],
                                     [int(i) for i in args.iters.split(",")], args.window)
    res = Path(args.results)
    res.mkdir(parents=True, exist_ok=True)
    (res / f"{args.name}.json").write_text(json.dumps(out, indent=1))
    (res / f"{args.name}.md").write_text(render(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
