"""``schlieren bench table1``: the paper's Table 1 (sec. 6) on the project's synthetic plume.

For every rig (ring, camera count) one synthetic session is rendered with its ground
truth (:func:`schlieren.workers.synth.synthesize`) and processed by the full pipeline
(:func:`schlieren.workers.run.run_session`). Then the rows of Table 1 are reconstructed:

``exact``
    Ray-traced exit directions: ``n_amb (d_out - d_in)`` from the truth's ``d_in`` /
    ``d_out`` -> gradient tomography (eq. 5) -> Poisson integration (eq. 8 with the default
    ``PoissonParams``: plain, alpha = 1, see :mod:`schlieren.pipeline.poisson`).
``approximate``
    The truth's image-plane ``deflection`` used as the optical flow, i.e. the
    single-refraction estimate ``d_out^`` of sec. 5 -> the same tomography and Poisson.
``optical_flow``
    The pipeline's own refractivity (optical flow on the rendered images, hull, tomography,
    Poisson): the full-system error of the paper's row three.
``approximate_aniso`` (one rig)
    ``approximate`` integrated with the Appendix's tensor active (alpha 0.8, 16-bit units),
    to measure what the anisotropic integration gains (the paper reports a gain; ours:
    docs/tuning.md, "Poisson").
``poisson_bound`` (once)
    Sec. 6: the truth's gradient from an "unknown" discretisation (central differences on
    the fine truth grid, block-averaged to the reconstruction grid) integrated by the
    anisotropic Poisson solver inside the truth's support dilated by ``bound_dilation``
    voxels (and, when that rig is run, inside the pipeline's hull of ``hull_rig``).

The truth-driven rows use, per frame, the pipeline run's visual hull and its tomography
and Poisson parameters (warm-started like the pipeline), so they differ from the
``optical_flow`` row only in the deflections. Every row is written as a small
refractivity store and scored by :func:`schlieren.workers.evaluate.evaluate` (SPEC
section 4: relative RMS over the whole box, normalised by the truth's range per frame, at
the store's frame times on the store's grid; PSNR = 20 log10(1 / RMS)).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline import metrics, poisson, tomography
from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.stages import RunConfig, bind_medium, config_from_dict
from schlieren.storage import arrays_cache, bench_io
from schlieren.storage import synthetic_io as sio
from schlieren.storage.session import load_session
from schlieren.storage.store import ResultStore
from schlieren.workers.evaluate import evaluate

__all__ = ["Table1Config", "PAPER_TABLE1", "PAPER_POISSON_BOUND", "DEFAULT_RIGS", "QUICK_RIGS",
           "parse_rigs", "run_table1", "bench_rig", "truth_rows", "poisson_bound", "bound_gradient",
           "ref_rig", "rig_failures"]

log = logging.getLogger(__name__)

#: Table 1 of the paper: (ring, cameras) -> row -> (PSNR dB, RMS %).
PAPER_TABLE1: dict[tuple[str, int], dict[str, tuple[float, float]]] = {
    ("half", 8): {"exact": (40.55, 0.94), "approximate": (40.43, 0.97), "optical_flow": (39.29, 1.09)},
    ("half", 16): {"exact": (41.29, 0.86), "approximate": (40.73, 0.91), "optical_flow": (39.84, 1.02)},
    ("half", 32): {"exact": (41.39, 0.85), "approximate": (40.76, 0.91), "optical_flow": (39.88, 1.01)},
    ("full", 7): {"approximate": (40.03, 1.00)},
    ("full", 15): {"approximate": (40.74, 0.92)},
    ("full", 31): {"approximate": (40.83, 0.91)},
}
#: Sec. 6: Poisson integration of the true gradient alone (PSNR dB, RMS %).
PAPER_POISSON_BOUND = (42.15, 0.78)

DEFAULT_RIGS: tuple[tuple[str, int], ...] = (("half", 8), ("half", 16), ("half", 32),
                                             ("full", 7), ("full", 15), ("full", 31))
QUICK_RIGS: tuple[tuple[str, int], ...] = (("half", 3),)

#: Store times (the pipeline's clock, estimated from the flash) within this many seconds of a
#: truth output instant use that instant's ray-traced deflections (frame period: 1/60 s).
TIME_TOLERANCE = 1e-4

FINE_BLOCK_TEXT = "central differences on the truth grid (half voxel), block-averaged"
COARSE_CENTRAL_TEXT = "truth sampled at the reconstruction voxels, central differences"

ROWS = ("exact", "approximate", "optical_flow")
#: The Appendix's diffusion tensor where it acts (alpha 0.8 in 16-bit units; the 8-bit
#: units leave D = alpha I, i.e. plain Poisson): the ``approximate_aniso`` row.
ANISO = {"alpha": 0.8, "value_scale": 65535.0}
ROW_LABELS = {"exact": "Ground truth (d_out)", "approximate": "Approximate (d^_out)",
              "optical_flow": "Optical flow", "approximate_aniso": "Approximate, anisotropic Poisson (alpha 0.8, tensor active)"}


@dataclass(frozen=True)
class Table1Config:
    """Sizes and options of the Table 1 benchmark.

    Attributes
    ----------
    rigs : tuple of (str, int)
        ``(ring, cameras)`` per rig, ring in ``{"half", "full"}``.
    size : (int, int)
        Image ``(width, height)``, pixels.
    frames : int
        Output frames per session.
    recon_voxel : float
        Reconstruction voxel, metres (the truth grid is half of it).
    flow_factor : int
        Flow-grid downsampling of the rendering (truth deflections) and the pipeline's
        ``flow.factor`` (with ``flow.auto_factor`` the largest it takes).
    supersample : int
        Rendering supersampling of the synthetic images.
    seed : int
        Phantom / background / noise seed (the same for every rig).
    noise : float
        Sensor noise, 8-bit grey levels.
    workers : int
        Dask workers of a local cluster for the pipeline runs; 0 runs them serially.
    plain_rig : (str, int) or None
        Rig whose ``approximate`` row is also integrated with the anisotropic tensor active.
    hull_rig : (str, int) or None
        Rig whose pipeline hull is also used for the Poisson-only bound.
    bound_dilation : int
        Dilation (voxels, 26-connected) of the truth's support for the bound's hull.
    support_threshold : float
        A voxel belongs to the truth's support where ``|r - r_ambient|`` exceeds this
        fraction of the frame's range.
    params : dict or None
        Run parameters (the ``--params`` mapping, :func:`~schlieren.pipeline.stages.config_from_dict`)
        instead of the defaults; ``flow.factor`` is always ``flow_factor`` (with the default
        ``flow.auto_factor`` the largest factor the runs may take: 2 on the 480x360 rigs).
    """

    rigs: tuple[tuple[str, int], ...] = DEFAULT_RIGS
    size: tuple[int, int] = (480, 360)
    frames: int = 2
    recon_voxel: float = 0.0025
    flow_factor: int = 3
    supersample: int = 3
    seed: int = 0
    noise: float = 1.5
    workers: int = 0
    plain_rig: tuple[str, int] | None = ("half", 16)
    hull_rig: tuple[str, int] | None = ("half", 16)
    bound_dilation: int = 2
    support_threshold: float = 1e-3
    params: dict | None = None

    def run_config(self) -> RunConfig:
        """The pipeline's configuration for every rig: ``params`` (or the defaults) with the
        flow grid's factor of this benchmark."""
        base = config_from_dict(self.params) if self.params else RunConfig()
        return dataclasses.replace(base, flow=dataclasses.replace(base.flow, factor=self.flow_factor))


