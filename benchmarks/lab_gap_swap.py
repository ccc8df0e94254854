"""Where a lab capture's loss sits: its flows or its hull, inside the plume or outside (issue 33).

    python benchmarks/lab_gap_swap.py --clean STORE --lab STORE --truth TRUTH.zarr [--frame 1]

Takes the kept stores of one family case run clean and as a lab records it (the same rig,
grid and geometry: ``schlieren bench realistic ... --keep-stores``), and solves one output frame
as the lab run solves it (its weight, window model, iterations) from mixtures of the two runs'
flows and hulls, each scored as the family scores (whole box / in plume dB):

* each run's own flows and hull, and the two swapped (the hull's share of the gap);
* the clean flows plus the lab flows' difference from them on the rays that see the plume
  only, or on the other rays only (where the lab flow's extra error costs: in the plume,
  bias and noise, or outside it, noise);
* the clean flows plus that difference scaled by 0.5 (the cost is quadratic in the error:
  a noise-like difference halved costs a quarter);
* the lab flows' gain against the clean ones on the plume rays (an attenuation the defocus
  or a correction adds) and the RMS of the difference inside and outside the plume.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _context(store: Path, truth: Path, frame: int):
    from schlieren.pipeline import metrics
    from schlieren.storage import synthetic_io as sio
    from schlieren.workers import tasks
    from schlieren.workers.evaluate import _r_ambient, _truth_at
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key

    ctx = tasks.context(str(store))
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    t = sio.read_truth(truth)
    tgrid = metrics.grid_from_attrs(t.grid_origin, t.voxel_size, tuple(t.refractivity.shape[1:]))
    tv, _ = _truth_at(t, float(ctx.times()[int(frame)]))
    return ctx, geom, metrics.resample_space(tv, tgrid, ctx.session.grid), _r_ambient(t)


def swap(clean: Path, lab: Path, truth: Path, frame: int) -> dict:
    from realistic_bounds import integrate_and_score

    from schlieren.pipeline import tomography
    from schlieren.workers import tasks

    k = int(frame)
    cc, _, _, _ = _context(clean, truth, k)
    lc, geom, t_on, r_amb = _context(lab, truth, k)
    params, blur = tasks.tomo_params(lc), tasks.flow_blur(lc)
    fc, fl = cc.tomography_flows(k), lc.tomography_flows(k)
    hc, hl = cc.store.read("hull", (k,)), lc.store.read("hull", (k,))
    # rays that see the plume: the clean run's masks (dilated as the hull is carved from them)
    masks = np.stack([np.asarray(cc.store.read("mask", (c, k)), bool) for c in range(len(cc.cameras))])
    if masks.shape[1:3] != fc.shape[1:3]:
        masks = tomography.bin_cells(masks[..., None].astype(np.float32), cc.ray_binning)[..., 0] > 0
    diff = np.where(np.isfinite(fl) & np.isfinite(fc), fl - fc, 0.0)

    def run(flows, hull):
        g, _ = tomography.solve_gradient(geom, flows, hull, params=params, **blur)
        w, p = integrate_and_score(lc, g, hull, t_on, r_amb)
        return {"whole_db": w, "plume_db": p}

    rows = {
        "clean flows, clean hull": run(fc, hc),
        "lab flows, lab hull (the lab run)": run(fl, hl),
        "lab flows, clean hull": run(fl, hc),
        "clean flows, lab hull": run(fc, hl),
        "clean flows + lab difference in the masks, lab hull": run(fc + diff * masks[..., None], hl),
        "clean flows + lab difference outside the masks, lab hull": run(fc + diff * ~masks[..., None], hl),
        "clean flows + half the lab difference, lab hull": run(fc + 0.5 * diff, hl),
    }
    ok = np.isfinite(fl).all(-1) & np.isfinite(fc).all(-1)
    inside, outside = ok & masks, ok & ~masks
    gain = [float(np.sum(fl[inside, i] * fc[inside, i]) / np.sum(fc[inside, i] ** 2)) for i in range(2)]
    stats = {"gain_in_masks": gain,
             "diff_rms_in_masks": float(np.sqrt(np.mean(diff[inside] ** 2))),
             "diff_rms_outside": float(np.sqrt(np.mean(diff[outside] ** 2))),
             "clean_rms_in_masks": float(np.sqrt(np.mean(fc[inside] ** 2))),
             "mask_fraction": float(masks.mean()),
             "hull_voxels": [int(hc.sum()), int(hl.sum()), int((hc & hl).sum())]}
    return {"frame": k, "rows": rows, "stats": stats}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clean", required=True)
    ap.add_argument("--lab", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--frame", type=int, default=1)
    ap.add_argument("--out", default=None, help="JSON file to write")
    a = ap.parse_args(argv)
    res = swap(Path(a.clean), Path(a.lab), Path(a.truth), a.frame)
    res["command"] = "python benchmarks/lab_gap_swap.py " + " ".join(argv or sys.argv[1:])
    for name, r in res["rows"].items():
        print(f"{r['whole_db']:6.2f} / {r['plume_db']:6.2f}  {name}")
    print(json.dumps(res["stats"]))
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
