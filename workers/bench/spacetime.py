"""``schlieren bench spacetime``: space-time reconstruction against the per-frame solve.

The realistic family's cases (:mod:`schlieren.workers.realistic`) process 3 frames; a
space-time solve needs neighbours on both sides of most frames, so this benchmark renders
longer variants of the same captures (:func:`longer_cases`: the same rig, flow, noise and
codec, ``frames`` processed frames, named ``<case>-f<frames>``; the CFD knots cover up to 9)
and runs each once with space-time reconstruction on. Its store holds both results: the
per-frame solve (``gradient_frame``, the same solve the pipeline runs with space-time
off) and the space-time one (``gradient``, integrated into ``refractivity``); both are
integrated alike and scored as the family scores (whole box and in plume, every frame).
Other space-time settings are scored from the same store without running the pipeline
again (:func:`variant_refractivity`).

Results go to ``benchmarks/results/spacetime[_LABEL].md`` / ``.json``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from schlieren.pipeline.spacetime import SpaceTimeParams, motion_compensated_mean, window_frames
from schlieren.pipeline.stages import RunConfig, config_to_dict
from schlieren.storage import arrays_cache, bench_io
from schlieren.workers import realistic as rb

__all__ = ["DEFAULT_FRAMES", "BENCH_WINDOW", "longer_cases", "render_cases", "per_frame_refractivity",
           "variant_refractivity", "score_refractivity", "run_case", "run_family", "spacetime_markdown"]

log = logging.getLogger(__name__)

#: Processed frames of the longer variants (the CFD knots cover up to 9).
DEFAULT_FRAMES = 7
#: The space-time window a run takes when its configuration has space-time off.
BENCH_WINDOW = 1


def longer_cases(cases=None, frames: int = DEFAULT_FRAMES) -> tuple:
    """The family's cases (``cases``, default all) with ``frames`` processed frames, named
    ``<case>-f<frames>`` (their own session folders: the rendered content differs)."""
    if frames < 1:
        raise ValueError("frames must be at least 1")
    return tuple(dataclasses.replace(c, name=f"{c.name}-f{frames}", frames=int(frames))
                 for c in (rb.CASES if cases is None else cases))


def render_cases(work: Path, cases, *, progress: Callable[[str], None] | None = None) -> list[dict]:
    """Render (or find cached) every case's session under ``work``."""
    return [rb.ensure_session(c, Path(work), progress=progress) for c in cases]


def _integrate_all(ctx, gradients) -> np.ndarray:
    """The run's integration (as its ``integrate`` task) of one gradient per frame: (F, nz, ny, nx)."""
    from schlieren.pipeline import poisson

    out = []
    for k, g in enumerate(gradients):
        r, _ = poisson.integrate(np.asarray(g, dtype=np.float64), ctx.store.read("hull", (k,)), ctx.session.grid,
                                 r_ambient=ctx.session.medium.refractivity_ambient, params=ctx.config.poisson)
        out.append(np.asarray(r, dtype=np.float32))
    return np.stack(out)


def per_frame_refractivity(store_path) -> np.ndarray:
    """The per-frame solve of a space-time run (its ``gradient_frame``), integrated: (F, nz, ny, nx)."""
    from schlieren.workers.tasks import context

    ctx = context(str(store_path))
    return _integrate_all(ctx, (ctx.store.read("gradient_frame", (k,)) for k in range(ctx.n_frames)))


def variant_refractivity(store_path, params: SpaceTimeParams) -> tuple[np.ndarray, float]:
    """What the space-time stage with ``params`` would have made of a space-time run's
    per-frame solutions, integrated: ``((F, nz, ny, nx), seconds of the space-time means)``."""
    from schlieren.pipeline.tomography.solve import basis_set
    from schlieren.workers.tasks import context

    ctx = context(str(store_path))
    per = [ctx.store.read("gradient_frame", (k,)) for k in range(ctx.n_frames)]
    grads, seconds = [], 0.0
    for k in range(ctx.n_frames):
        frames = list(window_frames(k, ctx.n_frames, params.window))
        support = basis_set(ctx.store.read("hull", (k,)), ctx.config.tomography.hull_dilation)
        g, info = motion_compensated_mean([per[j] for j in frames], [j - k for j in frames], support, params=params)
        grads.append(g)
        seconds += info.seconds
    return _integrate_all(ctx, grads), seconds


