"""Whether ``hull.outlier_ratio`` acts on a run, from its kept store (issue 33; lab_hull.md).

    python benchmarks/hull_outliers.py STORE [STORE ...] [--ratio 3] [--truth TRUTH.zarr]

The masks do not depend on the hull, so a run's stored masks (default or not) say for every
frame how many voxels each camera's mask alone rejects and whether the largest count exceeds
``ratio`` times the median camera's (the rule acts: that camera is forgiven) or not (the hull is
exactly the strict intersection, and so is everything downstream of it). With ``--truth`` (one
per store, in order) also the truth's plume voxels (``|n - n_amb|`` above 1 % of its range) the
strict hull and the rule's hull leave out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def outliers(store: str, ratio: float, truth: str | None = None) -> list[dict]:
    from schlieren.pipeline import hull as hullmod
    from schlieren.pipeline import metrics
    from schlieren.workers import tasks

    ctx = tasks.context(store)
    grid, cams = ctx.session.grid, ctx.cameras
    proj = hullmod.hull_projection(cams, grid, ctx.flow_grid, params=ctx.config.hull)
    rule = dataclasses.replace(ctx.config.hull, max_misses=0, outlier_ratio=ratio)
    strict = dataclasses.replace(rule, outlier_ratio=0.0)
    rows = []
    for k in range(ctx.n_frames):
        ms = np.stack([np.asarray(ctx.store.read("mask", (c, k)), bool) for c in range(len(cams))])
        alone = hullmod.lone_rejections(ms, cams, grid, ctx.flow_grid, params=strict, projection=proj)
        med = max(float(np.median(alone)), 1.0)
        row = {"frame": k, "largest_over_median": round(float(alone.max()) / med, 2),
               "forgiven": [cams[c].name for c in np.flatnonzero(alone > ratio * med)]}
        if truth:
            from lab_gap_swap import _context
            _, _, t_on, r_amb = _context(Path(store), Path(truth), k)
            plume = metrics.plume_mask(t_on, r_amb)
            for name, p in (("strict", strict), ("rule", rule)):
                h = hullmod.visual_hull(ms, cams, grid, ctx.flow_grid, params=p, projection=proj)
                row[f"{name}_hull"], row[f"{name}_plume_out"] = int(h.sum()), int((plume & ~h).sum())
        rows.append(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stores", nargs="+")
    ap.add_argument("--ratio", type=float, default=3.0)
    ap.add_argument("--truth", action="append", default=None, help="the truth of each store, in order")
    a = ap.parse_args(argv)
    truths = (a.truth or []) + [None] * (len(a.stores) - len(a.truth or []))
    for store, truth in zip(a.stores, truths):
        for row in outliers(store, a.ratio, truth):
            print(json.dumps({"store": store, **row}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
