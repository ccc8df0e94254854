"""Compile the declared stage table into a list of tasks with explicit dependencies.

Both executors run the same :class:`Plan`: ``workers/serial.py`` in a plain loop (in
order), ``workers/graph.py`` as Dask futures. Tasks whose completion marker is already
set in the store are left out, so a rerun computes only what is missing.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from schlieren.pipeline.stages import STAGES, Stage, middle_frame

__all__ = ["Task", "Plan", "make_plan", "Extents", "critical_path_priorities"]


@dataclass(frozen=True)
class Extents:
    """Sizes of the dims stages map over."""

    camera: int
    frame: int
    raw_frame: int
    raw_offset: int  # raw_frame index of output frame 0 (raw_first = first_frame - raw_offset)
    warm_start_block: int = 4


@dataclass(frozen=True)
class Task:
    """One graph node: a stage at one index, or at consecutive frames of one camera.

    ``index`` is the first index covered (it names the key); ``indices`` lists every
    index the task computes, in order (``(index,)`` unless the stage is batched).
    """

    stage: str
    index: tuple[int, ...]
    key: str
    deps: tuple[str, ...] = ()
    resources: tuple[tuple[str, int], ...] = ()
    indices: tuple[tuple[int, ...], ...] = ()

    def __post_init__(self):
        if not self.indices:
            object.__setattr__(self, "indices", (self.index,))

    @property
    def labels(self) -> dict:
        st = _STAGE[self.stage]
        return dict(zip(st.over, self.index))


@dataclass
class Plan:
    tasks: list[Task] = field(default_factory=list)
    skipped: int = 0
    token: str = ""  # the run's token (in every key; tasks key their per-process caches by it)

    def by_stage(self) -> dict[str, list[Task]]:
        out: dict[str, list[Task]] = {s.name: [] for s in STAGES}
        for t in self.tasks:
            out[t.stage].append(t)
        return out


_STAGE = {s.name: s for s in STAGES}


def _indices(st: Stage, ext: Extents) -> list[tuple[int, ...]]:
    sizes = {"camera": ext.camera, "frame": ext.frame, "raw_frame": ext.raw_frame}
    return list(itertools.product(*(range(sizes[d]) for d in st.over)))


def task_key(stage: str, token: str, index: tuple[int, ...]) -> str:
    """Deterministic Dask key: ``stage-token-i-j`` (the dashboard groups by ``stage``)."""
    return "-".join([stage, token] + [f"{i:06d}" for i in index])


def _deps(st: Stage, index: tuple[int, ...], ext: Extents) -> list[tuple[str, tuple[int, ...]]]:
    """The dependency indices of one task, built directly (linear in the plan size).

    ``same``: the dependency's dims shared with this stage fixed to this task's labels,
    the others over their whole range. ``window``: the same camera, frames within
    ``frame_halo`` (a ``raw_frame`` dependency shifted by ``raw_offset``), not by scanning
    every index of the dependency stage per task, which is quadratic in frames
    (docs/tuning.md, "Scheduling").
    """
    labels = dict(zip(st.over, index))
    sizes = {"camera": ext.camera, "frame": ext.frame, "raw_frame": ext.raw_frame}
    out: list[tuple[str, tuple[int, ...]]] = []
    for dep_name, how in st.after:
        dep = _STAGE[dep_name]
        if how == "all":
            out += [(dep_name, i) for i in _indices(dep, ext)]
        elif how == "same":
            axes = [(labels[d],) if d in labels else range(sizes[d]) for d in dep.over]
            out += [(dep_name, i) for i in itertools.product(*axes)]
        elif how == "window":
            # the dependency's frames within frame_halo of this task's frame, same camera
            centre = labels["frame"]
            axes = []
            for d in dep.over:
                if d == "camera":
                    axes.append((labels["camera"],) if "camera" in labels else range(sizes[d]))
                elif d in ("frame", "raw_frame"):
                    shift = ext.raw_offset if d == "raw_frame" else 0
                    lo = max(centre - st.frame_halo + shift, 0)
                    hi = min(centre + st.frame_halo + shift, sizes[d] - 1)
                    axes.append(range(lo, hi + 1))
                else:  # pragma: no cover - the table is static
                    axes.append(range(sizes[d]))
            out += [(dep_name, i) for i in itertools.product(*axes)]
        elif how == "chain":
            k = labels["frame"]
            if k % max(ext.warm_start_block, 1) != 0:
                out.append((dep_name, (k - 1,)))
        elif how == "margin":  # raw frames outside the output range only
            r = labels["raw_frame"]
            if r < ext.raw_offset or r >= ext.raw_offset + ext.frame:
                out += [(dep_name, i) for i in _indices(dep, ext)]
        elif how == "middle":  # the dependency at the middle output frame (every camera)
            k = middle_frame(sizes["frame"])
            axes = [(k,) if d == "frame" else range(sizes[d]) for d in dep.over]
            out += [(dep_name, i) for i in itertools.product(*axes)]
        elif how == "block":  # every frame of this task's warm-start block
            B = max(ext.warm_start_block, 1)
            lo = labels["frame"] - labels["frame"] % B
            out += [(dep_name, (k,)) for k in range(lo, min(lo + B, sizes["frame"]))]
        else:  # pragma: no cover - the table is static
            raise ValueError(f"unknown dependency kind {how!r} in stage {st.name}")
    return out


def batch_sizes(frames_per_task) -> dict[str, int]:
    """Frames per task of every batched stage, from one number for all of them or a
    mapping ``{stage: frames}`` (batched stages it leaves out get 1)."""
    if isinstance(frames_per_task, int):
        out = {s.name: int(frames_per_task) for s in STAGES if s.batch}
    else:
        unknown = set(frames_per_task) - {s.name for s in STAGES if s.batch}
        if unknown:
            raise ValueError(f"frames_per_task names stages that are not batched: {sorted(unknown)}")
        out = {s.name: int(frames_per_task.get(s.name, 1)) for s in STAGES if s.batch}
    bad = {k: v for k, v in out.items() if v < 1}
    if bad:
        raise ValueError(f"frames_per_task must be at least 1, not {bad}")
    return out


def _blocks(st: Stage, indices: list[tuple[int, ...]], frames_per_task: int) -> list[list[tuple[int, ...]]]:
    """Group a batched stage's indices by camera into runs of ``frames_per_task`` frames.

    Block boundaries are fixed (frame // frames_per_task), so a resumed run groups the
    frames still missing the same way.
    """
    if not st.batch or frames_per_task <= 1:
        return [[i] for i in indices]
    groups: dict[tuple[int, int], list[tuple[int, ...]]] = {}
    for i in indices:  # (camera, frame) or (camera, raw_frame)
        groups.setdefault((i[0], i[1] // frames_per_task), []).append(i)
    return [groups[k] for k in sorted(groups)]


def make_plan(ext: Extents, token: str, *, done=None, stages: tuple[Stage, ...] = STAGES,
              frames_per_task: int | dict = 1) -> Plan:
    """All tasks of all stages, minus those already complete.

    Parameters
    ----------
    ext : Extents
    token : str
        Short session/run token that makes keys unique per run.
    done : callable(stage, index) -> bool, optional
        Completion-marker lookup; complete indices are dropped and so are edges to them.
    frames_per_task : int or dict
        Consecutive frames of one camera per task for the cheap per-camera-frame stages
        (``Stage.batch``: deflection, resampling, potential, mask); one
        number for all or ``{stage: frames}`` (:func:`batch_sizes`).
        Their per-frame work is comparable to what each Dask task costs in the
        scheduler, the client and the worker (docs/tuning.md, "Scheduling"). Completion markers stay per
        frame, so resume and the store do not depend on the grouping.
    """
    sizes = batch_sizes(frames_per_task)
    plan = Plan(token=token)
    complete: set[tuple[str, tuple[int, ...]]] = set()
    owner: dict[tuple[str, tuple[int, ...]], str] = {}  # (stage, index) -> key of its task
    for st in stages:
        todo = []
        for index in _indices(st, ext):
            if done is not None and done(st.name, index):
                complete.add((st.name, index))
                plan.skipped += 1
            else:
                todo.append(index)
        fpt = sizes.get(st.name, 1)
        for block in _blocks(st, todo, fpt):
            first = block[0]
            if st.batch and fpt > 1:  # name the block by its fixed start
                first = (first[0], first[1] - first[1] % fpt)
            key = task_key(st.name, token, first)
            deps: dict[str, None] = {}   # ordered, de-duplicated (a list's `in` made "all" edges quadratic)
            for index in block:
                for n, i in _deps(st, index, ext):
                    if (n, i) in complete:
                        continue
                    d = owner[(n, i)]
                    if d != key:
                        deps[d] = None
            for index in block:
                owner[(st.name, index)] = key
            plan.tasks.append(Task(st.name, block[0], key, tuple(deps),
                                   tuple(sorted(st.resources.items())), tuple(block)))
    return plan


#: Priority step (rank seconds) between consecutive solves of a warm-start chain in
#: :func:`chain_first_priorities`: above the chain head's rank, below anything a second costlier.
CHAIN_STEP = 1e-3


def chain_first_priorities(plan: Plan, rank: dict[str, float]) -> dict[str, float]:
    """``rank`` with every task of a warm-start chain (a ``chain`` dependency, the
    tomography solves) lifted to its chain head's rank plus ``CHAIN_STEP`` per position.

    By rank alone a block's second solve ranks below every other block's first, so a
    worker that finished one block's first solve went on to the next block's first, and
    every solve missed the block restriction its worker had just built (``solve_gradient``'s
    ``support``; a worker thread keeps two, as Dask hands a worker its next task before the
    running one ends). Lifted, the next solve of the block a
    worker just advanced outranks other blocks' heads, so the worker that holds the block's
    restriction (it also holds the previous solve's receipt) carries the chain on; blocks
    still start side by side on idle workers, and at most one block per worker is left at
    the end.
    """
    out = dict(rank)
    chained = {st.name for st in STAGES if any(how == "chain" for _, how in st.after)}
    by_key = {t.key: t for t in plan.tasks}
    head_of: dict[str, tuple[str, int]] = {}
    for t in plan.tasks:  # dependency order: a chain's predecessor comes first
        if t.stage not in chained:
            continue
        prev = next((d for d in t.deps if d in head_of and by_key[d].stage == t.stage), None)
        head_of[t.key] = (t.key, 0) if prev is None else (head_of[prev][0], head_of[prev][1] + 1)
        head, pos = head_of[t.key]
        out[t.key] = max(rank[t.key], rank[head] + CHAIN_STEP * pos)
    return out


def critical_path_priorities(plan: Plan, costs: dict[str, float] | None = None) -> dict[str, float]:
    """Each task's priority: the longest chain of work from its start to the run's end.

    ``rank(t) = cost(t) + max(rank(s) for s waiting for t)`` (upward rank of list
    scheduling; the classic critical-path-first heuristic). Running the ready task of
    highest rank first starts the long chains early: after the threshold barrier the
    masks and hulls of each warm-start block (its first solve waits for all of them, to
    restrict the projection once to their union) go before other work, so the chained
    tomography solves of all blocks proceed side by side and
    the run does not end on one worker finishing a chain alone.

    Parameters
    ----------
    plan : Plan
        Its tasks are in dependency order (every dependency comes earlier).
    costs : dict, optional
        Stage name -> rough seconds per task; default each stage's declared ``cost``.

    Returns
    -------
    dict
        Task key -> rank in seconds (higher runs first).
    """
    costs = costs or {name: st.cost for name, st in _STAGE.items()}
    waiting: dict[str, list[str]] = {t.key: [] for t in plan.tasks}
    for t in plan.tasks:
        for d in t.deps:
            if d in waiting:
                waiting[d].append(t.key)
    rank: dict[str, float] = {}
    for t in reversed(plan.tasks):
        rank[t.key] = costs[t.stage] * len(t.indices) + max((rank[s] for s in waiting[t.key]), default=0.0)
    return rank