def score_refractivity(store_path, truth_path, refractivity: np.ndarray, scratch: Path) -> dict:
    """The family's scores (:func:`schlieren.workers.evaluate.evaluate`) of ``refractivity``
    (one volume per frame of the store), written to the estimate store ``scratch``."""
    from schlieren.storage.store import ResultStore
    from schlieren.workers.evaluate import evaluate

    st = ResultStore.open(store_path, mode="r")
    grid_attrs = st.array("refractivity").attrs
    bench_io.write_estimate_store(scratch, refractivity, np.asarray(st.read("time", ()), dtype=np.float64),
                                  origin=grid_attrs["origin"], voxel_size=float(np.ravel(grid_attrs["voxel_size"])[0]))
    try:
        return rb._rows_from(evaluate(scratch, truth_path))
    finally:
        bench_io.remove_tree(scratch)


def _config(config: RunConfig | None) -> RunConfig:
    cfg = config or RunConfig()
    if cfg.spacetime.window > 0:
        return cfg
    return dataclasses.replace(cfg, spacetime=dataclasses.replace(cfg.spacetime, window=BENCH_WINDOW))


def run_case(case, work: Path, *, config: RunConfig | None = None, client=None, label: str = "",
             variants: dict[str, SpaceTimeParams] | None = None, keep_store: bool = True,
             progress: Callable[[str], None] | None = None) -> dict:
    """Render (or reuse) ``case``, run it with space-time on and score the per-frame and the
    space-time results (and ``variants``: other space-time settings on the same per-frame
    solutions), with the seconds of the tomography and space-time stages per frame."""
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.run import run_session

    say = progress or (lambda m: log.info("%s", m))
    info = rb.ensure_session(case, work, progress=say)
    d = Path(work) / case.name
    store = d / f"store-st{('-' + label) if label else ''}.zarr"
    bench_io.remove_tree(store)
    cfg = _config(config)
    t0 = time.perf_counter()
    summary = run_session(info["session"], store, client=client, serial=client is None, config=cfg)
    res = {"case": case.name, "role": case.role, "cameras": case.cameras, "size": list(case.size),
           "video": case.video, "frames": case.frames, "pipeline_seconds": time.perf_counter() - t0,
           "spacetime": dataclasses.asdict(cfg.spacetime), "rows": {}}
    if not summary.ok:
        res["failures"] = dict(summary.root_failures())
        return res
    n = max(case.frames, 1)
    res["seconds_per_frame"] = {s: summary.stage_seconds.get(s, 0.0) / n for s in ("tomography", "spacetime")}
    res["rows"]["per_frame"] = score_refractivity(store, info["truth"], per_frame_refractivity(store),
                                                  d / f"est-perframe-{label or 'st'}.zarr")
    res["rows"]["spacetime"] = rb._rows_from(evaluate(store, info["truth"]))
    res["chosen"] = rb._chosen(store)
    for name, params in (variants or {}).items():
        vol, sec = variant_refractivity(store, params)
        res["rows"][name] = score_refractivity(store, info["truth"], vol, d / f"est-{name}-{label or 'st'}.zarr")
        res["rows"][name]["spacetime_seconds_per_frame"] = sec / n
    pf, st = res["rows"]["per_frame"], res["rows"]["spacetime"]
    say(f"{case.name}: per-frame {pf['psnr']:.2f} / {pf['psnr_plume']:.2f} dB, space-time {st['psnr']:.2f} / "
        f"{st['psnr_plume']:.2f} dB (whole box / in plume)")
    if not keep_store:
        arrays_cache.remove_cache(store)
        bench_io.remove_tree(store)
    res["store"] = str(store) if keep_store else None
    return res


