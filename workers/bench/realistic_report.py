"""The realistic family's results as Markdown: every case, and each lab case beside its clean twin.

:func:`family_markdown` writes ``benchmarks/results/realistic[_LABEL].md``: one row per case
(scores, the truth's own deflections through the run's hull, the run time), then, where a
run holds a clean case and its lab variant (``-lab``, ``-laball``), the two side by side with
the difference and what the run made of the capture
(:func:`~schlieren.workers.bench.realistic_metrics.capture_diagnostics`).
"""

from __future__ import annotations

import numpy as np

from schlieren.workers.bench.realistic_cases import DEFAULT_LINE_TIME, PAPER_TARGETS

__all__ = ["family_markdown", "lab_markdown", "lab_pairs"]


def _f(x, spec=".2f") -> str:
    return format(x, spec) if isinstance(x, (int, float)) and np.isfinite(x) else "—"


def family_markdown(result: dict, *, machine: str = "") -> str:
    """Markdown table of :func:`run_family`'s result, with the targets of issue 14."""
    lab = result.get("label") or "defaults"
    rates = sorted({r.get("bits_per_pixel") or 0.16 for r in result["cases"] if r.get("video")})
    video = ("H.264 at " + ", ".join(f"{b:g}" for b in rates) + " bit/pixel") if rates else "no video cases"
    lines = [f"# Realistic benchmark family ({lab})", "",
             "Command: `schlieren bench realistic` (see `workers/realistic.py`). CFD flows (PhiFlow) simulated on "
             "the 2.5 mm grid, upsampled 2x by cubic splines, rendered and scored on that one field; weak "
             "deflections; 8-bit frames, noise 1.5 grey levels, rolling shutter, strobe sync, noisy reference "
             "frames; distortion on the 960x720 rigs; "
             f"{video}. Whole box = SPEC section 4; in plume = the same RMS over voxels where "
             "|truth - ambient| > 1 % of the range. `approximate` = the truth's own deflections through "
             "tomography and integration (no optical flow).", "",
             "| case | role | cams | image | peak px | whole box dB | in plume dB | peak ratio | approx. whole / plume dB "
             "| target whole / plume | pipeline s |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---|---:|"]
    for r in result["cases"]:
        of = r["rows"].get("optical_flow", {})
        ap = r["rows"].get("approximate", {})
        tgt = PAPER_TARGETS.get(r["cameras"])
        img = _capture(r)
        lines.append(f"| {r['case']} | {r['role']} | {r['cameras']} | {img} | {_f(r['peak_px'], '.3f')} | "
                     f"{_f(of.get('psnr'))} | {_f(of.get('psnr_plume'))} | {_f(of.get('peak_ratio'))} | "
                     f"{_f(ap.get('psnr'))} / {_f(ap.get('psnr_plume'))} | "
                     f"{'%g / %g' % tgt if tgt else '—'} | {_f(r['pipeline_seconds'], '.0f')} |")
    lines.append("")
    for role in ("tune", "report"):
        rs = [r for r in result["cases"] if r["role"] == role and "optical_flow" in r["rows"]]
        if rs:
            w = np.mean([r["rows"]["optical_flow"]["psnr"] for r in rs])
            p = np.mean([r["rows"]["optical_flow"]["psnr_plume"] for r in rs])
            lines.append(f"* Mean over the {role} cases: {w:.2f} dB whole box, {p:.2f} dB in plume.")
    chosen = [(r["case"], r["chosen"]) for r in result["cases"] if r.get("chosen")]
    if chosen:
        lines += ["", "## Chosen from the data", ""]
        for name, ch in chosen:
            lines.append(f"* {name}: " + ", ".join(f"{k} = {v}" for k, v in sorted(ch.items())))
    lab_md = lab_markdown(result)
    if lab_md:
        lines += ["", lab_md]
    lines += ["", f"Wall time {result['seconds']:.0f} s. Machine: {machine or 'n/a'}.", ""]
    return "\n".join(lines)