def parse_rigs(text: str) -> tuple[tuple[str, int], ...]:
    """``"half:8,full:7"`` -> ``(("half", 8), ("full", 7))``."""
    out = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        ring, _, n = item.partition(":")
        ring = ring.strip().lower()
        if ring not in ("half", "full") or not n.strip().isdigit() or int(n) < 2:
            raise ValueError(f"rig {item!r}: expected half:N or full:N with N >= 2 cameras")
        out.append((ring, int(n)))
    if not out:
        raise ValueError("no rigs given")
    return tuple(out)


def _rig_name(rig: tuple[str, int]) -> str:
    return f"{rig[0]}{rig[1]:02d}"


def _score(est_path: Path, volumes: np.ndarray, times: np.ndarray, grid: Grid, truth_path, variant: str) -> dict:
    """Write one variant as an estimate store and score it with :func:`evaluate`."""
    bench_io.write_estimate_store(est_path, volumes, times, origin=grid.origin, voxel_size=grid.voxel_size,
                                  attrs={"variant": variant})
    res = evaluate(est_path, truth_path)
    return _rows(res)


def _rows(res: dict) -> dict:
    """A Table 1 row from :func:`evaluate`: whole box and in plume (SPEC section 4)."""
    return {"rms": res["overall"]["rms"], "psnr": res["overall"]["psnr"],
            "psnr_plume": res["plume"]["psnr"], "rms_plume": res["plume"]["rms"],
            "frames": [{"frame": r["frame"], "rms": r["rms"], "psnr": r["psnr"], "psnr_plume": r["psnr_plume"]}
                       for r in res["frames"]]}