def run_family(work, cases, *, config: RunConfig | None = None, client=None, label: str = "",
               variants: dict[str, SpaceTimeParams] | None = None, keep_stores: bool = True,
               progress: Callable[[str], None] | None = None) -> dict:
    """:func:`run_case` of every case; ``{"cases": [...], "config": ..., "seconds"}``."""
    t0 = time.perf_counter()
    out = [run_case(c, Path(work), config=config, client=client, label=label, variants=variants,
                    keep_store=keep_stores, progress=progress) for c in cases]
    return {"label": label, "cases": out, "config": config_to_dict(_config(config)),
            "variants": {k: dataclasses.asdict(v) for k, v in (variants or {}).items()},
            "seconds": time.perf_counter() - t0}


def _f(x, spec=".2f") -> str:
    return format(x, spec) if isinstance(x, (int, float)) and np.isfinite(x) else "—"


def spacetime_markdown(result: dict, *, machine: str = "", command: str = "schlieren bench spacetime") -> str:
    """Markdown table of :func:`run_family`'s result: per case the per-frame and space-time
    scores (whole box / in plume), their difference and the stages' seconds per frame."""
    cfg = result["config"]["spacetime"]
    names = [n for n in ("per_frame", "spacetime") + tuple(result.get("variants", {}))]
    lines = [f"# Space-time reconstruction against the per-frame solve ({result.get('label') or 'defaults'})", "",
             f"Command: `{command}` (see `workers/bench/spacetime.py`). The realistic family's cases rendered "
             "with more frames (`<case>-f<N>`), run once with space-time on; `per_frame` is the same run's "
             "per-frame solve (`gradient_frame`), integrated alike. Space-time: "
             + ", ".join(f"{k} {v}" for k, v in cfg.items()) + ". Whole box / in plume dB over every frame.", ""]
    head = "| case | role | cams | image | " + " | ".join(names) + " | change | tomography s/frame | " \
           "space-time s/frame | ratio |"
    lines += [head, "|---|---|---:|---|" + "---:|" * (len(names) + 4)]
    for r in result["cases"]:
        rows = r.get("rows", {})
        cells = [f"{_f(rows.get(n, {}).get('psnr'))} / {_f(rows.get(n, {}).get('psnr_plume'))}" for n in names]
        pf, st = rows.get("per_frame", {}), rows.get("spacetime", {})
        change = "—"
        if pf and st:
            change = f"{st['psnr'] - pf['psnr']:+.2f} / {st['psnr_plume'] - pf['psnr_plume']:+.2f}"
        sec = r.get("seconds_per_frame", {})
        tomo, stsec = sec.get("tomography", float("nan")), sec.get("spacetime", float("nan"))
        img = f"{r['size'][0]}x{r['size'][1]}" + (f" {r['video']}" if r.get("video") else " png")
        lines.append(f"| {r['case']} | {r['role']} | {r['cameras']} | {img} | " + " | ".join(cells)
                     + f" | {change} | {_f(tomo)} | {_f(stsec)} | {_f(stsec / tomo if tomo else float('nan'))} |")
    lines.append("")
    for role in ("tune", "report"):
        rs = [r for r in result["cases"] if r["role"] == role and "spacetime" in r.get("rows", {})]
        if rs:
            d = [(r["rows"]["spacetime"]["psnr"] - r["rows"]["per_frame"]["psnr"],
                  r["rows"]["spacetime"]["psnr_plume"] - r["rows"]["per_frame"]["psnr_plume"]) for r in rs]
            lines.append(f"* Mean change over the {role} cases: {np.mean([a for a, _ in d]):+.2f} dB whole box, "
                         f"{np.mean([b for _, b in d]):+.2f} dB in plume.")
    lines += ["", f"Wall time {result['seconds']:.0f} s. Machine: {machine or 'n/a'}.", ""]
    return "\n".join(lines)
