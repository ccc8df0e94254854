"""Running tasks: one stage at one index, its completion marker, its receipt and its failure.

:func:`run_task` and :func:`run_tasks` (a batch of indices of one stage) are what the
executors call (``workers/serial.py`` in a loop, ``workers/graph.py`` as Dask nodes).
Each index's stage task (:data:`STAGE_TASKS`) runs unless its marker is set; the marker
is written after every chunk of the task, so a task killed midway is simply run again.
Any error becomes :class:`~schlieren.workers.tasks.run_context.TaskFailed` with one line
naming the stage, camera and frame.
"""

from __future__ import annotations

import logging
import time

from schlieren.pipeline.stages import stage
from schlieren.storage.inflight import settle
from schlieren.workers.monitoring import log_receipt
from schlieren.workers.tasks.capture import capture_task
from schlieren.workers.tasks.deflection import deflection_task
from schlieren.workers.tasks.geometry import geometry_task
from schlieren.workers.tasks.hull import hull_task
from schlieren.workers.tasks.integrate import integrate_task
from schlieren.workers.tasks.masks import mask_task, potential_task, threshold_task
from schlieren.workers.tasks.regularisation import regularisation_task
from schlieren.workers.tasks.resample import resample_task
from schlieren.workers.tasks.run_context import RunContext, TaskFailed, context
from schlieren.workers.tasks.spacetime import spacetime_task
from schlieren.workers.tasks.sync import clock_task, sync_task
from schlieren.workers.tasks.tomography import tomography_task
from schlieren.workers.tasks.uncertainty import uncertainty_task

__all__ = ["run_task", "run_tasks", "flush_writes", "STAGE_TASKS", "failure_text"]

log = logging.getLogger(__package__)  # the package's logger: log records name it as before the split

#: Each stage's task: ``task(ctx, *index) -> dict`` of extra receipt fields.
STAGE_TASKS = {
    "sync": sync_task, "clock": clock_task, "capture": capture_task, "deflection": deflection_task,
    "regularisation": regularisation_task,
    "resample": resample_task, "potential": potential_task, "threshold": threshold_task, "mask": mask_task,
    "geometry": geometry_task, "hull": hull_task, "tomography": tomography_task,
    "spacetime": spacetime_task, "integrate": integrate_task, "uncertainty": uncertainty_task,
}


def _describe(stage_name: str, index: tuple[int, ...], ctx: RunContext | None) -> str:
    st = stage(stage_name)
    parts = [stage_name]
    for dim, i in zip(st.over, index):
        if dim == "camera" and ctx is not None:
            parts.append(f"camera {ctx.cameras[i].name}")
        elif dim == "frame" and ctx is not None:
            parts.append(f"frame {ctx.first_frame + i}")
        elif dim == "raw_frame" and ctx is not None:
            parts.append(f"frame {ctx.raw_first + i}")
        else:
            parts.append(f"{dim} {i}")
    return ", ".join(parts)


