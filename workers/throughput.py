"""Whole-session throughput: a small model of a run's wall time on N workers, fitted to receipts.

Used by ``benchmarks/session.py``: it fits the per-task seconds of each stage to the
receipts of one measured run (``schlieren run --log`` JSON lines, or
``RunSummary.receipts``) and predicts the wall time of a capture of C cameras x F frames
on N single-threaded workers (one core each), naming the term that limits it.

The run's graph (``pipeline/stages.py``) has one global barrier, the single ``threshold``
task that pools every camera-frame's potential summary; everything else is wide and
short, except the tomography solves, which are chained inside each warm-start block of
B frames (frame k starts from frame k-1's solution). So the model splits the run in three
phases:

* **A, before the barrier**: sync, clock, capture, deflection, resample,
  potential, and the once-per-session ``geometry`` task (nothing in A waits for it;
  tomography does). Work ``W_A`` = sum over those stages of tasks x seconds per task;
  longest chain ``L_A`` = max(sync + clock, capture + deflection) + resample + potential.
* **B, the barrier**: the threshold task alone, ``T_B`` = C x F summaries x its fitted
  seconds per summary (it reads every summary: its cost grows with the capture).
* **C, after the barrier**: mask, hull, tomography, integrate: ``W_C``, and the chain of
  one warm-start block ``L_C`` = mask + hull + one cold solve + (B - 1) warm solves +
  integrate.

A greedy scheduler (any ready task starts on any idle worker) keeps every worker busy
except while a critical chain is the only work left, so each phase takes at least
``max(W/N, L)`` and at most ``W/N + (1 - 1/N) L`` (Graham's bound for list scheduling).
The prediction is the sum of the phases' upper bounds, plus:

* ``G``, the geometry wait: the geometry task starts at once (highest priority) but is
  one task; when it outlasts phases A and B, the first solves wait for it;
* ``O``, per-task overhead: ``o`` seconds of worker idle time per task between two
  tasks when the next was already ready (measured from the 2-worker run's task stream,
  :func:`ready_gaps`), spread over N workers, plus ``o`` for each task along the chain;
* the scheduler floor ``S`` = tasks x ``s``: one scheduler process handles every task
  (``s`` = CPU seconds of the scheduler + client process per task in the measured run);
  the wall time is at least ``S`` whatever N is;
* ``P``, planning: the client compiles the plan before the first task (given, measured
  apart; it does not shrink with N).

``T(N) = P + max(A + T_B + C + G + O, S)``; the lower bound replaces each phase's upper
bound by ``max(W/N, L)`` (without the geometry in phase A, which may also run after the
barrier) and is at least the total work / N, the geometry task
followed by one warm-start block's solves and integration, and ``S``. The limiting term is the largest of the prediction's terms:
each stage's work / N, the chains, the barrier, the geometry wait, the overhead, or the
scheduler floor.

Pure arithmetic: no dask, no files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from schlieren.pipeline.stages import STAGES
from schlieren.workers.plan import batch_sizes

__all__ = ["StageCosts", "Prediction", "fit_costs", "predict", "ready_gaps", "task_counts",
           "PHASE_A", "BARRIER", "PHASE_C"]

PHASE_A = ("sync", "clock", "capture", "deflection", "resample", "potential", "geometry")
BARRIER = "threshold"
PHASE_C = ("mask", "regularisation", "hull", "tomography", "integrate")
_OVER = {s.name: s.over for s in STAGES}
_BATCH = {s.name: s.batch for s in STAGES}


@dataclass(frozen=True)
class StageCosts:
    """Seconds per task of every stage, fitted to one run's receipts.

    Attributes
    ----------
    per_index : dict
        Stage -> mean seconds per index (per camera-frame, frame, camera, or once).
    tomography_cold, tomography_warm : float
        Seconds of the first solve of a warm-start block, and of the others.
    threshold_per_summary : float
        Seconds of the threshold task per camera-frame summary it pools.
    overhead_per_task : float
        Worker idle seconds per task (dispatch latency with the next task ready).
    scheduler_per_task : float
        Scheduler (and client) CPU seconds per task.
    source : dict
        What the costs were fitted to (cameras, frames, receipts, field).
    """

    per_index: dict[str, float]
    tomography_cold: float
    tomography_warm: float
    threshold_per_summary: float
    overhead_per_task: float = 0.0
    scheduler_per_task: float = 0.0
    source: dict = field(default_factory=dict)

    def with_overheads(self, overhead_per_task: float, scheduler_per_task: float) -> "StageCosts":
        return replace(self, overhead_per_task=float(overhead_per_task),
                       scheduler_per_task=float(scheduler_per_task))


def fit_costs(receipts, *, cameras: int, frames: int, warm_start_block: int = 4,
              field_name: str = "seconds") -> StageCosts:
    """Mean seconds per index of each stage in ``receipts`` of a run of ``cameras`` x ``frames``.

    Parameters
    ----------
    receipts : iterable of dict
        Task receipts (``stage``, ``index``, ``seconds``, ``cpu_seconds``); skipped ones
        (a resumed run's) are ignored.
    field_name : {"seconds", "cpu_seconds"}
        Wall seconds inside the task, or the task thread's CPU seconds (what a quiet core
        would take).
    """
    if warm_start_block < 1:
        raise ValueError("warm_start_block must be at least 1")
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    cold: list[float] = []
    warm: list[float] = []
    for r in receipts:
        if r.get("skipped"):
            continue
        s = r["stage"]
        if s not in _OVER:  # a stage this version no longer has (receipts of an older run)
            continue
        v = float(r[field_name])
        sums[s] = sums.get(s, 0.0) + v
        counts[s] = counts.get(s, 0) + 1
        if s == "tomography":
            (cold if int(r["index"][0]) % warm_start_block == 0 else warm).append(v)
    missing = [s.name for s in STAGES if s.name not in counts]
    if missing:
        raise ValueError(f"receipts: no receipt of stage(s) {', '.join(missing)}: the model needs a complete run")
    per_index = {s: sums[s] / counts[s] for s in sums}
    t_cold = sum(cold) / len(cold)
    t_warm = sum(warm) / len(warm) if warm else t_cold
    return StageCosts(per_index=per_index, tomography_cold=t_cold, tomography_warm=t_warm,
                      threshold_per_summary=per_index[BARRIER] / (cameras * frames),
                      source={"cameras": cameras, "frames": frames, "warm_start_block": warm_start_block,
                              "receipts": sum(counts.values()), "field": field_name})


def _indices(stage: str, cameras: int, frames: int, raw_margin: int) -> int:
    sizes = {"camera": cameras, "frame": frames, "raw_frame": frames + 2 * raw_margin}
    return math.prod(sizes[d] for d in _OVER[stage])


def task_counts(cameras: int, frames: int, *, raw_margin: int = 2, frames_per_task: int | dict = 1
                ) -> dict[str, int]:
    """Tasks of each stage in a run of ``cameras`` x ``frames`` (batched stages take
    ``frames_per_task`` consecutive frames of one camera per task: one number for all, or
    ``{stage: frames}``)."""
    sizes = batch_sizes(frames_per_task)
    out = {}
    for s in STAGES:
        n = _indices(s.name, cameras, frames, raw_margin)
        fpt = sizes.get(s.name, 1)
        if s.batch and fpt > 1:
            per_camera = n // cameras
            n = cameras * math.ceil(per_camera / fpt)
        out[s.name] = n
    return out


@dataclass
class Prediction:
    """Predicted wall time of one capture on ``workers`` workers (seconds).

    ``terms`` adds up to ``seconds`` unless the scheduler floor binds (then ``seconds``
    is the floor); ``limiting`` names the largest term.
    """

    cameras: int
    frames: int
    workers: int
    seconds: float
    lower: float
    terms: dict[str, float]
    limiting: str
    tasks: int
    work: dict[str, float]

    @property
    def per_frame(self) -> float:
        return self.seconds / self.frames

    def as_dict(self) -> dict:
        return {"cameras": self.cameras, "frames": self.frames, "workers": self.workers,
                "seconds": self.seconds, "seconds_per_frame": self.per_frame, "lower_bound": self.lower,
                "limiting": self.limiting, "tasks": self.tasks, "terms": dict(self.terms),
                "work_by_stage": dict(self.work)}


def predict(costs: StageCosts, *, cameras: int, frames: int, workers: int, warm_start_block: int = 4,
            raw_margin: int = 2, frames_per_task: int | dict = 1, planning: float = 0.0) -> Prediction:
    """Wall time of ``cameras`` x ``frames`` on ``workers`` single-threaded workers (module docstring).

    ``planning`` is the client's seconds to compile the plan before any task runs
    (measured apart: it does not depend on N).
    """
    if workers < 1 or frames < 1 or cameras < 1:
        raise ValueError("cameras, frames and workers must be at least 1")
    n = float(workers)
    t = costs.per_index
    B = min(warm_start_block, frames)
    n_cold = math.ceil(frames / warm_start_block)
    work = {}
    for s in STAGES:
        if s.name == "tomography":
            work[s.name] = n_cold * costs.tomography_cold + (frames - n_cold) * costs.tomography_warm
        elif s.name == BARRIER:
            work[s.name] = cameras * frames * costs.threshold_per_summary
        else:
            work[s.name] = _indices(s.name, cameras, frames, raw_margin) * t[s.name]
    fpt = batch_sizes(frames_per_task)
    k = (lambda s: fpt[s] if _BATCH[s] else 1)  # indices per task along a chain
    # the pre-barrier chain: one camera's sync and the clock, or its defective pixels and one
    # deflection; then its resample and potential (geometry is not on it: nothing before the
    # barrier needs it)
    L_A = max(t["sync"] + t["clock"], t["capture"] + k("deflection") * t["deflection"]) \
        + k("resample") * t["resample"] + k("potential") * t["potential"]
    T_B = work[BARRIER]
    # after the masks: the frame's hull and the run's regularisation weight (one task, on
    # every chain: each solve waits for it), then the block of solves and the integration
    L_C = k("mask") * t["mask"] + max(t["hull"], t["regularisation"]) + costs.tomography_cold \
        + (B - 1) * costs.tomography_warm + t["integrate"]
    W_A = sum(work[s] for s in PHASE_A)
    W_C = sum(work[s] for s in PHASE_C)
    shrink = 1.0 - 1.0 / n
    geometry_wait = max(0.0, t["geometry"] - max(W_A / n, L_A) - T_B - k("mask") * t["mask"]
                        - max(t["hull"], t["regularisation"]))
    counts = task_counts(cameras, frames, raw_margin=raw_margin, frames_per_task=fpt)
    n_tasks = sum(counts.values())
    chain_tasks = 4 + 1 + 2 + B + 1  # sync, clock, resample, potential | threshold | mask, hull or
    # regularisation, B solves, integrate
    overhead = costs.overhead_per_task * (n_tasks / n + chain_tasks)
    terms = {f"{s}: work / N": work[s] / n for s in PHASE_A + PHASE_C}
    terms["2D chain before the barrier (x (1 - 1/N))"] = shrink * L_A
    terms["threshold barrier (one task)"] = T_B
    terms["warm-start chain: mask, hull / regularisation, block of solves, integrate (x (1 - 1/N))"] = shrink * L_C
    terms["geometry wait"] = geometry_wait
    terms["per-task overhead"] = overhead
    terms["planning (client, before any task)"] = float(planning)
    total = sum(terms.values())
    floor = costs.scheduler_per_task * n_tasks
    # the geometry need not finish before the barrier (nothing in A waits for it), so the
    # rigorous lower bound counts it only in the total work
    W_A_needed = W_A - work["geometry"]
    geometry_path = t["geometry"] + t["regularisation"] + costs.tomography_cold + (B - 1) * costs.tomography_warm \
        + t["integrate"]
    lower = planning + max(max(W_A_needed / n, L_A) + T_B + max(W_C / n, L_C), sum(work.values()) / n,
                           geometry_path, floor)
    if planning + floor > total:  # the scheduler binds: the run is planning, then the scheduler's pace
        limiting = ("scheduler throughput (tasks x scheduler seconds per task)" if floor >= planning
                    else "planning (client, before any task)")
        seconds = planning + floor
    else:
        limiting = max(terms, key=terms.get)
        seconds = total
    return Prediction(cameras=cameras, frames=frames, workers=workers, seconds=seconds, lower=lower,
                      terms=terms | {"scheduler floor (not added)": floor}, limiting=limiting,
                      tasks=n_tasks, work=work)


def ready_gaps(spans, deps: dict[str, tuple[str, ...]]) -> list[float]:
    """Idle gaps of the workers between two tasks when the second was already ready.

    Parameters
    ----------
    spans : iterable of (key, worker, start, stop)
        When each task ran and where (e.g. from Dask's task stream).
    deps : dict
        Task key -> keys it waits for.

    Returns
    -------
    list of float
        For each worker and each pair of consecutive tasks (a, b) on it where every
        dependency of b had finished by the time a stopped: ``start(b) - stop(a)``, the
        time the worker spent between tasks although work was ready (dispatch, messages,
        the scheduler's bookkeeping). Gaps where b was still waiting are left out: that
        idle time is the graph's, not the scheduler's.
    """
    spans = list(spans)
    stop = {key: s1 for key, _w, _s0, s1 in spans}
    by_worker: dict[str, list[tuple[float, float, str]]] = {}
    for key, w, s0, s1 in spans:
        by_worker.setdefault(w, []).append((s0, s1, key))
    gaps = []
    for runs in by_worker.values():
        runs.sort()
        for (_a0, a1, _ka), (b0, _b1, kb) in zip(runs, runs[1:]):
            ready = max((stop.get(d, -math.inf) for d in deps.get(kb, ())), default=-math.inf)
            if ready <= a1:
                gaps.append(max(0.0, b0 - a1))
    return gaps
