"""A/B of the defaults against a parameter file on small synthesized sessions (check_common's two and two
more seeds), optionally rendered with a reference of few noisy frames, as a lab records it.

    python benchmarks/small_sessions_ab.py --work DIR [--cases tiny,plume,tiny4,plume8] [--reference-frames 3]
        --params OFF.yaml [--label NAME]

Each case is synthesized once (``schlieren.workers.synth.synthesize``; ``--reference-frames 0`` keeps its
one noise-free reference image), run serially with the parameters of ``--params`` ("A") and with the
defaults ("B"), and scored against its truth (whole box / in plume PSNR, SPEC section 4). Writes
``benchmarks/results/small_sessions_<label>.json`` and ``.md``. Used for the reference top-up
(``capture.reference_topup``: ``--params`` with ``capture: {reference_topup: 0}``;
benchmarks/results/reference_topup.md) and the hull's outlier rule (``hull.outlier_ratio``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"

CASES = {
    "tiny": dict(cameras=4, ring="half", phantom="blob", frames=3, size=(192, 144), seed=3, recon_voxel=0.005,
                 supersample=2),
    "plume": dict(cameras=6, ring="half", phantom="plume", frames=2, size=(256, 192), seed=5, recon_voxel=0.006,
                  supersample=2),
    "tiny4": dict(cameras=4, ring="half", phantom="blob", frames=3, size=(192, 144), seed=4, recon_voxel=0.005,
                  supersample=2),
    "plume8": dict(cameras=8, ring="half", phantom="plume", frames=2, size=(256, 192), seed=6, recon_voxel=0.006,
                   supersample=2),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", required=True, type=Path, help="scratch folder for the sessions and stores")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--reference-frames", type=int, default=0, help="noisy reference frames (0: one noise-free image)")
    ap.add_argument("--params", required=True, help="YAML of run parameters for run A (B: the defaults)")
    ap.add_argument("--label", default="ab")
    ap.add_argument("--seeds", type=int, default=1, help="each case also rendered with its seed + 1 .. + (seeds - 1)")
    args = ap.parse_args(argv)

    from schlieren.pipeline.stages import config_from_dict
    from schlieren.storage.params_io import read_params
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.run import run_session
    from schlieren.workers.synth import synthesize

    params_a = read_params(args.params)
    rows = []
    todo = [(f"{n}+{k}" if k else n, {**CASES[n], "seed": CASES[n]["seed"] + k})
            for n in args.cases.split(",") for k in range(args.seeds)]
    for name, kw in todo:
        sess = synthesize(args.work / name, **{**kw, "reference_frames": args.reference_frames})
        row = {"case": name, "seed": kw["seed"]}
        for run, cfg in (("A", params_a), ("B", None)):
            out = args.work / f"{name}_{run}.zarr"
            shutil.rmtree(out, ignore_errors=True)
            s = run_session(sess.session, out, serial=True, config=config_from_dict(cfg))
            if not s.ok:
                raise SystemExit(f"{name} run {run} failed: {s.failures}")
            e = evaluate(out, sess.session.parent / "truth.zarr")
            row[run] = [round(e["overall"]["psnr"], 2), round(e["plume"]["psnr"], 2)]
            shutil.rmtree(out, ignore_errors=True)
        rows.append(row)
        print(row, flush=True)
    cmd = (f"python benchmarks/small_sessions_ab.py --work DIR --cases {args.cases} --reference-frames "
           f"{args.reference_frames} --params {args.params} --label {args.label} --seeds {args.seeds}")
    (RESULTS / f"small_sessions_{args.label}.json").write_text(json.dumps(
        {"command": cmd, "params_a": params_a, "rows": rows, "load": os.getloadavg()}, indent=1))
    lines = [f"# Small synthesized sessions: `{args.params}` (A) against the defaults (B)", "",
             f"Command: `{cmd}`. Reference: "
             + (f"{args.reference_frames} noisy frames." if args.reference_frames else "one noise-free image."),
             f" A = {json.dumps(params_a)}. Whole box / in plume PSNR dB.", "",
             "| case | A | B (defaults) | B - A |", "|---|---:|---:|---:|"]
    for r in rows:
        d = [round(b - a, 2) for a, b in zip(r["A"], r["B"])]
        lines.append(f"| {r['case']} (seed {r['seed']}) | {r['A'][0]} / {r['A'][1]} | {r['B'][0]} / {r['B'][1]} | {d[0]:+.2f} / {d[1]:+.2f} |")
    d = np.array([[b - a for a, b in zip(r["A"], r["B"])] for r in rows])
    lines += ["", f"Mean B - A over {len(rows)} sessions: {d[:, 0].mean():+.2f} / {d[:, 1].mean():+.2f} dB "
              f"(standard error {d[:, 0].std(ddof=1) / np.sqrt(len(rows)) if len(rows) > 1 else float('nan'):.2f} / "
              f"{d[:, 1].std(ddof=1) / np.sqrt(len(rows)) if len(rows) > 1 else float('nan'):.2f})."]
    (RESULTS / f"small_sessions_{args.label}.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