def _geometry(session, store_path, flow_grid: FlowGrid, cfg: RunConfig):
    """The pipeline run's cached tomography geometry, or a fresh one if it is not cached."""
    key = tomography.content_hash(session.cameras, session.grid, flow_grid, cfg.tomography)
    path = arrays_cache.cache_dir(store_path, "geometry", key)
    if arrays_cache.has_arrays(path):
        return tomography.load_geometry(arrays_cache.load_arrays(path))
    log.info("no cached geometry in %s; building it", store_path)
    return tomography.build_geometry(session.cameras, session.grid, flow_grid, params=cfg.tomography)


def _run_tomo_params(store: ResultStore, cfg: RunConfig):
    """The run's tomography parameters with the weight its regularisation stage chose (if any)."""
    try:
        w = float(np.asarray(store.read("reg_weight", ())).ravel()[0])
    except (KeyError, ValueError, IndexError):
        return cfg.tomography
    return dataclasses.replace(cfg.tomography, reg_weight=w) if np.isfinite(w) else cfg.tomography


def _truth_frame(truth: sio.Truth, t: float) -> int:
    j = int(np.argmin(np.abs(truth.time - t)))
    if abs(truth.time[j] - t) > TIME_TOLERANCE:
        log.warning("store time %.6f s has no truth frame (nearest %.6f s); using the nearest", t, truth.time[j])
    return j


