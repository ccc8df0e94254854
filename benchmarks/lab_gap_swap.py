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


def flow_errors(store: Path, truth: Path, plume_px: float = 0.02) -> dict:
    """The stored flows against the truth's deflections on the flow cells (the flow's window
    blur included): RMS error on the cells where the truth exceeds ``plume_px`` (in plume) and
    where it is zero (quiet), and each split into the part common to every frame (fixed
    pattern: what a reference's noise leaves) and the part that changes from frame to frame,
    from the cells' mean error over the frames and their spread (``F = mean(m^2) - s^2 / n``)."""
    from schlieren.storage import synthetic_io as sio
    from schlieren.storage.store import ResultStore
    from schlieren.workers.bench.realistic_metrics import _quiet_cells

    st = ResultStore.open(store, mode="r")
    flow = np.asarray(st.read("flow"), dtype=np.float64)  # camera, frame, v, u, 2
    u, v = (np.asarray(st.read(k), dtype=np.float64) for k in ("u", "v"))
    t = sio.read_truth(truth)
    tf = int(t.attrs.get("flow_factor", 3))
    tdef = np.asarray(t.group["deflection"][...], dtype=np.float64)
    n = min(flow.shape[1], tdef.shape[1])
    rows = np.clip((v // tf).astype(int), 0, tdef.shape[2] - 1)
    cols = np.clip((u // tf).astype(int), 0, tdef.shape[3] - 1)
    out = {}
    for name in ("plume", "quiet"):
        tot, fixed, cells = 0.0, 0.0, 0
        for c in range(flow.shape[0]):
            td = tdef[c, :n][:, rows][:, :, cols]  # frame, v, u, 2
            if name == "quiet":
                sel = np.all([_quiet_cells(tdef[c, k], tf, u, v) for k in range(n)], axis=0)
            else:
                sel = np.all(np.hypot(td[..., 0], td[..., 1]) > plume_px, axis=0)
            e = flow[c, :n] - td
            ok = sel & np.isfinite(e).all(axis=(0, -1))
            e = e[:, ok]  # frame, cells, 2
            if e.shape[1] == 0:
                continue
            m = e.mean(axis=0)
            s2 = e.var(axis=0, ddof=1) if n > 1 else np.zeros_like(m)
            tot += float(np.sum(e ** 2) / n)
            fixed += float(np.sum(m ** 2) - np.sum(s2) / n)
            cells += e.shape[1]
        out[name] = {"rms": float(np.sqrt(tot / max(cells, 1))),
                     "fixed_rms": float(np.sqrt(max(fixed, 0.0) / max(cells, 1))), "cells": cells}
    return out


def hull_variants(store: Path, truth: Path, frame: int) -> dict:
    """One run's frame solved from its own flows through hulls carved from its own masks
    with other settings: the strict intersection (the run's), one or two cameras allowed to
    miss a voxel (``hull.max_misses``), the masks dilated by one more cell; and the hull's
    plume voxels lost (the truth's plume, ``|n - n_amb|`` above 1 % of its range)."""
    import dataclasses

    from realistic_bounds import integrate_and_score
    from scipy import ndimage

    from schlieren.pipeline import hull as hullmod
    from schlieren.pipeline import metrics, tomography
    from schlieren.workers import tasks

    k = int(frame)
    ctx, geom, t_on, r_amb = _context(store, truth, k)
    params, blur = tasks.tomo_params(ctx), tasks.flow_blur(ctx)
    flows = ctx.tomography_flows(k)
    ms = np.stack([np.asarray(ctx.store.read("mask", (c, k)), bool) for c in range(len(ctx.cameras))])
    plume = metrics.plume_mask(t_on, r_amb)
    rows = {}
    for name, misses, grow in (("run hull", 0, 0), ("max_misses 1", 1, 0), ("max_misses 2", 2, 0),
                               ("masks dilated 1 more cell", 0, 1)):
        m = ms if not grow else np.stack([ndimage.binary_dilation(x, iterations=grow) for x in ms])
        hp = dataclasses.replace(ctx.config.hull, max_misses=misses)
        h = hullmod.visual_hull(m, ctx.cameras, ctx.session.grid, ctx.flow_grid, params=hp)
        g, _ = tomography.solve_gradient(geom, flows, h, params=params, **blur)
        w, p = integrate_and_score(ctx, g, h, t_on, r_amb)
        rows[name] = {"whole_db": w, "plume_db": p, "hull_voxels": int(h.sum()),
                      "plume_voxels_outside": int((plume & ~h).sum()), "plume_voxels": int(plume.sum())}
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clean", required=True)
    ap.add_argument("--lab", required=True)
    ap.add_argument("--truth", required=True)
    ap.add_argument("--frame", type=int, default=1)
    ap.add_argument("--out", default=None, help="JSON file to write")
    ap.add_argument("--hulls", action="store_true", help="only each run's own flows through other hulls")
    ap.add_argument("--errors-only", action="store_true", help="only the flows' errors against the truth")
    a = ap.parse_args(argv)
    if a.hulls:
        for s in (a.clean, a.lab):
            for name, r in hull_variants(Path(s), Path(a.truth), a.frame).items():
                print(s, name, json.dumps(r), flush=True)
        return 0
    if a.errors_only:
        for s in (a.clean, a.lab):
            print(s, json.dumps(flow_errors(Path(s), Path(a.truth))))
        return 0
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
