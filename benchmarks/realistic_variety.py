"""The realistic family's variety cases, clean against lab, gathered from several bench runs (issue 33).

    python benchmarks/realistic_variety.py [LABEL ...]

Each LABEL names a ``schlieren bench realistic --label LABEL`` run whose
``benchmarks/results/realistic_LABEL.json`` holds a clean case and its lab twin (or more
cases). This script merges their cases (a case run under several labels: the last label
given wins) and writes ``benchmarks/results/realistic_variety.json`` and ``.md``: per case
the scores, masks, hull and pipeline time, and each lab case beside its clean twin
(:func:`schlieren.workers.bench.realistic_report.lab_markdown`). The prose around the
tables (what the cases are, what was looked at where a lab case misses) is kept in
``realistic_variety_notes.md`` beside it and copied in.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from schlieren.workers.bench.realistic_report import _capture, _f, _pct, lab_markdown

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_LABELS = ("i33v_p2", "i33v_dots", "i33v_dots_fix", "i33v_turb", "i33v_longro", "i33v_laball", "i33v_tex",
                  "i33v_candle", "m3v_clean", "m3v_fix", "m3v_turb", "m3v_tex", "m3_jetcandle")


def merge(labels) -> dict:
    """The cases of every label's results file that exists, in the order given."""
    cases: dict[str, dict] = {}
    runs = []
    for label in labels:
        p = RESULTS / f"realistic_{label}.json"
        if not p.exists():
            continue
        d = json.loads(p.read_text())
        runs.append({"label": label, "machine": d.get("machine"), "wall_seconds": d.get("wall_seconds"),
                     "cases": [c["case"] for c in d["cases"]]})
        for c in d["cases"]:
            cases[c["case"]] = dict(c, label=label)
    return {"label": "variety", "runs": runs, "cases": list(cases.values())}


def case_table(result: dict) -> str:
    lines = ["| case | role | capture | run label | whole box dB | in plume dB | masks % (max) | hull % | "
             "pipeline s |", "|---|---|---|---|---:|---:|---:|---:|---:|"]
    for r in result["cases"]:
        of = r["rows"].get("optical_flow", {})
        g = r.get("diagnostics", {})
        fail = " (failed)" if r.get("failures") else ""
        lines.append(f"| {r['case']}{fail} | {r['role']} | {_capture(r)} | {r['label']} | {_f(of.get('psnr'))} | "
                     f"{_f(of.get('psnr_plume'))} | {_pct(g.get('mask_fill'))} ({_pct(g.get('mask_fill_max'))}) | "
                     f"{_pct(g.get('hull_fill'))} | {_f(r['pipeline_seconds'], '.0f')} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    labels = (argv if argv else None) or list(DEFAULT_LABELS)
    result = merge(labels)
    notes = RESULTS / "realistic_variety_notes.md"
    parts = [notes.read_text().rstrip() if notes.exists() else "# Realistic family: variety cases, clean and lab",
             "", "## Every case", "", case_table(result), "", lab_markdown(result), "", "## Runs", ""]
    for run in result["runs"]:
        parts.append(f"* `{run['label']}` ({', '.join(run['cases'])}): wall {_f(run['wall_seconds'], '.0f')} s; "
                     f"{run['machine']}; tables in realistic_{run['label']}.md.")
    (RESULTS / "realistic_variety.md").write_text("\n".join(parts) + "\n")
    (RESULTS / "realistic_variety.json").write_text(json.dumps(result, indent=1) + "\n")
    print(f"{len(result['cases'])} cases from {len(result['runs'])} runs -> {RESULTS / 'realistic_variety.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
