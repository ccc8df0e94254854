"""Retention: the intermediates a run keeps, dropped as soon as nothing will read them again.

``schlieren run --keep`` (:func:`arrays_to_drop`): ``all`` (the default) keeps every
array; ``results`` drops the three large intermediates :data:`DROPPABLE` (``flow_raw``,
``flow``, ``potential``: nearly all of a paper-scale store, benchmarks/results/retention.md)
and keeps the volumes, masks, hulls and the small per-frame arrays; a comma-separated
list keeps those intermediates and drops the others.

How it stays correct (docs/store.md, "Retention"):

* **Who reads what.** :func:`reader_group` and :func:`group_reads` state, per task that
  reads a droppable array, which of its chunks it reads (a chunk is named by its
  producer's index: ``flow`` chunk ``(c, k)`` is ``resample`` task ``(c, k)``'s output).
  Readers are grouped (the masks of one camera read all of that camera's frames: one
  counter, not one per frame pair), so the bookkeeping stays linear in the run's size.
* **Dropping** (:class:`Dropper`, fed the run's receipts in the coordinator): a chunk is
  deleted once every task reading it has completed; at the end of a complete run an
  array without chunks is removed from the store altogether.
* **Resume and verify.** The store's ``retention`` attribute lists the arrays whose
  chunks may be missing by policy; the integrity scans do not count those as lost, and
  readers say "not kept" (storage/store/retention.py). Before planning,
  :func:`to_regenerate` finds the dropped chunks that a task still to run will read (a
  downstream chunk found damaged, a killed run) or that a wider ``--keep`` now keeps, and
  clears their producers' markers, recursively (a resampled flow needs its raw flows):
  those are computed again, bit for bit as before, and nothing downstream of them is
  invalidated.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from typing import Callable, Iterable

from schlieren.pipeline.stages import stage as stage_of
from schlieren.workers.plan import Extents, _deps, _indices

log = logging.getLogger(__name__)

__all__ = ["DROPPABLE", "PRODUCER", "arrays_to_drop", "keep_text", "reader_group", "group_reads", "Dropper",
           "to_regenerate", "KEEP_HELP"]

#: The intermediates a run may drop, and the stage writing each (one chunk per task index).
DROPPABLE = ("flow_raw", "flow", "potential")
PRODUCER = {"flow_raw": "deflection", "flow": "resample", "potential": "potential"}
#: The stages reading a droppable array (the tasks a dropped chunk waits for).
READERS = ("resample", "potential", "mask", "regularisation", "tomography")

KEEP_HELP = ("intermediates to keep: all (default), results (drop flow_raw, flow and potential once the stages "
             "reading them are done; volumes, masks and hulls stay), or a comma-separated list of flow_raw, flow, "
             "potential to keep (the others are dropped). Store per time step at paper scale (16 cameras at "
             "1440x1080, 2.5 mm voxels): all 56.9 MB, flow 23.7 MB, results 1.6 MB (docs/store.md, Retention)")


def arrays_to_drop(keep: str | Iterable[str] | None) -> frozenset[str]:
    """The droppable arrays that ``keep`` (``"all"``, ``"results"`` or the names of the
    intermediates to keep, comma-separated or a list) does not keep.

    Raises
    ------
    ValueError
        An unknown name, naming the valid ones.
    """
    if keep is None:
        return frozenset()
    names = [n.strip() for n in keep.split(",")] if isinstance(keep, str) else [str(n).strip() for n in keep]
    names = [n for n in names if n]
    if names == ["all"]:
        return frozenset()
    if names == ["results"]:
        return frozenset(DROPPABLE)
    bad = [n for n in names if n not in DROPPABLE]
    if bad or not names:
        raise ValueError(f"--keep {','.join(names)!r}: expected all, results, or a comma-separated list of "
                         f"{', '.join(DROPPABLE)} (the intermediates to keep)")
    return frozenset(DROPPABLE) - set(names)


def keep_text(keep: str | Iterable[str] | None) -> str:
    """``keep`` as the store records it: ``all``, ``results`` or ``flow,potential``."""
    drop = arrays_to_drop(keep)
    if not drop:
        return "all"
    if drop == set(DROPPABLE):
        return "results"
    return ",".join(n for n in DROPPABLE if n not in drop)


# --------------------------------------------------------------------------------------
# who reads what
# --------------------------------------------------------------------------------------
def reader_group(stage: str, index: tuple[int, ...]) -> tuple | None:
    """The group of reader tasks ``stage`` at ``index`` belongs to (None: reads no droppable array)."""
    if stage == "resample":
        return ("resample", index[0], index[1])
    if stage == "potential":
        return ("potential", index[0], index[1])
    if stage == "mask":  # frame_evidence of frames k +- masks.temporal_radius: any frame of the camera
        return ("mask", index[0])
    if stage == "regularisation":  # the middle frame's flows (every camera): held for any frame
        return ("regularisation",)
    if stage == "tomography":
        return ("tomography", index[0])
    return None


def group_reads(group: tuple, ext: Extents) -> list[tuple[str, tuple[int, ...]]]:
    """``(array, producer index)`` of every droppable chunk a reader group reads."""
    kind = group[0]
    if kind == "resample":  # the raw flows of the plan's window (resample_window never reads beyond it)
        c, k = group[1], group[2]
        return [("flow_raw", i) for dep, i in _deps(stage_of("resample"), (c, k), ext) if dep == "deflection"]
    if kind == "potential":
        return [("flow", (group[1], group[2]))]
    if kind == "mask":
        c = group[1]
        return [(a, (c, i)) for a in ("flow", "potential") for i in range(ext.frame)]
    if kind == "regularisation":
        return [("flow", (c, k)) for c in range(ext.camera) for k in range(ext.frame)]
    if kind == "tomography":
        return [("flow", (c, group[1])) for c in range(ext.camera)]
    raise ValueError(f"unknown reader group {group!r}")  # pragma: no cover - the table is static


def _readers(ext: Extents) -> dict[tuple, set[tuple[str, tuple[int, ...]]]]:
    """Every reader group with its tasks ``(stage, index)``."""
    out: dict[tuple, set] = defaultdict(set)
    for name in READERS:
        for index in _indices(stage_of(name), ext):
            out[reader_group(name, index)].add((name, index))
    return out


def _stored(store, name: str) -> set[tuple[int, ...]]:
    """Producer indices of the stored chunks of ``name`` (a listing; empty if the array is gone)."""
    keys, _ = store.list_chunks(name)
    n = len(stage_of(PRODUCER[name]).over)
    return {tuple(k[:n]) for k in keys}


# --------------------------------------------------------------------------------------
# dropping as the run goes
# --------------------------------------------------------------------------------------
class Dropper:
    """Deletes each chunk of the arrays in ``drop`` once every task reading it is done.

    Feed it the run's receipts (:meth:`receipt`); :meth:`start` drops at once what no task
    of this run will read (a resumed store under a narrower ``--keep``), :meth:`finish`
    removes the arrays left without chunks after a complete run.
    """

    def __init__(self, store, ext: Extents, drop: Iterable[str], done: Callable[[str, tuple], bool]):
        self.store, self.ext, self.drop = store, ext, frozenset(drop)
        self.done = done
        self.pending: dict[tuple, set] = {}
        self.groups_of: dict[tuple[str, tuple], list[tuple]] = defaultdict(list)
        self.dropped = 0
        if not self.drop:
            return
        for group, members in _readers(ext).items():
            reads = [(a, i) for a, i in group_reads(group, ext) if a in self.drop]
            if not reads:
                continue
            self.pending[group] = {m for m in members if not done(*m)}
            for chunk in reads:
                self.groups_of[chunk].append(group)

    def start(self) -> None:
        """Drop the stored chunks no task of this run reads (their producers done)."""
        for a in self.drop:
            for i in sorted(_stored(self.store, a)):
                if self.done(PRODUCER[a], i) and not any(self.pending.get(g) for g in self.groups_of[(a, i)]):
                    self._delete(a, i)

    def receipt(self, r: dict) -> None:
        """A task completed (or was found complete): drop the chunks it was the last to need."""
        group = reader_group(r.get("stage", ""), tuple(r.get("index") or ()))
        waiting = self.pending.get(group)
        if not waiting:
            return
        waiting.discard((r["stage"], tuple(int(v) for v in r["index"])))
        if waiting:
            return
        for a, i in group_reads(group, self.ext):
            if a in self.drop and not any(self.pending.get(g) for g in self.groups_of[(a, i)]):
                self._delete(a, i)

    def _delete(self, a: str, i: tuple[int, ...]) -> None:
        self.store.drop_chunk(a, i)
        self.dropped += 1

    def finish(self) -> list[str]:
        """After a complete run: remove the dropped arrays that hold no chunk any more."""
        empty = [a for a in DROPPABLE if a in self.drop and not _stored(self.store, a)]
        return self.store.remove_arrays(empty)


# --------------------------------------------------------------------------------------
# what a rerun must compute again
# --------------------------------------------------------------------------------------
def to_regenerate(store, ext: Extents, done: dict[str, set], drop: Iterable[str],
                  dropped_before: Iterable[str]) -> set[tuple[str, tuple[int, ...]]]:
    """Producer tasks ``(stage, index)`` whose dropped chunks this run needs again.

    A chunk of an array in ``dropped_before`` (the store's ``retention``) that has no file
    although its producer is marked done is needed when a task still to run reads it, or
    when the policy now keeps its array (not in ``drop``). Producers to run again read
    their own inputs: the search goes on until nothing new is needed.
    """
    dropped_before = frozenset(dropped_before) & set(DROPPABLE)
    if not dropped_before:
        return set()
    drop = frozenset(drop)
    stored = {a: _stored(store, a) for a in dropped_before}

    def missing(a: str, i: tuple[int, ...]) -> bool:
        return a in stored and i in done.get(PRODUCER[a], ()) and i not in stored[a]

    need: set[tuple[str, tuple[int, ...]]] = set()
    frontier: list[tuple[str, tuple[int, ...]]] = []
    for a in dropped_before - drop:  # kept again: every chunk the policy dropped
        st = stage_of(PRODUCER[a])
        for i in _indices(st, ext):
            if missing(a, i):
                need.add((st.name, i))
    frontier += sorted(need)
    for name in READERS:  # readers still to run
        frontier += [(name, i) for i in _indices(stage_of(name), ext) if i not in done.get(name, ())]
    seen_groups: set[tuple] = set()
    while frontier:
        name, i = frontier.pop()
        group = reader_group(name, i)
        if group is None or group in seen_groups:
            continue
        seen_groups.add(group)
        for a, j in group_reads(group, ext):
            producer = PRODUCER[a]
            if missing(a, j) and (producer, j) not in need:
                need.add((producer, j))
                frontier.append((producer, j))
    return need
