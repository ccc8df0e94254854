"""The Markdown pages of ``benchmarks/uncertainty_coverage.py``: the fit of the uncertainty's
scales on the tune cases, and the coverage table of every case."""

from __future__ import annotations

import numpy as np

__all__ = ["fit_markdown", "coverage_markdown"]


def _pct(v) -> str:
    return f"{100 * v:.1f} %" if isinstance(v, (int, float)) and np.isfinite(v) else "—"


def _sec(v) -> str:
    return f"{v:.1f}" if isinstance(v, (int, float)) and np.isfinite(v) else "—"


def _pair(c: dict | None) -> str:
    return f"{_pct(c['within_1'])} / {_pct(c['within_2'])}" if c and c.get("voxels", 1) else "—"


def fit_markdown(out: dict) -> str:
    """:func:`benchmarks/uncertainty_coverage.fit`'s result as a page."""
    f = out["fit"]
    lines = ["# Uncertainty per voxel: the scales fitted on the tune cases", "",
             f"Command: `{out['command']}`. Every frame of the tune cases' stores (run `{out['label']}`), "
             f"{out['samples']} noise samples per frame; RMS over the plume voxels inside the hull, in % of the "
             "truth's range (the SPEC's normalisation), averaged over the frames.", "",
             f"Fitted: `uncertainty.boundary_scale` = {f['boundary_scale']:g}, `uncertainty.structure_scale` = "
             f"{f['structure_scale']:g}, `uncertainty.bias_scale` = {f.get('bias_scale', 0.0):g} (in-hull plume coverage closest to 68 % / 95 % within one / two sigma, "
             "case by case).", "",
             "| case | error RMS | noise term | boundary term (unscaled) | structure term (unscaled) | "
             "bias term (unscaled) | noise alone: within 1 / 2 sigma | fitted: within 1 / 2 sigma | "
             "plume outside the hull |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for case, r in out["cases"].items():
        c = f["cases"].get(case, [np.nan, np.nan])
        lines.append(f"| {case} | {100 * r['error_rms']:.2f} % | {100 * r['noise_rms']:.2f} % | "
                     f"{100 * r['boundary_rms']:.2f} % | {100 * r['structure_rms']:.2f} % | "
                     f"{100 * r.get('bias_rms', np.nan):.2f} % | "
                     f"{_pct(r['noise_within_1'])} / {_pct(r['noise_within_2'])} | {_pct(c[0])} / {_pct(c[1])} | "
                     f"{_pct(r['plume_outside_hull'])} |")
    return "\n".join(lines) + "\n"


def coverage_markdown(out: dict) -> str:
    """:func:`benchmarks/uncertainty_coverage.coverage`'s result as a page (tune and report separate)."""
    if out.get("from_terms"):
        how = (f"Command: `{out['command']}` on the kept stores of a default run (`schlieren bench realistic --label "
               f"{out['label']} --keep-stores`): each frame's terms recomputed through the stage's kernel "
               f"({out.get('samples', '?')} noise samples) and combined with "
               + (f"the scales {out['scales']} (boundary, structure, bias)" if out.get("scales")
                  else "the defaults' scales")
               + ", as the stage would store them.")
    else:
        how = (f"Command: `{out['command']}` after `schlieren bench realistic --label {out['label']} --keep-stores "
               "--params` with `uncertainty: {enabled: true}`.")
    lines = ["# Uncertainty per voxel: coverage on the realistic family", "",
             how + " Coverage = the fraction of voxels whose error "
             "|estimate - truth| lies within one / two `refractivity_sigma` (a Gaussian: 68.3 % / 95.4 %), "
             "pooled over the three frames. Plume = SPEC's in-plume voxels (|truth - ambient| > 1 % of the "
             "range); outside = the rest, inside the visual hull and beyond it (where sigma is 0 by construction: "
             "the hull's ambient constraint; an error of exactly 0 counts as covered). Noise alone = the sigma "
             "without its bias, boundary and structure terms. Seconds: task seconds per frame on the loaded "
             "machine (— where the terms came from an earlier cache); bias term: the seconds of its probes' solves "
             "and integrations alone.", ""]
    for role in ("tune", "report"):
        rows = [(n, r) for n, r in out["cases"].items() if r["role"] == role]
        if not rows:
            continue
        lines += [f"## {role.capitalize()} cases", "",
                  "| case | plume | plume in hull | plume outside the hull | outside, in hull | outside the hull | "
                  "plume, noise alone | tomography s/frame | uncertainty s/frame | bias term s/frame |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for name, r in rows:
            p = r["pooled"]
            out_frac = p["plume"]["voxels"] and 1 - p["plume_in_hull"]["voxels"] / p["plume"]["voxels"]
            sec = r.get("seconds_per_frame", {})
            lines.append(f"| {name} | {_pair(p['plume'])} | {_pair(p['plume_in_hull'])} | {_pct(out_frac)} | "
                         f"{_pair(p['outside_in_hull'])} | {_pair(p['outside_hull'])} | {_pair(r.get('noise_only'))} | "
                         f"{_sec(sec.get('tomography'))} | {_sec(sec.get('uncertainty'))} | {_sec(sec.get('bias'))} |")
        lines.append("")
    load = out.get("load")
    if load:
        lines.append(f"Load average while scoring: {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} (2 cores, shared); the "
                     "seconds are task seconds of the run, measured on the loaded machine (re-measure quiet).")
    return "\n".join(lines) + "\n"