def _worker_address() -> str | None:
    """The Dask worker running this task, or None (the serial loop)."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return None


def run_task(store_path: str, stage_name: str, index: tuple[int, ...], *_deps, run_token: str = "") -> dict:
    """Run one stage at one index and return its receipt.

    Extra positional arguments are the receipts of the tasks this one waits for (the Dask
    executor passes them so the graph carries the dependencies); they are ignored.
    ``run_token`` (the plan's) keys this process's caches of the run.
    """
    receipt = _run_one(store_path, stage_name, index, run_token)
    flush_writes(store_path, run_token, stage_name)
    return receipt


def flush_writes(store_path: str, run_token: str = "", stage_name: str = "store") -> None:
    """Wait until this process's writes to the run's store are stored.

    In an object store chunks and markers go out in the background (storage/remote.py);
    a task's dependents may run elsewhere, so every Dask task calls this before it
    returns. A failed write raises :class:`TaskFailed` naming the array and index (its
    marker was not sent, so a rerun computes it again).
    """
    try:
        context(str(store_path), str(run_token)).store.flush()
    except OSError as exc:
        raise TaskFailed(f"{stage_name}: {exc}") from None


def _run_one(store_path: str, stage_name: str, index: tuple[int, ...], run_token: str) -> dict:
    index = tuple(int(i) for i in index)
    try:
        return _run_task(store_path, stage_name, index, run_token)
    except TaskFailed:
        settle()  # the failed call's other chunk reads and writes end before the failure is reported
        raise
    except Exception as exc:  # the store unreadable, the disk full while marking...: one line
        settle()
        raise TaskFailed(failure_text(f"{stage_name} {list(index)}", exc)) from exc


def failure_text(where: str, exc: BaseException) -> str:
    """``where: Type: message`` on one line; a full disk says so and that nothing is lost."""
    import errno

    msg = f"{where}: {type(exc).__name__}: {exc}"
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        msg += " (the disk is full: free space and rerun; completed chunks are kept)"
    return " ".join(msg.split())


def _run_task(store_path: str, stage_name: str, index: tuple[int, ...], run_token: str) -> dict:
    t0 = time.perf_counter()
    c0 = time.thread_time()
    ctx = context(str(store_path), str(run_token))
    receipt = {"stage": stage_name, "index": list(index), "skipped": False}
    worker = _worker_address()
    if worker:
        receipt["worker"] = worker
    st = stage(stage_name)
    labels = dict(zip(st.over, index))
    if "camera" in labels:
        receipt["camera"] = ctx.cameras[labels["camera"]].name
    if "frame" in labels:
        receipt["frame"] = ctx.first_frame + labels["frame"]
    if "raw_frame" in labels:
        receipt["frame"] = ctx.raw_first + labels["raw_frame"]
    if ctx.store.is_done(stage_name, index):
        receipt["skipped"] = True
        receipt["seconds"] = time.perf_counter() - t0
        receipt["cpu_seconds"] = time.thread_time() - c0
        return receipt
    try:
        extra = STAGE_TASKS[stage_name](ctx, *index)
    except TaskFailed:
        raise
    except Exception as exc:  # name the camera/frame; the original type stays in the text
        raise TaskFailed(failure_text(_describe(stage_name, index, ctx), exc)) from exc
    try:
        ctx.store.mark_done(stage_name, index)
    except Exception as exc:  # noqa: BLE001 - e.g. the disk filled up right now
        raise TaskFailed(failure_text(_describe(stage_name, index, ctx), exc)) from exc
    receipt.update(extra)
    receipt["seconds"] = time.perf_counter() - t0
    # CPU of this thread only: below ``seconds`` when other processes took the core
    receipt["cpu_seconds"] = time.thread_time() - c0
    log_receipt(receipt)
    return receipt


def _prefetch_frames(store_path: str, run_token: str, stage_name: str, indices) -> None:
    """The input frames a batch of ``deflection`` indices reads, fetched together
    (one concurrent batch from an object store; nothing happens for folders)."""
    if stage_name != "deflection" or not indices:
        return
    try:
        ctx = context(str(store_path), str(run_token))
        by_camera: dict[int, list[int]] = {}
        for c, k in indices:
            by_camera.setdefault(int(c), []).append(ctx.raw_first + int(k))
        for c, frames in by_camera.items():
            ctx.frames(c).prefetch(frames)
    except Exception:  # noqa: BLE001 - only a hint: each read reports its own problem, naming the frame
        log.debug("prefetching the frames of %s %s failed", stage_name, indices, exc_info=True)


def run_tasks(store_path: str, stage_name: str, indices, *_deps, run_token: str = "",
              flush: bool = True) -> list[dict]:
    """Run one stage at each of ``indices`` in order (a batched task) and return the receipts.

    Every index is attempted even after one fails, so everything computable is written
    and marked; then the first failure is raised (its message names the camera and
    frame, with how many more failed in this task). ``flush=False`` returns without
    waiting for background writes (the serial loop, which reads them back in this
    process, calls :func:`flush_writes` at its end).
    """
    receipts: list[dict] = []
    failed: list[str] = []
    _prefetch_frames(store_path, run_token, stage_name, indices)
    for index in indices:
        try:
            receipts.append(_run_one(store_path, stage_name, index, run_token))
        except TaskFailed as exc:
            failed.append(str(exc))
    if flush:
        try:
            flush_writes(store_path, run_token, stage_name)
        except TaskFailed as exc:
            failed.append(str(exc))
    if failed:
        more = f" (and {len(failed) - 1} more frame(s) of this task)" if len(failed) > 1 else ""
        raise TaskFailed(failed[0] + more)
    return receipts
