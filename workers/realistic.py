"""``schlieren bench realistic``: accuracy on captures that look like real flows.

The project's Table 1 phantom is smooth (simulated coarse, upsampled with cubic
B-splines, truth block-averaged from a half-voxel grid) and deflects strongly (about
3 px): it measures the optical-flow noise floor, not resolution. This family is built to
look like a lab's capture instead:

* flows from a real CFD library (PhiFlow, :mod:`schlieren.pipeline.synthetic.cfd`): a
  buoyant plume and a hot jet simulated on the 2.5 mm grid of the paper's reconstruction,
  so the truth has structure down to that voxel (no block averaging); the knots are
  cubic-spline upsampled twice (:func:`~schlieren.pipeline.synthetic.cfd.upsample_cfd`)
  and that one field is both traced and scored, so the rendered data carry the structure
  the score asks for (the tracer's central differences on the 2.5 mm grid itself removed
  part of it: benchmarks/results/realistic_forward_model.md, docs/tuning.md "Synthetic
  truth");
* weak deflections: the excess temperature is scaled so that the 99.9th percentile of
  the deflection magnitude is :attr:`RealisticCase.peak_px` pixels (0.25 px at 640x480,
  0.375 px at 960x720 for the same flow);
* 8-bit frames with sensor noise, a rolling shutter and a strobe flash (offsets hidden),
  a reference recorded as several noisy frames (a video in the video cases), lens
  distortion on the 960x720 rigs, and lossy H.264 video at a camcorder's bit budget;
* 8 and 16 cameras on a half ring;
* variety no default was chosen on: a thin candle-like and a turbulent plume, finer and
  coarser noise and a printed dot pattern, a rolling shutter reading out for most of the
  frame period;
* every case also as a lab records it (``-lab``: the camera shaking against its
  reference, lamp flicker, defocus, hot pixels; :mod:`schlieren.pipeline.synthetic.lab`),
  reported beside its clean twin.

Cases are split into a *tune* set (flow seed 1), on which defaults may be chosen, and a
*report* set (other seeds, the jet) that no default was chosen on. Every case reports
the whole-box and the in-plume PSNR (SPEC section 4), the peak ratio, and the same
figures for the truth's own deflections (``approximate`` d_out of sec. 5: tomography and
integration alone, no optical flow) to separate the two error sources.

Modules: the cases (:mod:`.bench.realistic_cases`), their rendering and the cache
(:mod:`.bench.realistic_render`), what a run made of a capture
(:mod:`.bench.realistic_metrics`) and the Markdown (:mod:`.bench.realistic_report`); this
module runs and scores them. Files: sessions and the CFD knots are cached under the work
folder (rendering is the expensive part), results go to
``benchmarks/results/realistic[_LABEL].json/.md``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from schlieren.pipeline.stages import RunConfig, config_to_dict
from schlieren.storage import arrays_cache, bench_io
from schlieren.storage import synthetic_io as sio
from schlieren.workers.bench.realistic_cases import (BITRATE_CASES, BOX, CASES, CFD_KNOTS, CFD_T0, FLOWS,
                                                     PAPER_OPTICAL_FLOW, PAPER_TARGETS, QUICK_CASES,
                                                     QUICK_LAB_CASES, TEXTURES, VOXEL, Flow, RealisticCase,
                                                     clean_twin, select_cases)
from schlieren.workers.bench.realistic_metrics import capture_diagnostics
from schlieren.workers.bench.realistic_render import (MAX_PROBES, PEAK_TOL, PROPORTIONAL_STEPS, RENDER_TOL,
                                                      cfd_flow, ensure_session)
from schlieren.workers.bench.realistic_report import family_markdown, lab_markdown

__all__ = ["RealisticCase", "Flow", "FLOWS", "TEXTURES", "CASES", "QUICK_CASES", "QUICK_LAB_CASES", "BITRATE_CASES",
           "select_cases", "clean_twin", "cfd_flow", "ensure_session", "run_case", "run_family", "family_markdown",
           "lab_markdown", "PAPER_TARGETS", "PAPER_OPTICAL_FLOW", "BOX", "VOXEL", "CFD_T0", "CFD_KNOTS", "PEAK_TOL",
           "PROPORTIONAL_STEPS", "MAX_PROBES", "RENDER_TOL"]

log = logging.getLogger(__name__)


def _rows_from(ev: dict) -> dict:
    return {"psnr": ev["overall"]["psnr"], "rms": ev["overall"]["rms"], "psnr_plume": ev["plume"]["psnr"],
            "rms_plume": ev["plume"]["rms"],
            "peak_ratio": float(np.nanmean([f["peak_ratio"] for f in ev["frames"]])),
            "frames": [{k: f[k] for k in ("frame", "psnr", "psnr_plume", "peak_ratio")} for f in ev["frames"]]}


def _chosen(store_path) -> dict:
    """What the run chose from the data: the voxel, the regularisation weight and the noise it saw."""
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store_path, mode="r")
    out = {}
    try:
        vs = np.ravel(st.array("refractivity").attrs["voxel_size"])[0]
        out["voxel_mm"] = round(1e3 * float(vs), 3)
    except (KeyError, IndexError):
        pass
    for name in ("reg_weight", "rhs_noise"):
        try:
            v = np.asarray(st.read(name, ()), dtype=np.float64).ravel()
        except KeyError:
            continue
        out[name] = float(v[0]) if v.size == 1 else [float(x) for x in v]
    return out


def run_case(case: RealisticCase, work: Path, *, config: RunConfig | None = None, client=None, label: str = "",
             truth_rows: bool = True, progress: Callable[[str], None] | None = None,
             voxel: float | None = None, keep_store: bool = True) -> dict:
    """Render (or reuse) ``case``, run the full pipeline and score it; returns a JSON-able dict.

    ``voxel`` runs on a copy of the manifest that gives this ``volume.voxel_size`` (as a
    user's manifest may), instead of letting the pipeline choose it. ``keep_store=False``
    deletes the scored store, its cache folder and the truth rows' estimate afterwards (a
    failed run's store is kept to look at).
    """
    from schlieren.workers import bench
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.run import run_session

    say = progress or (lambda m: log.info("%s", m))
    info = ensure_session(case, work, progress=say)
    d = Path(work) / case.name
    if voxel is not None:
        info = dict(info, session=str(sio.manifest_with_voxel(info["session"], voxel)))
    store = d / f"store{('-' + label) if label else ''}.zarr"
    bench_io.remove_tree(store)
    cfg = config or RunConfig()
    t0 = time.perf_counter()
    summary = run_session(info["session"], store, client=client, serial=client is None, config=cfg)
    seconds = time.perf_counter() - t0
    twin = clean_twin(case)
    res = {"case": case.name, "role": case.role, "cameras": case.cameras, "size": list(case.size),
           "video": case.video, "distortion": case.distortion, "peak_px": info["peak_px"],
           "bits_per_pixel": case.bits_per_pixel if case.video else None, "flow": case.flow,
           "lab": case.lab, "twin": twin.name if twin is not None else None, "texture": case.texture,
           "line_time": case.line_time, "reference_frames": case.reference_frames,
           "render_seconds": info.get("render_seconds"), "pipeline_seconds": seconds, "rows": {}}
    if not summary.ok:
        res["failures"] = dict(summary.root_failures())
        return res
    res["rows"]["optical_flow"] = _rows_from(evaluate(store, info["truth"]))
    res["chosen"] = _chosen(store)
    res["diagnostics"] = capture_diagnostics(store, info["truth"])
    if truth_rows:
        vols = bench.truth_rows(info["session"], store, info["truth"], config=cfg)
        from schlieren.storage.session import load_session

        grid = load_session(info["session"]).grid
        for v in ("approximate",):
            p = d / f"est-{v}{('-' + label) if label else ''}.zarr"
            bench_io.write_estimate_store(p, vols[v], vols["time"], origin=grid.origin, voxel_size=grid.voxel_size,
                                          attrs={"variant": v})
            res["rows"][v] = _rows_from(evaluate(p, info["truth"]))
    of = res["rows"]["optical_flow"]
    say(f"{case.name}: {of['psnr']:.2f} dB whole box, {of['psnr_plume']:.2f} dB in plume, peak ratio "
        f"{of['peak_ratio']:.2f} ({seconds:.0f} s)")
    if not keep_store:
        arrays_cache.remove_cache(store)  # <store>.cache: the geometry
        for p in (store, d / f"est-approximate{('-' + label) if label else ''}.zarr"):
            bench_io.remove_tree(p)
    res["store"] = str(store) if keep_store else None
    return res


def run_family(work, cases=CASES, *, config: RunConfig | None = None, client=None, label: str = "",
               truth_rows: bool = True, progress: Callable[[str], None] | None = None,
               voxel: float | None = None, keep_stores: bool = True) -> dict:
    """Every case of ``cases``; returns ``{"cases": [...], "config": ..., "seconds"}``."""
    t0 = time.perf_counter()
    out = [run_case(c, Path(work), config=config, client=client, label=label, truth_rows=truth_rows,
                    progress=progress, voxel=voxel, keep_store=keep_stores) for c in cases]
    return {"label": label, "cases": out, "config": config_to_dict(config or RunConfig()), "voxel": voxel,
            "seconds": time.perf_counter() - t0}