def truth_rows(session_path, store_path, truth_path, *, config: RunConfig | None = None,
               plain: bool = False) -> dict[str, np.ndarray]:
    """Refractivity reconstructed from the truth's deflections with the run's hull and parameters.

    Parameters
    ----------
    session_path, store_path, truth_path : path
        A synthetic session, its pipeline result store (for the hulls, times and the cached
        geometry) and its ``truth.zarr``.
    config : RunConfig, optional
        The run's configuration (default ``RunConfig()``, bound to the session's medium).
    plain : bool
        Also integrate the ``approximate`` gradients with the anisotropic tensor active
        (:data:`ANISO`).

    Returns
    -------
    dict
        ``"exact"``, ``"approximate"`` (and ``"approximate_aniso"``): ndarray (F, nz, ny, nx)
        ``n - 1`` on the session grid at the store's frames; ``"time"``: ndarray (F,).
    """
    session = load_session(session_path)
    cfg = bind_medium(config or RunConfig(), session.medium.n_ambient)
    store = ResultStore.open(store_path, mode="r")
    truth = sio.read_truth(truth_path)
    times = np.asarray(store.read("time"), dtype=np.float64)
    # the truth's deflections are on the flow grid the session was rendered with (which the
    # run's flow.auto_factor may have refined): the reconstruction from them uses that grid
    W, H = session.cameras[0].image_size
    cols = int(truth.group["deflection"].shape[-2])
    fg = FlowGrid((W, H), max(1, W // cols))
    if fg.shape[1] != cols:
        raise ValueError(f"{truth_path}: deflections {cols} cells wide fit no flow grid of {W} px")
    b = tomography.ray_binning(session.cameras, session.grid, fg, cfg.tomography.ray_binning)
    geom = _geometry(session, store_path, tomography.ray_grid(fg, b), cfg)
    grid = session.grid
    r_amb = session.medium.refractivity_ambient
    n_amb = session.medium.n_ambient
    variants = ["exact", "approximate"]
    out = {v: np.empty((len(times),) + tuple(grid.shape)) for v in variants}
    if plain:
        out["approximate_aniso"] = np.empty((len(times),) + tuple(grid.shape))
    plain_params = dataclasses.replace(cfg.poisson, **ANISO)
    tomo = _run_tomo_params(store, cfg)
    prev: dict[str, np.ndarray | None] = {v: None for v in variants}
    block = max(cfg.warm_start_block, 1)
    for k, t in enumerate(times):
        j = _truth_frame(truth, float(t))
        hull = np.asarray(store.read("hull", (k,)), dtype=bool)
        d_in = np.asarray(truth.group["d_in"][:, j], dtype=np.float64)
        d_out = np.asarray(truth.group["d_out"][:, j], dtype=np.float64)
        data = {"exact": tomography.bin_cells(n_amb * (d_out - d_in), b),
                "approximate": tomography.bin_cells(np.asarray(truth.group["deflection"][:, j], dtype=np.float64), b)}
        for v in variants:
            x0 = prev[v] if k % block != 0 else None
            grad, info = tomography.solve_gradient(geom, data[v], hull, params=tomo, x0=x0)
            prev[v] = grad
            out[v][k], _ = poisson.integrate(grad, hull, grid, r_ambient=r_amb, params=cfg.poisson)
            if v == "approximate" and plain:
                out["approximate_aniso"][k], _ = poisson.integrate(grad, hull, grid, r_ambient=r_amb,
                                                                   params=plain_params)
            log.info("frame %d %s: %d tomography iterations (%s)", k, v, info.iterations, info.stop_reason)
    out["time"] = times
    return out


def bound_gradient(volume: np.ndarray, src: Grid, dst: Grid, *, scheme: str = "fine_block") -> np.ndarray:
    """The "unknown"-discretisation gradient of sec. 6.

    Parameters
    ----------
    volume : ndarray, shape src.shape
        ``n - 1`` on the fine truth grid.
    src, dst : Grid
        Fine truth grid and reconstruction grid.
    scheme : {"fine_block", "coarse_central"}
        ``"fine_block"``: central differences on the fine grid, then block means over each
        ``dst`` voxel when ``dst`` voxels are whole blocks of ``src`` voxels (same corner,
        integer ratio), else trilinear resampling. ``"coarse_central"``: the truth
        trilinearly sampled at the ``dst`` voxel centres, then central differences there.

    Returns
    -------
    ndarray, shape dst.shape + (3,)
        ``grad n`` in 1/m, component 0 = x.
    """
    v = np.asarray(volume, dtype=np.float64)
    if scheme == "coarse_central":
        gz, gy, gx = np.gradient(metrics.resample_space(v, src, dst), dst.voxel_size)
        return np.stack([gx, gy, gz], axis=-1)
    if scheme != "fine_block":
        raise ValueError(f"scheme must be 'fine_block' or 'coarse_central', not {scheme!r}")
    gz, gy, gx = np.gradient(v, src.voxel_size)
    ratio = dst.voxel_size / src.voxel_size
    r = int(round(ratio))
    aligned = (abs(ratio - r) < 1e-6 and np.allclose(src.vmin, dst.vmin, atol=1e-6 * src.voxel_size)
               and tuple(s // r for s in src.shape) == tuple(dst.shape) and all(s % r == 0 for s in src.shape))
    comps = []
    for g in (gx, gy, gz):
        if aligned:
            nz, ny, nx = dst.shape
            comps.append(g.reshape(nz, r, ny, r, nx, r).mean(axis=(1, 3, 5)))
        else:
            comps.append(metrics.resample_space(g, src, dst))
    return np.stack(comps, axis=-1)


def poisson_bound(truth_path, grid: Grid, times: np.ndarray, *, r_ambient: float,
                  params: poisson.PoissonParams = poisson.PoissonParams(), dilation: int = 2,
                  support_threshold: float = 1e-3, hulls: np.ndarray | None = None,
                  scheme: str = "fine_block") -> np.ndarray:
    """Sec. 6 Poisson-only bound: integrate the truth's own gradient at ``times``.

    Parameters
    ----------
    truth_path : path
    grid : Grid
        Reconstruction grid.
    times : ndarray (F,)
        The frames' instants (truth frames at these times are used).
    r_ambient : float
        ``n_ambient - 1``.
    params : PoissonParams
    dilation : int
        Dilation (voxels, 26-connected) of the truth's support when ``hulls`` is None.
    support_threshold : float
        Fraction of the frame's range above which ``|r - r_ambient|`` is support.
    hulls : ndarray (F, nz, ny, nx) bool, optional
        Use these hulls (e.g. a pipeline run's) instead of the dilated support.
    scheme : str
        Gradient discretisation, see :func:`bound_gradient`.

    Returns
    -------
    ndarray (F, nz, ny, nx)
    """
    truth = sio.read_truth(truth_path)
    tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
    out = np.empty((len(times),) + tuple(grid.shape))
    for k, t in enumerate(times):
        j = _truth_frame(truth, float(t))
        fine = np.asarray(truth.refractivity[j], dtype=np.float64)
        g = bound_gradient(fine, tgrid, grid, scheme=scheme)
        if hulls is None:
            coarse = metrics.resample_space(fine, tgrid, grid)
            dev = np.abs(coarse - r_ambient)
            support = dev > support_threshold * float(coarse.max() - coarse.min())
            hull = ndi.binary_dilation(support, structure=np.ones((3, 3, 3), bool), iterations=dilation) \
                if dilation > 0 else support
        else:
            hull = np.asarray(hulls[k], dtype=bool)
        out[k], _ = poisson.integrate(g, hull, grid, r_ambient=r_ambient, params=params)
    return out


def bench_rig(work_dir, rig: tuple[str, int], config: Table1Config, *, client=None) -> dict:
    """Render, run and score one rig; returns ``{"ring", "cameras", "rows", "seconds", ...}``.

    ``rows`` maps ``exact`` / ``approximate`` / ``optical_flow`` (and ``approximate_aniso``
    for :attr:`Table1Config.plain_rig`) to ``{"rms", "psnr", "frames"}``.
    """
    from schlieren.workers.run import run_session
    from schlieren.workers.synth import synthesize

    ring, n = rig
    d = Path(work_dir) / _rig_name(rig)
    bench_io.remove_tree(d)
    res = {"ring": ring, "cameras": n, "rows": {}, "seconds": {}, "failures": {}}
    t0 = time.perf_counter()
    syn = synthesize(d, cameras=n, ring=ring, phantom="plume", frames=config.frames, size=tuple(config.size),
                     flow_factor=config.flow_factor, seed=config.seed, noise=config.noise,
                     recon_voxel=config.recon_voxel, supersample=config.supersample)
    t1 = time.perf_counter()
    res["seconds"]["synth"] = t1 - t0
    store_path = d / "store.zarr"
    cfg = config.run_config()
    summary = run_session(syn.session, store_path, client=client, serial=client is None, config=cfg)
    t2 = time.perf_counter()
    res["seconds"]["pipeline"] = t2 - t1
    res["executor"] = summary.executor
    if not summary.ok:
        res["failures"] = dict(summary.root_failures())
        log.error("pipeline run of %s failed: %s", _rig_name(rig), res["failures"])
        return res
    res["rows"]["optical_flow"] = _rows(evaluate(store_path, syn.truth))
    session = load_session(syn.session)
    plain = config.plain_rig is not None and tuple(config.plain_rig) == tuple(rig)
    vols = truth_rows(syn.session, store_path, syn.truth, config=cfg, plain=plain)
    for v in ("exact", "approximate", "approximate_aniso"):
        if v in vols:
            res["rows"][v] = _score(d / f"est_{v}.zarr", vols[v], vols["time"], session.grid, syn.truth, v)
    t3 = time.perf_counter()
    res["seconds"]["truth_rows"] = t3 - t2
    res["grid_shape"] = list(session.grid.shape)
    run_factor = int(ResultStore.open(store_path, mode="r").attrs["run"]["flow_factor"])  # flow.auto_factor's
    res["flow_factor"] = run_factor
    res["flow_shape"] = [int(v) for v in FlowGrid(session.cameras[0].image_size, run_factor).shape]
    res["paths"] = {"session": str(syn.session), "truth": str(syn.truth), "store": str(store_path)}
    res["hull_voxels"] = [int(np.sum(ResultStore.open(store_path, mode="r").read("hull", (k,))))
                          for k in range(len(vols["time"]))]
    return res


def run_table1(work_dir, config: Table1Config = Table1Config(), *, client=None,
               progress: Callable[[str], None] | None = None) -> dict:
    """Every rig of ``config`` plus the Poisson-only bound; returns the JSON-able results.

    Parameters
    ----------
    work_dir : path
        Sessions, stores and estimate stores are written under it (one folder per rig).
    config : Table1Config
    client : distributed.Client, optional
        Runs the pipeline on this cluster; ``None`` runs it serially.
    progress : callable, optional
        Called with a one-line message after each step.

    Returns
    -------
    dict
        ``{"config", "rigs": [bench_rig(...)...], "poisson_bound": {...}, "paper": {...},
        "seconds"}``.
    """
    say = progress or (lambda msg: log.info("%s", msg))
    t0 = time.perf_counter()
    rigs = []
    for rig in config.rigs:
        r = bench_rig(work_dir, rig, config, client=client)
        rigs.append(r)
        rows = ", ".join(f"{k} {v['psnr']:.2f} dB" for k, v in r["rows"].items())
        say(f"{_rig_name(rig)}: {rows or 'failed'} ({sum(r['seconds'].values()):.0f} s)")
    bound: dict = {}
    ok = [r for r in rigs if "paths" in r]
    if ok:
        bound = _bound_rows(work_dir, ok, config)
        say(f"Poisson-only bound: {bound['support']['psnr']:.2f} dB")
    return {"config": dataclasses.asdict(config), "rigs": rigs, "poisson_bound": bound,
            "paper": {"table1": {f"{k[0]}:{k[1]}": v for k, v in PAPER_TABLE1.items()},
                      "poisson_bound": PAPER_POISSON_BOUND},
            "seconds": time.perf_counter() - t0}


def _bound_rows(work_dir, ok: list[dict], config: Table1Config) -> dict:
    """The Poisson-only bound's rows (sec. 6) on the truth of the :attr:`Table1Config.hull_rig`
    run (else the first rig that ran): inside the dilated truth support with two gradient
    discretisations, and inside that run's pipeline hull."""
    bound: dict = {}
    tb = time.perf_counter()
    ref = next((r for r in ok if config.hull_rig and (r["ring"], r["cameras"]) == tuple(config.hull_rig)),
               ok[0])
    session = load_session(ref["paths"]["session"])
    cfg = bind_medium(RunConfig(), session.medium.n_ambient)
    store = ResultStore.open(ref["paths"]["store"], mode="r")
    times = np.asarray(store.read("time"), dtype=np.float64)
    r_amb = session.medium.refractivity_ambient
    wd = Path(work_dir) / "poisson_bound"
    vols = poisson_bound(ref["paths"]["truth"], session.grid, times, r_ambient=r_amb, params=cfg.poisson,
                         dilation=config.bound_dilation, support_threshold=config.support_threshold)
    bound["support"] = _score(wd / "est_support.zarr", vols, times, session.grid, ref["paths"]["truth"],
                              "poisson_bound_support")
    support_text = f"truth support (abs(r - r_amb) > {config.support_threshold:g} x range) dilated by " \
                   f"{config.bound_dilation} voxels"
    bound["support"]["hull"] = support_text
    bound["support"]["scheme"] = FINE_BLOCK_TEXT
    vols = poisson_bound(ref["paths"]["truth"], session.grid, times, r_ambient=r_amb, params=cfg.poisson,
                         dilation=config.bound_dilation, support_threshold=config.support_threshold,
                         scheme="coarse_central")
    bound["coarse_central"] = _score(wd / "est_coarse.zarr", vols, times, session.grid,
                                     ref["paths"]["truth"], "poisson_bound_coarse_central")
    bound["coarse_central"]["hull"] = support_text
    bound["coarse_central"]["scheme"] = COARSE_CENTRAL_TEXT
    if config.hull_rig and (ref["ring"], ref["cameras"]) == tuple(config.hull_rig):
        hulls = np.stack([store.read("hull", (k,)) for k in range(len(times))])
        vols = poisson_bound(ref["paths"]["truth"], session.grid, times, r_ambient=r_amb,
                             params=cfg.poisson, hulls=hulls)
        bound["pipeline_hull"] = _score(wd / "est_hull.zarr", vols, times, session.grid,
                                        ref["paths"]["truth"], "poisson_bound_hull")
        bound["pipeline_hull"]["hull"] = f"pipeline hull of the {_rig_name(ref_rig(ref))} run"
        bound["pipeline_hull"]["scheme"] = FINE_BLOCK_TEXT
    bound["seconds"] = time.perf_counter() - tb
    return bound


def ref_rig(r: dict) -> tuple[str, int]:
    return r["ring"], r["cameras"]


def rig_failures(result: dict) -> list[str]:
    """Names of rigs whose pipeline run failed."""
    return [_rig_name(ref_rig(r)) for r in result["rigs"] if r.get("failures")]
