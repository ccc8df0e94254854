"""Diagnostic: realistic-family cases re-rendered from the CFD field upsampled before tracing.

    python benchmarks/realistic_rerender.py [--cases plume1-16cam-640,...] [--work /work/realistic/work_up2]
        [--upsample 2] [--cfd /work/realistic/work/_cfd]

The family's tracer interpolates the truth's central-difference gradient on the truth's own
2.5 mm grid, which removes the structure at that grid's scale that the scored truth keeps
(``benchmarks/realistic_forward_model.py``). This renders the named cases with the same
flows, rigs, noise and peak deflections but with the CFD knots cubic-upsampled by
``--upsample`` (the tracer's differences then attenuate the 2.5 mm structure far less, and
the truth is stored on the finer grid), runs the pipeline at the default parameters and
scores it as the family does. It does not change the family (``schlieren bench
realistic``): it measures what the consistent rendering would change before the family is
re-based on it. Reuses the family's CFD cache (``--cfd``); writes
``benchmarks/results/realistic_rerender.md`` / ``.json``.
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


def main(argv=None) -> int:
    from scipy import ndimage

    from schlieren.pipeline.synthetic.cfd import CFDResult
    from schlieren.workers import realistic as R

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="plume1-16cam-640,plume2-16cam-640,jet3-16cam-640,plume1-8cam-960-dist,"
                                       "jet3-8cam-960-dist")
    ap.add_argument("--work", default="/work/realistic/work_up2")
    ap.add_argument("--cfd", default="/work/realistic/work/_cfd", help="the family's CFD cache")
    ap.add_argument("--upsample", type=int, default=2)
    ap.add_argument("--results", default=str(RESULTS))
    a = ap.parse_args(argv)
    original = R.cfd_flow

    def upsampled(flow, cache_dir, *, voxel, progress=None):
        base = original(flow, Path(a.cfd), voxel=R.VOXEL, progress=progress)
        ex = np.stack([ndimage.zoom(np.asarray(e, np.float64), a.upsample, order=3, mode="nearest", grid_mode=True)
                       for e in base.excess]).astype(np.float32)
        grid = R._grid(voxel)
        if ex.shape[1:] != tuple(grid.shape):
            raise SystemExit(f"upsampled CFD {ex.shape[1:]} does not fill the {grid.shape} grid")
        return CFDResult(grid=grid, knot_times=base.knot_times, excess=ex, params=base.params)

    R.cfd_flow = upsampled  # this process only: ensure_session reads the flow through it
    t0 = time.perf_counter()
    out = {"command": "python benchmarks/realistic_rerender.py " + " ".join(argv or sys.argv[1:]),
           "upsample": a.upsample, "cases": {}}
    for name in [c for c in a.cases.split(",") if c]:
        case = [c for c in R.CASES if c.name == name]
        if not case:
            print(f"no family case {name}", file=sys.stderr)
            return 2
        case = dataclasses.replace(case[0], voxel=R.VOXEL / a.upsample)
        res = R.run_case(case, Path(a.work), truth_rows=False, progress=lambda m: print(m, flush=True))
        of = res["rows"]["optical_flow"]
        out["cases"][name] = {"whole_db": round(of["psnr"], 2), "plume_db": round(of["psnr_plume"], 2),
                              "peak_ratio": round(of["peak_ratio"], 3), "peak_px": round(res["peak_px"], 3),
                              "chosen": res.get("chosen"), "pipeline_seconds": round(res["pipeline_seconds"], 1)}
    out["seconds"] = round(time.perf_counter() - t0, 1)
    res_dir = Path(a.results)
    res_dir.mkdir(parents=True, exist_ok=True)
    (res_dir / "realistic_rerender.json").write_text(json.dumps(out, indent=1))
    lines = [f"# Realistic cases re-rendered from the CFD field upsampled {a.upsample}x (benchmarks/realistic_rerender.py)",
             "", f"Command: `{out['command'].strip()}`", "",
             "Same flows, rigs, noise and peak deflections as the family; the tracer then differentiates a field "
             f"{a.upsample}x finer than the CFD grid, and the truth is that field. Default parameters; whole box / in "
             "plume dB as the family scores.", "",
             "| case | peak px | whole box dB | in plume dB | peak ratio | chosen voxel mm / weight |",
             "|---|---:|---:|---:|---:|---|"]
    for name, r in out["cases"].items():
        ch = r.get("chosen") or {}
        lines.append(f"| {name} | {r['peak_px']} | {r['whole_db']:.2f} | {r['plume_db']:.2f} | {r['peak_ratio']:.2f} | "
                     f"{ch.get('voxel_mm')} / {ch.get('reg_weight', float('nan')):.4g} |")
    lines += ["", f"Wall time {out['seconds']} s (rendering included).", ""]
    (res_dir / "realistic_rerender.md").write_text("\n".join(lines))
    print(f"wrote {res_dir / 'realistic_rerender.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
