"""The Dask executor: the same :class:`~schlieren.workers.plan.Plan` as Dask futures.

One future per task, keyed deterministically (``stage-token-index``) so the dashboard
groups them by stage; dependencies are passed as arguments so the scheduler orders the
work; tasks take paths and indices and return small receipts. Tomography and
integration tasks ask for the ``TOMO`` worker resource, so a worker never runs more of
those memory-heavy solves at once than it advertises (when no worker advertises it, the
annotation is dropped rather than letting tasks wait forever, DASK-ZARR.md pitfall 12).
"""

from __future__ import annotations

import logging
import time
from typing import Callable

from distributed import Client, as_completed

from schlieren.workers.plan import Plan
from schlieren.workers.tasks import run_task

log = logging.getLogger(__name__)

__all__ = ["run_graph", "worker_resources"]


def worker_resources(client: Client) -> set[str]:
    """Resource names advertised by at least one worker."""
    info = client.scheduler_info()
    names: set[str] = set()
    for w in info.get("workers", {}).values():
        names |= set((w.get("resources") or {}).keys())
    return names


def run_graph(client: Client, store_path: str, plan: Plan, *,
              on_receipt: Callable[[dict], None] | None = None,
              on_failure: Callable[[str, str], None] | None = None,
              retries: int = 1) -> tuple[list[dict], dict[str, str]]:
    """Submit every task of ``plan`` to ``client`` and wait for all of them.

    Returns
    -------
    receipts : list of dict
    failures : dict
        Task key -> one-line error. Tasks downstream of a failure carry the upstream
        message prefixed with ``not run: depends on failed``.
    """
    have = worker_resources(client)
    futures = {}
    for task in plan.tasks:
        deps = [futures[d] for d in task.deps if d in futures]
        resources = {k: v for k, v in task.resources if k in have} or None
        futures[task.key] = client.submit(
            run_task, str(store_path), task.stage, task.index, *deps, run_token=plan.token,
            key=task.key, resources=resources, retries=retries, pure=False)
    if any(t.resources for t in plan.tasks) and not have:
        log.warning("no worker advertises the TOMO resource; solves are not limited per worker")
    receipts: list[dict] = []
    failures: dict[str, str] = {}
    first_error: dict[str, str] = {}
    pending = as_completed(list(futures.values()))
    for fut in pending:
        if fut.status not in {"finished", "error", "cancelled"}:
            # a result lost with its worker is recomputed by the scheduler: wait for it again
            time.sleep(0.05)
            pending.add(fut)
            continue
        if fut.status == "finished":
            r = fut.result()
            receipts.append(r)
            if on_receipt:
                on_receipt(r)
            continue
        exc = fut.exception()
        msg = " ".join(f"{type(exc).__name__}: {exc}".split()) if exc is not None else f"task {fut.status}"
        if msg.startswith("TaskFailed: "):
            msg = msg[len("TaskFailed: "):]
        origin = first_error.setdefault(msg, fut.key)
        failures[fut.key] = msg if origin == fut.key else f"not run: depends on failed {origin}"
        if on_failure:
            on_failure(fut.key, failures[fut.key])
    return receipts, failures
