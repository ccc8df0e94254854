"""Verified resume: find lost or corrupt chunks and recompute them with everything downstream.

Before a rerun trusts the completion markers it lists the store (:func:`verify_store`
with ``full=False``: one directory walk, every marker read, no data read): a chunk that
has no file although its task's marker is set was lost. ``schlieren verify STORE`` and
``schlieren run ... --verify`` also read every chunk and check its CRC-32C. Each damaged
chunk names the task that writes it (the array's producer stage at the chunk's marker
position); *repair* clears the markers of that task and of every task downstream of it in
the plan (in that order: downstream first, so an interrupted repair is found again by the
next scan) and removes the damaged files, so the next run recomputes exactly those tasks.
Tasks are deterministic (the executors already agree bit for bit), so the repaired store
equals an undisturbed run's.

The tomography geometry is a cache beside the store (``<store>.cache``), not a result. A
corrupt one (sizes and CRC-32C recorded in its manifest) is a problem, removed by the
repair; a missing one (a store copied without it) is not. Either way, if tomography work
remains the ``geometry`` marker is cleared so that the run builds it again. Nothing
downstream is recomputed for it: every tomography task checked the geometry's checksums
when it mapped it, so the results it made came from intact bytes.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

from schlieren.storage import arrays_cache
from schlieren.storage.integrity import Problem, ScanResult, scan_store
from schlieren.storage.store import ResultStore
from schlieren.workers.plan import Extents, make_plan

log = logging.getLogger(__name__)

__all__ = ["VerifyReport", "verify_store", "extents_of", "downstream"]


@dataclass
class VerifyReport:
    scan: ScanResult
    invalidated: dict[str, int] = field(default_factory=dict)  # stage -> markers cleared
    removed_files: int = 0
    rewritten_metadata: int = 0
    repaired: bool = False

    @property
    def problems(self) -> list[Problem]:
        return self.scan.problems

    @property
    def ok(self) -> bool:
        return self.scan.ok

    @property
    def done(self) -> dict[str, set]:
        return self.scan.done

    def lines(self, limit: int = 20) -> list[str]:
        from schlieren.storage.integrity import describe

        return describe(self.scan, limit)

    def summary(self) -> str:
        from schlieren.storage.integrity import summary_line

        text = summary_line(self.scan)
        if self.repaired and self.invalidated:
            n = sum(self.invalidated.values())
            per = ", ".join(f"{s} {k}" for s, k in self.invalidated.items())
            text += f"; {n} task(s) to recompute ({per})"
        if self.repaired and self.rewritten_metadata:
            text += f"; {self.rewritten_metadata} metadata file(s) rewritten from the consolidated metadata"
        return text


def _run_stages(store: ResultStore):
    """The stages the store's run has: every default stage and the optional ones with a marker."""
    from schlieren.pipeline.stages import stages_with

    return stages_with(set(store.stages()))


def extents_of(store: ResultStore) -> Extents:
    """The plan's extents, from the store's ``run`` attributes."""
    a = store.attrs
    run = a["run"]
    first = int(run["frames"][0])
    params = a.get("params") or {}
    return Extents(camera=int(store.array("camera").shape[0]), frame=int(run["n_frames"]),
                   raw_frame=int(run["n_raw"]), raw_offset=first - int(run["raw_first"]),
                   warm_start_block=int(params.get("warm_start_block", 4)),
                   spacetime_window=int((params.get("spacetime") or {}).get("window", 0)))


def downstream(ext: Extents, roots, stages=None) -> set[tuple[str, tuple[int, ...]]]:
    """``roots`` (stage, index) and every task that depends on them, directly or not
    (``stages``: the run's, default :data:`~schlieren.pipeline.stages.STAGES`)."""
    plan = make_plan(ext, "v", frames_per_task=1, **({"stages": tuple(stages)} if stages is not None else {}))
    node = {t.key: (t.stage, tuple(t.index)) for t in plan.tasks}
    key_of = {v: k for k, v in node.items()}
    waiting: dict[str, list[str]] = {k: [] for k in node}
    for t in plan.tasks:
        for d in t.deps:
            waiting[d].append(t.key)
    seen = {key_of[(s, tuple(i))] for s, i in roots if (s, tuple(i)) in key_of}
    todo = deque(seen)
    while todo:
        for k in waiting[todo.popleft()]:
            if k not in seen:
                seen.add(k)
                todo.append(k)
    return {node[k] for k in seen}


