"""Calibration of the uncertainty per voxel on the realistic family (issue 35, items 1-2).

    python benchmarks/uncertainty_coverage.py fit --work /work/realistic --label LABEL
    python benchmarks/uncertainty_coverage.py coverage --work /work/realistic --label LABEL

``fit`` reads the tune cases' kept stores (``WORK/<case>/store-LABEL.zarr`` of
``schlieren bench realistic --out WORK --label LABEL --keep-stores``; any run of the
default reconstruction), recomputes every frame's terms unscaled through the
pipeline's kernel (:func:`schlieren.workers.bench.coverage.decompose`: the noise ensemble,
the boundary sensitivity, the curvature, the regularisation's bias) and fits
``uncertainty.boundary_scale``, ``structure_scale`` and ``bias_scale``
(:func:`~schlieren.workers.bench.coverage.fit_scales`); it also reports
how much of the in-plume error the noise alone covers. Writes
``benchmarks/results/uncertainty_fit.json`` / ``.md``. The report cases are never read.

``coverage`` reads every case's kept store of a run with ``uncertainty.enabled`` and scores
its stored ``refractivity_sigma`` against the truth: the fraction of voxels whose error is
within one and two sigma, in the plume and outside, per case (tune and report separate),
with the noise term's share (the stored sigma minus the recomputed boundary and structure
terms) and the cost per frame (the store's ``stage_times``; with ``--from-terms`` the bias
term's own seconds). Writes
``benchmarks/results/uncertainty_coverage.json`` / ``.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def _tune_cases():
    from schlieren.workers.realistic import CASES

    return [c.name for c in CASES if c.role == "tune"]


def _all_cases():
    from schlieren.workers.realistic import CASES

    return [(c.name, c.role, c.cameras, c.video) for c in CASES]


def fit(args) -> dict:
    from schlieren.pipeline import uncertainty as unc
    from schlieren.workers import tasks
    from schlieren.workers.bench import coverage as cov

    params = dataclasses.replace(unc.UncertaintyParams(), samples=args.samples)
    frames, rows = [], {}
    for case in args.cases.split(",") if args.cases else _tune_cases():
        store, truth = cov.case_paths(args.work, case, args.label)
        ctx = tasks.context(str(store))
        if ctx.config.uncertainty.enabled:  # the decomposition takes the defaults' other settings
            params = dataclasses.replace(ctx.config.uncertainty, samples=args.samples)
        stats = []
        for k, t_on, r_amb in cov.truth_on_grid(store, truth):
            t0 = time.perf_counter()
            cache = Path(args.cache) / f"{case}-{args.label}-{k}.npz" if args.cache else None
            z = cov.cached_terms(ctx, k, params, cache)
            hull = np.asarray(ctx.store.read("hull", (k,)), dtype=bool)
            err = np.asarray(ctx.store.read("refractivity", (k,)), dtype=np.float64) - t_on
            reg = cov.frame_regions(t_on, r_amb, hull)
            frames.append({"case": case, "error": err, "where": reg["plume_in_hull"],
                           **{n: np.asarray(v, dtype=np.float64) for n, v in z.items()}})
            stats.append(_decomposition(err, z, reg, t_on))
            print(f"{case} frame {k}: {time.perf_counter() - t0:.0f} s", flush=True)
        rows[case] = {key: float(np.mean([s[key] for s in stats])) for key in stats[0]}
    best = cov.fit_scales(frames)
    return {"command": "python benchmarks/uncertainty_coverage.py " + " ".join(sys.argv[1:]),
            "label": args.label, "samples": args.samples, "fit": best, "cases": rows}


def _decomposition(err, z, reg, t_on) -> dict:
    """RMS (relative to the truth's range) of the error and of each term over the plume voxels in
    the hull, and the noise term's own coverage there."""
    from schlieren.workers.bench import coverage as cov

    m = reg["plume_in_hull"]
    rng = float(t_on.max() - t_on.min())

    def rms(v):
        return float(np.sqrt(np.mean(np.asarray(v, dtype=np.float64)[m] ** 2)) / rng)

    c = cov.coverage(err, z["noise"], m)
    return {"error_rms": rms(err), "noise_rms": rms(z["noise"]), "boundary_rms": rms(z["boundary"]),
            "structure_rms": rms(z["structure"]), "bias_rms": rms(z["bias"]) if "bias" in z else float("nan"), "noise_within_1": c["within_1"], "noise_within_2": c["within_2"],
            "plume_outside_hull": float(np.mean(~m[reg["plume"]])) if reg["plume"].any() else float("nan")}


def coverage(args) -> dict:
    from schlieren.workers.bench import coverage as cov

    out = {"command": "python benchmarks/uncertainty_coverage.py " + " ".join(sys.argv[1:]), "label": args.label,
           "cases": {}, "load": os.getloadavg(), "from_terms": bool(args.from_terms), "samples": args.samples,
           "scales": args.scales}
    wanted = set(args.cases.split(",")) if args.cases else None
    for name, role, cameras, video in _all_cases():
        if wanted is not None and name not in wanted:
            continue
        store, truth = cov.case_paths(args.work, name, args.label)
        if not store.exists():
            print(f"{name}: no store {store}; skipped", flush=True)
            continue
        if args.from_terms:
            res = _terms_coverage(args, name, store, truth)
        else:
            res = cov.store_coverage(store, truth)
            res.update({"seconds_per_frame": cov.stage_seconds(store), "noise_only": _noise_only(store, truth)})
        res.update({"role": role, "cameras": cameras, "video": video})
        out["cases"][name] = res
        p = res["pooled"]["plume"]
        print(f"{name}: plume {p['within_1']:.3f} / {p['within_2']:.3f}", flush=True)
    return out


def _terms_coverage(args, case, store, truth) -> dict:
    """:func:`coverage` of a default run's store (no stored sigma): each frame's terms recomputed
    through the stage's kernel (:func:`~schlieren.workers.bench.coverage.cached_terms`, ``--samples``
    noise samples) and combined with the defaults' scales, as the stage would store them."""
    from schlieren.pipeline import uncertainty as unc
    from schlieren.storage.store import ResultStore
    from schlieren.workers import tasks
    from schlieren.workers.bench import coverage as cov

    ctx = tasks.context(str(store))
    params = dataclasses.replace(unc.UncertaintyParams(), samples=args.samples)
    if args.scales:  # other boundary / structure (/ bias) scales than the defaults'
        v = [float(x) for x in args.scales.split(",")]
        params = dataclasses.replace(params, boundary_scale=v[0], structure_scale=v[1],
                                     **({"bias_scale": v[2]} if len(v) > 2 else {}))
    st = ResultStore.open(store, mode="r")
    terms = {}

    def term(k):
        if k not in terms:
            cache = Path(args.cache) / f"{case}-{args.label}-{k}.npz" if args.cache else None
            terms[k] = cov.cached_terms(ctx, k, params, cache)
        return terms[k]

    res = cov.store_coverage(store, truth, sigma=lambda k: cov.terms_sigma(term(k), params, st.read("hull", (k,))))
    noise = cov.store_coverage(store, truth, sigma=lambda k: np.where(st.read("hull", (k,)), term(k)["noise"], 0.0))
    res["noise_only"] = noise["pooled"]["plume"]
    secs = [float(z["seconds"]) for z in terms.values() if "seconds" in z]
    bias_secs = [float(z["bias_seconds"]) for z in terms.values() if "bias_seconds" in z]
    times = cov.stage_seconds(store)
    res["seconds_per_frame"] = {**times, **({"uncertainty": float(np.mean(secs))} if secs else {}),
                                **({"bias": float(np.mean(bias_secs))} if bias_secs else {})}
    return res


def _noise_only(store, truth) -> dict:
    """In-plume coverage of the noise term alone: the stored sigma without the bias, boundary and
    structure terms (recomputed: the bias term's probes and two Poisson solves per frame, no ensemble)."""
    from schlieren.storage.store import ResultStore
    from schlieren.workers import tasks
    from schlieren.workers.bench import coverage as cov

    ctx = tasks.context(str(store))
    p = ctx.config.uncertainty
    st = ResultStore.open(store, mode="r")
    hits = np.zeros(3)
    for k, t_on, r_amb in cov.truth_on_grid(store, truth):
        z = cov.decompose(ctx, k, dataclasses.replace(p, samples=0))
        s = np.asarray(st.read("refractivity_sigma", (k,)), dtype=np.float64)
        noise = np.sqrt(np.maximum(s * s - (p.boundary_scale * z.boundary_sigma) ** 2
                                   - (p.structure_scale * z.structure_sigma) ** 2
                                   - (p.bias_scale * z.bias_sigma) ** 2, 0.0))
        err = np.asarray(st.read("refractivity", (k,)), dtype=np.float64) - t_on
        c = cov.coverage(err, noise, cov.frame_regions(t_on, r_amb, st.read("hull", (k,)))["plume"])
        hits += [c["within_1"] * c["voxels"], c["within_2"] * c["voxels"], c["voxels"]]
    return {"within_1": hits[0] / hits[2], "within_2": hits[1] / hits[2]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=["fit", "coverage"])
    ap.add_argument("--work", default="/work/realistic", help="the family's --out folder")
    ap.add_argument("--label", default="", help="the run's --label (stores store-LABEL.zarr)")
    ap.add_argument("--cases", default=None, help="comma-separated cases (fit: default the tune cases)")
    ap.add_argument("--samples", type=int, default=8, help="fit, --from-terms: noise samples per frame")
    ap.add_argument("--cache", default=None, help="folder caching each frame's terms")
    ap.add_argument("--from-terms", action="store_true",
                    help="coverage: score a default run's stores, the sigma recomputed from the terms with the "
                         "defaults' scales (no run with uncertainty.enabled needed)")
    ap.add_argument("--scales", default=None,
                    help="coverage --from-terms: BOUNDARY,STRUCTURE[,BIAS] scales instead of the defaults'")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    from schlieren.workers.bench import coverage_markdown as md

    res = Path(args.results)
    res.mkdir(parents=True, exist_ok=True)
    if args.mode == "fit":
        out = fit(args)
        (res / "uncertainty_fit.json").write_text(json.dumps(out, indent=1))
        (res / "uncertainty_fit.md").write_text(md.fit_markdown(out))
    else:
        out = coverage(args)
        (res / "uncertainty_coverage.json").write_text(json.dumps(out, indent=1, default=float))
        (res / "uncertainty_coverage.md").write_text(md.coverage_markdown(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