def _capture(r: dict) -> str:
    """A case's capture in words: size, distortion, format, texture, readout, lab preset."""
    s = f"{r['size'][0]}x{r['size'][1]}" + (" dist" if r["distortion"] else "") + \
        (f" {r['video']}" if r["video"] else " png") + \
        (f" {r['bits_per_pixel']:g} bit/px" if r.get("bits_per_pixel") not in (None, 0.16) else "")
    if r.get("texture"):
        s += f" {r['texture']} texture"
    if r.get("line_time") and r["line_time"] != DEFAULT_LINE_TIME:
        s += f" {1e6 * r['line_time']:g} us/row"
    if r.get("lab"):
        s += f" {r['lab']}"
    return s


def lab_pairs(result: dict) -> list[tuple[dict, dict]]:
    """``(clean, lab)`` result pairs: each lab case with its clean twin, both in ``result``."""
    by_name = {r["case"]: r for r in result["cases"]}
    return [(by_name[r["twin"]], r) for r in result["cases"]
            if r.get("lab") and r.get("twin") in by_name]


def _pct(x) -> str:
    return f"{100 * x:.1f}" if isinstance(x, (int, float)) and np.isfinite(x) else "—"


def _d(a, b) -> str:
    ok = all(isinstance(x, (int, float)) and np.isfinite(x) for x in (a, b))
    return f"{b - a:+.2f}" if ok else "—"


def lab_markdown(result: dict) -> str:
    """The clean-vs-lab table (empty without a pair): scores, their difference, the masks' and
    the hull's fill, the flow's median magnitude where nothing flows, and the run times."""
    pairs = lab_pairs(result)
    if not pairs:
        return ""
    lines = ["## Clean against lab captures", "",
             "Each lab case is its clean twin's capture with what a lab records (`-lab`: the `lab` preset of "
             "`pipeline/synthetic/lab.py`, a camera shaking against its reference by a 0.05 px random walk per "
             "frame from a 0.1 px offset, lamp flicker of 2 % gain and 1 grey level per frame, the background "
             "0.7 px out of focus, 25 hot pixels per camera; `-laball`: every effect, and 3 reference frames). "
             "Masks: mean fraction of the flow cells masked per camera-frame; hull: mean fraction of the box; "
             "quiet |flow|: median flow magnitude over the cells where the truth has no deflection.", "",
             "| case | role | whole box dB clean / lab (diff) | in plume dB clean / lab (diff) | peak ratio clean / lab "
             "| masks % clean / lab | hull % clean / lab | quiet abs flow px clean / lab | pipeline s clean / lab |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    dw, dp = {}, {}
    for clean, lab in pairs:
        a, b = clean["rows"].get("optical_flow", {}), lab["rows"].get("optical_flow", {})
        ga, gb = clean.get("diagnostics", {}), lab.get("diagnostics", {})
        lines.append(
            f"| {lab['case']} | {lab['role']} | {_f(a.get('psnr'))} / {_f(b.get('psnr'))} "
            f"({_d(a.get('psnr'), b.get('psnr'))}) | {_f(a.get('psnr_plume'))} / {_f(b.get('psnr_plume'))} "
            f"({_d(a.get('psnr_plume'), b.get('psnr_plume'))}) | {_f(a.get('peak_ratio'))} / "
            f"{_f(b.get('peak_ratio'))} | {_pct(ga.get('mask_fill'))} / {_pct(gb.get('mask_fill'))} | "
            f"{_pct(ga.get('hull_fill'))} / {_pct(gb.get('hull_fill'))} | "
            f"{_f(ga.get('quiet_flow_median'), '.3f')} / {_f(gb.get('quiet_flow_median'), '.3f')} | "
            f"{_f(clean['pipeline_seconds'], '.0f')} / {_f(lab['pipeline_seconds'], '.0f')} |")
        if "psnr" in a and "psnr" in b:
            dw.setdefault(lab.get("lab"), []).append(b["psnr"] - a["psnr"])
            dp.setdefault(lab.get("lab"), []).append(b["psnr_plume"] - a["psnr_plume"])
    lines.append("")
    for preset in dw:
        w, p = np.asarray(dw[preset]), np.asarray(dp[preset])
        within = int(np.sum((w >= -1.0) & (p >= -1.0)))
        lines.append(f"* `{preset}` against clean over {w.size} case(s): {w.mean():+.2f} dB whole box "
                     f"({w.min():+.2f} to {w.max():+.2f}), {p.mean():+.2f} dB in plume ({p.min():+.2f} to "
                     f"{p.max():+.2f}); within 1 dB of clean on both: {within} of {w.size}.")
    return "\n".join(lines)
