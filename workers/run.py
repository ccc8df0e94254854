"""Process one capture session into a result store: validate, template, plan, execute.

Order of events (SPEC sections 1-2):

1. the session is loaded and validated completely (bad input stops here, nothing is
   scheduled and no store is touched);
2. the preflight checks memory (the model measured by benchmarks/memory.py, times the
   workers) and disk space;
3. the store's lease is taken (one writer per store, ``storage/lease.py``), then the store
   is created with every array up front, or reopened when it was made for the same
   session and parameters (a rerun resumes; a different run is refused, never
   overwritten);
4. the markers are verified (``workers/verify.py``): every chunk a set marker covers must
   have a file (``verify=True`` also reads every chunk's checksum); damaged tasks and
   everything downstream of them are unmarked;
5. the stage table is compiled into tasks, minus those whose completion marker is set;
6. the tasks run in a plain loop or as Dask futures; failures (I/O errors such as a full
   disk included) are collected per task and summarised, every completed chunk stays.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Callable

from schlieren.pipeline.capture import row_knots
from schlieren.pipeline.geometry import FlowGrid
from schlieren.pipeline.overrides import bind_run, records, session_overrides
from schlieren.pipeline.stages import STAGES, RunConfig, check_config, config_to_dict, run_stages
from schlieren.storage import location
from schlieren.storage.layout import result_layout, with_uncertainty
from schlieren.storage.session import Session, load_session
from schlieren.storage.errors import StoreError
from schlieren.storage.store import ResultStore, remove_store
from schlieren.workers.monitoring import log_receipt
from schlieren.workers.overrides import DERIVED_ATTR, RunOverrides
from schlieren.workers.plan import Extents, Plan, make_plan

log = logging.getLogger(__name__)

__all__ = ["run_session", "RunSummary", "prepare_store"]

RAW_MARGIN = 2  # raw frames either side of the output range used by rolling-shutter resampling
#: Image pixels per task the deflection aims for by default (its cost grows with the
#: image): 8 frames per task at 480x360, 4 at 960x720, 2 at 1440x1080, 1 from 2560x1440
#: up, so that a task's work outweighs what Dask spends on it. A task also decodes the
#: frame before its first (the frozen-frame test), so two frames per task decode three
#: frames instead of four (docs/tuning.md, "Scheduling").
PIXELS_PER_TASK = 3.1e6
MAX_FRAMES_PER_TASK = 8


#: Flow-grid cells per task the batched stages on the flow grid (resampling, potential,
#: mask) aim for: 4 frames per task at 1440x1080 with
#: flow factor 3. Consecutive frames in one task also share work: an output instant's
#: resampling reuses the motion of the frame pair it shares with the previous instant,
#: and a mask the per-frame evidence its neighbours' masks computed.
FLOW_CELLS_PER_TASK = 7e5


def default_frames_per_task(image_size: tuple[int, int], flow_factor: int | None = None) -> int | dict:
    """Frames of one camera per task for images of ``(width, height)``: about
    :data:`PIXELS_PER_TASK` pixels, between 1 and :data:`MAX_FRAMES_PER_TASK`.

    With ``flow_factor`` (the flow grid's downsampling) a mapping ``{stage: frames}``:
    the stages on the flow grid (``Stage.grid == "flow"``) aim for
    :data:`FLOW_CELLS_PER_TASK` flow cells instead.
    """
    w, h = image_size

    def frames(units: float, per_task: float) -> int:
        return int(min(MAX_FRAMES_PER_TASK, max(1, round(per_task / max(1.0, units)))))

    image = frames(w * h, PIXELS_PER_TASK)
    if flow_factor is None:
        return image
    fh, fw = FlowGrid((w, h), flow_factor).shape
    cells = fh * fw
    return {s.name: frames(cells, FLOW_CELLS_PER_TASK) if s.grid == "flow" else image
            for s in STAGES if s.batch}


@dataclass
class RunSummary:
    """What a run did. Counts are of *steps*: one stage at one index (a camera and frame, a
    frame, or the whole run), the unit a completion marker records; a task computes one
    step or several consecutive frames of one camera (``frames_per_task``).

    ``steps``: steps this run set out to compute, in ``tasks`` tasks; ``skipped``: steps
    already complete in the store (not run again)."""

    store: str
    executor: str
    tasks: int = 0
    skipped: int = 0
    steps: int = 0
    task_steps: dict[str, int] = field(default_factory=dict)  # task key -> its steps
    failures: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    stage_cpu_seconds: dict[str, float] = field(default_factory=dict)
    receipts: list[dict] = field(default_factory=list)
    dashboard: str | None = None
    warnings: list[str] = field(default_factory=list)
    integrity: object = None  # the VerifyReport of the markers checked before planning
    bad_frames: list = field(default_factory=list)  # (camera, capture frame, [reasons]) excluded

    @property
    def ok(self) -> bool:
        return not self.failures

    @property
    def steps_computed(self) -> int:
        """Steps this run computed (those of its failed and not-run tasks left out)."""
        return self.steps - sum(self.task_steps.get(k, 1) for k in self.failures if k in self.task_steps)

    def root_failures(self) -> dict[str, str]:
        return {k: v for k, v in self.failures.items() if not v.startswith("not run:")}


def software_version() -> str:
    try:
        return version("schlieren")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0+unknown"


def _fingerprint(session: Session, cfg: RunConfig, frames: tuple[int, int]) -> str:
    blob = json.dumps({"manifest": session.manifest, "params": config_to_dict(cfg),
                       "frames": list(frames)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()


def session_location(session: Session) -> str:
    """The manifest's absolute path, or its URL for a session on object storage."""
    m = str(session.manifest_path)
    return m if location.is_url(m) else str(Path(m).resolve())


def run_layout(session: Session, cfg: RunConfig) -> tuple[list, Extents]:
    """The store's arrays and the plan's extents for ``session`` and ``cfg``."""
    a, b = session.frames
    n_frames = b - a
    raw_first = max(0, a - RAW_MARGIN)
    raw_last = min(session.n_frames_available, b + RAW_MARGIN)
    fg = FlowGrid(session.cameras[0].image_size, cfg.flow_factor)
    ext = Extents(camera=len(session.cameras), frame=n_frames, raw_frame=raw_last - raw_first,
                  raw_offset=a - raw_first, warm_start_block=cfg.warm_start_block,
                  spacetime_window=cfg.spacetime.window)
    layout = result_layout(camera_names=[c.name for c in session.cameras], n_frames=n_frames,
                           flow_shape=fg.shape, grid=session.grid, first_frame=a,
                           n_raw=ext.raw_frame, raw_first=raw_first,
                           n_summary=cfg.masks.n_quantiles + 1, flow_factor=fg.factor,
                           image_shape=(session.cameras[0].height, session.cameras[0].width),
                           row_knots=row_knots(session.cameras[0].height, cfg.capture.banding_rows),
                           per_frame_gradient=cfg.spacetime.window > 0,
                           reference_topup=cfg.capture.reference_topup > 0)
    if cfg.uncertainty.enabled:  # the optional stage's standard errors beside the values
        layout = with_uncertainty(layout)
    return layout, ext


def prepare_store(session: Session, out_path: str | Path, cfg: RunConfig,
                  derived: dict | None = None) -> tuple[ResultStore, Extents, str]:
    """Create (or reopen for resume) the result store for ``session`` and return the extents;
    ``derived``: the run's overrides known so far (root attribute ``derived``)."""
    a, b = session.frames
    n_frames = b - a
    raw_first = max(0, a - RAW_MARGIN)
    fg = FlowGrid(session.cameras[0].image_size, cfg.flow_factor)
    layout, ext = run_layout(session, cfg)
    fp = _fingerprint(session, cfg, (a, b))
    attrs = {
        "session": session.manifest,
        "session_path": session_location(session),
        "session_name": session.name,
        "params": config_to_dict(cfg),
        "version": software_version(),
        "fingerprint": fp,
        "run": {"frames": [a, b], "n_frames": n_frames, "raw_first": raw_first,
                "n_raw": ext.raw_frame, "flow_factor": cfg.flow_factor,
                "flow_shape": list(fg.shape),
                # each video's timestamp scan (frames it dropped): the workers do not decode it again
                "video_slots": {name: [int(n), [int(k) for k in gone]]
                                for name, (n, gone) in session.video_slots.items()}},
        "stage_times": {},
        DERIVED_ATTR: dict(derived or {}),
    }
    markers = {st.name: st.over for st in run_stages(cfg)}
    try:
        store = ResultStore.create(out_path, layout, attrs=attrs, markers=markers,
                                   producers=producers(cfg, [s.name for s in layout]))
    except OSError as exc:  # a full disk or a read-only folder while writing the template
        raise StoreError(f"cannot write the store ({exc.strerror or exc}); nothing computed is lost, "
                         "rerun when fixed", file=str(out_path)) from None
    return store, ext, fp[:10]


def producers(cfg: RunConfig, names) -> dict[str, str]:
    """Array -> the stage whose completion marker covers its chunks (the task writing them)."""
    out = {a: st.name for st in run_stages(cfg) for a in st.outputs if a in names}
    if cfg.spacetime.window > 0 and "gradient_frame" in names:
        out["gradient_frame"] = "tomography"  # the per-frame solve, which the spacetime stage averages
    if cfg.reconstruction == "direct" and "refractivity" in out:
        out["refractivity"] = "tomography"  # solved directly by the tomography task
    return out


def excluded_frames(store: ResultStore, receipts: list[dict] | None = None) -> list[tuple[str, int, list[str]]]:
    """``(camera, capture frame, reasons)`` of every frame flagged dark, saturated, frozen or
    dropped by the camera (not the margin frames no output instant needed).

    ``receipts``: the run's task receipts. When this run's deflection tasks covered every raw
    frame of every camera, their receipts (``excluded``: the same flag names the stored
    ``frame_quality`` holds) answer without reading the store; otherwise (a resumed run,
    failed tasks) the flags are read from ``frame_quality``: one small chunk per camera-frame,
    which from an object store is one request each.
    """
    import numpy as np

    from schlieren.pipeline.frame_quality import PROBLEMS, flag_names
    from schlieren.storage.errors import ChunkError

    if "frame_quality" not in store:
        return []
    if receipts:
        C, n_raw = (int(v) for v in store.array("frame_quality").shape[:2])
        known = {}
        for r in receipts:
            if r.get("stage") == "deflection" and not r.get("skipped") and "camera" in r:
                c, j = (int(v) for v in r["index"][:2])
                known[(c, j)] = (r["camera"], int(r["frame"]), list(r.get("excluded") or []))
        if len(known) == C * n_raw:
            return [v for _, v in sorted(known.items()) if v[2]]
    try:
        flags = np.asarray(store.array("frame_quality")[..., 3])
    except ChunkError:
        return []  # a damaged chunk is reported by the task that reads it
    names = [str(n) for n in np.asarray(store.array("camera")[...])]
    raw_first = int(store.attrs["run"]["raw_first"])
    problems = np.nan_to_num(flags).astype(np.int64) & PROBLEMS  # not UNUSED margin frames
    return [(names[int(c)], raw_first + int(j), flag_names(problems[c, j]))
            for c, j in zip(*np.nonzero(problems))]


def flash_spans(store: ResultStore) -> dict[str, tuple[int, int]]:
    """Camera -> first and last frame the strobe flash lit (``(-1, -1)``: none; empty when
    the sync has not run)."""
    import numpy as np

    from schlieren.storage.errors import ChunkError

    try:
        spans = np.asarray(store.array("flash_frames")[...])
        names = [str(n) for n in np.asarray(store.array("camera")[...])]
    except (ChunkError, StoreError):
        return {}
    return {n: (int(lo), int(hi)) for n, (lo, hi) in zip(names, spans) if np.isfinite([lo, hi]).all()}


def store_lease(out_path, purpose: str = "run"):
    """The lease of the store (:func:`schlieren.storage.lease.lease_for`): a folder's lease
    file or an S3 store's lease object; a no-op context for other stores."""
    from schlieren.storage.lease import lease_for

    return lease_for(out_path, purpose)


def _done_predicate(done_sets: dict, ext: Extents) -> Callable[[str, object], bool]:
    """Marker lookup for the plan (the markers verified before planning); the tomography
    geometry counts as done while no tomography task is left (``schlieren clean`` removes
    it and clears its marker)."""
    def done(stage: str, index) -> bool:
        if tuple(index) in done_sets.get(stage, ()):
            return True
        # (and no uncertainty task, which reads the geometry too, when the run has that stage)
        return stage == "geometry" and all(len(done_sets.get(s, ())) == ext.frame for s in ("tomography", "uncertainty")
                                           if s == "tomography" or s in done_sets)
    return done


def run_session(session_path: str | Path, out_path: str | Path, *, client=None,
                frames: tuple[int, int] | None = None, serial: bool = False,
                config: RunConfig | None = None, report: str | None = None,
                on_receipt: Callable[[dict], None] | None = None,
                on_failure: Callable[[str, str], None] | None = None,
                on_plan: Callable[[Plan], None] | None = None,
                progress: bool = False, frames_per_task: int | None = None,
                overwrite: bool = False, verify: bool = False, keep=None) -> RunSummary:
    """Validate ``session_path``, then compute every missing chunk of ``out_path``.

    Parameters
    ----------
    session_path : path or Session
        The session folder or its ``session.yaml`` (or a session already loaded, with
        ``frames`` applied).
    out_path : path
        The result store (Zarr v3 folder).
    client : distributed.Client, optional
        Run on this cluster; ``None`` with ``serial=True`` runs the reference loop.
    frames : (int, int), optional
        Half-open frame range overriding the manifest's.
    config : RunConfig, optional
    report : str, optional
        Path of a Dask performance report (HTML), with a client.
    frames_per_task : int, optional
        Consecutive frames of one camera per task in the cheap 2D stages (default
        :func:`default_frames_per_task` of the image size and flow grid; 1 = one task per
        camera and frame). Results, markers and resume do not depend on it.
    overwrite : bool
        Replace a store of another configuration at ``out_path`` (only a result store:
        anything else is still refused). A store of this same run is resumed either way.
    verify : bool
        Read every chunk of the existing store and check its checksum before trusting the
        markers (otherwise only a listing checks that the marked chunks exist). Damaged
        chunks are recomputed with everything downstream of them.
    keep : str or list of str, optional
        The intermediates the store keeps (:func:`~schlieren.workers.retention.arrays_to_drop`):
        ``"all"`` (default), ``"results"`` (``flow_raw``, ``flow`` and ``potential`` are
        dropped once the stages reading them are done) or the names of those to keep.
        Results do not depend on it; it is not part of the run's fingerprint.
    """
    from schlieren.workers.preflight import WorkerSlots, preflight, workers_of_client
    from schlieren.workers.tasks import adopt_session

    from schlieren.workers.retention import arrays_to_drop

    config = check_config(config or RunConfig())  # a bad value stops here, before the store exists
    try:
        arrays_to_drop(keep)
    except ValueError as exc:
        raise StoreError(str(exc), field="keep") from None
    session = session_path if isinstance(session_path, Session) else load_session(session_path, frames=frames)
    adopt_session(session_location(session), session)  # this process's task contexts reuse it
    cfg, derived = bind_run(config, session.cameras, session.grid, session.medium.n_ambient)
    given = (session.manifest.get("volume") or {}).get("voxel_size") is not None
    derived = session_overrides(session.cameras, session.grid, voxel_size_given=given) + derived
    overrides = RunOverrides(cfg, derived, session.frames[1] - session.frames[0], len(session.cameras))
    overrides.start()
    # memory and disk, with the measured model, before anything is written
    preflight(session, cfg, run_layout(session, cfg)[0], out_path,
              workers=[WorkerSlots()] if (serial or client is None) else workers_of_client(client))
    with store_lease(out_path):
        return _run_leased(session, out_path, cfg, overrides, client=client, serial=serial, report=report,
                           on_receipt=on_receipt, on_failure=on_failure, on_plan=on_plan,
                           frames_per_task=frames_per_task, overwrite=overwrite, verify=verify, keep=keep)


def _run_leased(session, out_path, cfg, overrides, *, client, serial, report, on_receipt, on_failure, on_plan,
                frames_per_task, overwrite, verify, keep) -> RunSummary:
    store, ext, token = _open_store(session, out_path, cfg, overwrite=overwrite,
                                    derived=records(overrides.overrides))
    if frames_per_task is None:
        frames_per_task = default_frames_per_task(session.cameras[0].image_size, cfg.flow_factor)
    check = _verify(store, out_path, ext, full=verify)
    dropper = _retention(store, ext, check, keep)
    if not isinstance(frames_per_task, dict):
        frames_per_task = int(frames_per_task)
    plan = make_plan(ext, token, done=_done_predicate(check.done, ext), frames_per_task=frames_per_task,
                     stages=run_stages(cfg))
    if on_plan:
        on_plan(plan)
    summary = RunSummary(store=str(out_path), executor="serial" if (serial or client is None) else "dask",
                         tasks=len(plan.tasks), skipped=plan.skipped, integrity=check,
                         steps=sum(len(t.indices) for t in plan.tasks),
                         task_steps={t.key: len(t.indices) for t in plan.tasks})
    t0 = time.time()
    if dropper is not None:
        dropper.start()
        on_receipt = _both(dropper.receipt, on_receipt)
    clock = _StageClock(summary.executor, _both(overrides.receipt, on_receipt))
    receipts, failures = _execute(summary.executor, client, str(out_path), plan, report=report,
                                  on_receipt=clock, on_failure=on_failure)
    summary.receipts = receipts
    summary.failures = failures
    summary.seconds = time.time() - t0
    summary.stage_seconds = dict(clock.busy)
    summary.stage_cpu_seconds = dict(clock.cpu)
    summary.bad_frames = excluded_frames(store, receipts)
    _record_run_attrs(store, out_path, plan, summary, clock, overrides)
    from schlieren.workers.diagnostics import diagnose

    summary.warnings = diagnose(receipts, n_voxels=math.prod(session.grid.shape), flash_frames=flash_spans(store),
                                motion_warning=cfg.capture.motion_warning)
    for w in summary.warnings:
        log.warning("%s", w)
    if dropper is not None and summary.ok:  # complete: the arrays left without chunks go
        removed = dropper.finish()
        store.set_retention(dropper.keep, dropper.drop)
        log.info("retention %s: %d chunks dropped this run%s", dropper.keep, dropper.dropped,
                 f"; {', '.join(removed)} removed" if removed else "")
    return summary


def _retention(store: ResultStore, ext: Extents, check, keep):
    """The run's :class:`~schlieren.workers.retention.Dropper` (None when nothing is or was
    dropped: today's store, no attribute written), after clearing the markers of the
    producers whose dropped chunks this run needs again."""
    from schlieren.workers.retention import Dropper, arrays_to_drop, keep_text, to_regenerate

    drop, before = arrays_to_drop(keep), store.dropped_arrays
    if not drop and not before:
        return None
    regen = to_regenerate(store, ext, check.done, drop, before)
    for stage, idx in sorted(regen):
        store.unmark(stage, idx)
        check.done.get(stage, set()).discard(idx)
    if regen:
        log.info("recomputing %d dropped intermediate chunk(s) that this run needs again", len(regen))
    store.set_retention(keep_text(keep), drop | before)  # until the run completes: either may be missing
    dropper = Dropper(store, ext, drop, _done_predicate(check.done, ext))
    dropper.keep = keep_text(keep)
    return dropper


def _open_store(session, out_path, cfg, *, overwrite: bool, derived: dict) -> tuple[ResultStore, Extents, str]:
    """:func:`prepare_store`; with ``overwrite`` a store of another configuration is replaced."""
    try:
        return prepare_store(session, out_path, cfg, derived=derived)
    except StoreError as exc:
        if not (overwrite and exc.field == "fingerprint"):
            raise
        log.warning("replacing the store %s of another configuration (--overwrite)", out_path)
        remove_store(out_path)
        return prepare_store(session, out_path, cfg, derived=derived)


def _both(first: Callable[[dict], None], second: Callable[[dict], None] | None) -> Callable[[dict], None]:
    """A receipt callback calling ``first``, then ``second`` (if any)."""
    def call(r: dict) -> None:
        first(r)
        if second is not None:
            second(r)
    return call


def _verify(store: ResultStore, out_path, ext: Extents, *, full: bool):
    """The markers checked (and damaged ones cleared) before planning: the ``VerifyReport``."""
    from schlieren.workers.verify import verify_store

    try:
        return verify_store(store, full=full, repair=True, ext=ext)
    except OSError as exc:
        raise StoreError(f"cannot check the store ({exc.strerror or exc})", file=str(out_path)) from None


class _StageClock:
    """The receipt callback of a run: per stage, the first start, the last completion and the
    summed task seconds and CPU seconds; logs the Dask workers' receipts and passes every
    receipt on to ``on_receipt``."""

    def __init__(self, executor: str, on_receipt: Callable[[dict], None] | None):
        self.executor = executor
        self.on_receipt = on_receipt
        self.first: dict[str, float] = {}
        self.last: dict[str, float] = {}
        self.busy: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def __call__(self, r: dict) -> None:
        if self.executor == "dask":  # the serial loop's tasks log their own, in this process
            log_receipt(r, level=logging.DEBUG if r.get("skipped") else logging.INFO)
        now = time.time()
        s = r["stage"]
        self.first.setdefault(s, now - r.get("seconds", 0.0))
        self.last[s] = now
        self.busy[s] = self.busy.get(s, 0.0) + float(r.get("seconds", 0.0))
        self.cpu[s] = self.cpu.get(s, 0.0) + float(r.get("cpu_seconds", 0.0))
        if self.on_receipt:
            self.on_receipt(r)


def _execute(executor: str, client, store_path: str, plan: Plan, *, report, on_receipt, on_failure):
    """Run ``plan`` in the serial loop or on the Dask cluster: ``(receipts, failures)``."""
    if executor == "serial":
        from schlieren.workers.serial import run_serial

        return run_serial(store_path, plan, on_receipt=on_receipt, on_failure=on_failure)
    from schlieren.workers.graph import run_graph

    if report:
        from distributed import performance_report

        # inline: BokehJS embedded, so the report opens offline (the default loads it from a CDN)
        with performance_report(filename=str(report), mode="inline"):
            return run_graph(client, store_path, plan, on_receipt=on_receipt, on_failure=on_failure)
    return run_graph(client, store_path, plan, on_receipt=on_receipt, on_failure=on_failure)


def _record_run_attrs(store: ResultStore, out_path, plan: Plan, summary: RunSummary, clock: _StageClock,
                      overrides: RunOverrides) -> None:
    """Store each stage's first start, last completion and task seconds of this run in the
    store's ``stage_times`` (stages with a failed task keep their previous entry), and the
    run's derived overrides in ``derived`` (:class:`~schlieren.workers.overrides.RunOverrides`)."""
    times = dict(store.attrs.get("stage_times") or {})
    done_stages = {t.stage for t in plan.tasks} - {k.split("-")[0] for k in summary.failures}
    for s in done_stages:
        if s in clock.first:
            times[s] = {"started": clock.first[s], "completed": clock.last[s],
                        "task_seconds": clock.busy.get(s, 0.0), "executor": summary.executor}
    try:
        store.update_attrs({"stage_times": times, DERIVED_ATTR: overrides.attrs(store)})
    except OSError as exc:  # only the timing attributes are lost; every chunk and marker stays
        from schlieren.workers.tasks.runner import failure_text

        summary.failures["store-attributes"] = failure_text(f"recording stage times in {out_path}", exc)