def _geometry_cache(store: ResultStore, scan: ScanResult, *, full: bool) -> tuple[list[Problem], bool]:
    """``(problems, unusable)`` of the geometry cache (checked whether or not its marker is
    set: a set of files that exists is trusted by the stage that would build it)."""
    try:
        from schlieren.workers.tasks import context
        from schlieren.workers.tasks.geometry import geometry_key

        path = arrays_cache.cache_dir(store.path, "geometry", geometry_key(context(store.path)))
    except Exception as exc:  # noqa: BLE001 - e.g. the session manifest moved: cannot tell
        log.warning("cannot locate the geometry cache of %s (%s); not checked", store.path, exc)
        return [], False
    if not arrays_cache.has_arrays(path):  # removed (schlieren clean) or never copied
        return [], () in scan.done.get("geometry", set())
    bad = arrays_cache.verify_arrays(path, read=full)
    if bad:
        return [Problem("geometry cache", (), "corrupt", bad[0])], True
    return [], False


def verify_store(store: ResultStore, *, full: bool = False, repair: bool = False,
                 ext: Extents | None = None) -> VerifyReport:
    """Scan ``store`` and, with ``repair``, clear what must be recomputed.

    Parameters
    ----------
    store : ResultStore
        Open read-write for ``repair``.
    full : bool
        Read every chunk (checksums); otherwise list files and read markers only.
    repair : bool
        Clear the markers of every damaged task and of everything downstream of it,
        remove damaged chunk files and orphaned ``*.partial`` files. The next run
        recomputes those tasks.
    ext : Extents, optional
        Default :func:`extents_of` the store.

    Returns
    -------
    VerifyReport
        ``done`` holds the marker positions still set after the repair.
    """
    scan = scan_store(store, full=full)
    geo_problems, geo_unusable = _geometry_cache(store, scan, full=full)
    scan.problems += geo_problems
    report = VerifyReport(scan=scan)
    if not repair or (scan.ok and not scan.partial_files and not geo_unusable):
        return report
    ext = ext or extents_of(store)
    roots = {(p.stage, tuple(p.index)) for p in scan.problems if p.stage is not None}
    redo = downstream(ext, roots, _run_stages(store))
    # downstream first, the damaged tasks last: an interrupted repair is found again
    order = sorted(redo - roots) + sorted(roots)
    for stage, idx in order:
        if idx in scan.done.get(stage, set()) or (stage, idx) in roots:
            store.unmark(stage, idx)
            scan.done.get(stage, set()).discard(idx)
            report.invalidated[stage] = report.invalidated.get(stage, 0) + 1
    if any(p.kind == "corrupt-metadata" for p in scan.problems):
        report.rewritten_metadata = len(store.check_metadata(repair=True))
    for p in scan.problems:
        if p.kind in ("corrupt", "stray") and p.array != "geometry cache":
            store.remove_chunk(p.array, p.chunk)
            report.removed_files += 1
    if geo_problems:
        arrays_cache.remove_cache(store.path)
        report.removed_files += 1
    readers = [s for s in ("tomography", "uncertainty") if s == "tomography" or s in scan.done]
    if geo_unusable and () in scan.done.get("geometry", set()) and any(len(scan.done.get(s, ())) < ext.frame
                                                                       for s in readers):
        store.unmark("geometry")  # tomography remains: the run builds the geometry again
        scan.done.get("geometry", set()).discard(())
        report.invalidated["geometry"] = report.invalidated.get("geometry", 0) + 1
    import os

    for f in scan.partial_files:
        try:
            os.remove(f)
            report.removed_files += 1
        except FileNotFoundError:
            pass
    report.repaired = True
    if scan.problems:
        log.warning("%s: %s", store.path, report.summary())
    return report
