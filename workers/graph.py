"""The Dask executor: the same :class:`~schlieren.workers.plan.Plan` as one Dask graph.

Every task of the plan becomes a node keyed deterministically (``stage-token-index``, so
the dashboard groups them by stage) that depends on the nodes of the tasks it waits for;
tasks take paths and indices and return small receipts. The whole plan goes to the
scheduler in one ``update-graph`` per resource group (two: tomography and integration
tasks ask for the ``TOMO`` worker resource, so a worker never runs more of those
memory-heavy solves at once than it advertises; when no worker advertises it, the
annotation is dropped rather than letting tasks wait forever, DASK-ZARR.md pitfall 12).

Each task's priority is its critical-path rank (:func:`~schlieren.workers.plan.critical_path_priorities`),
so the warm-start blocks' chains of tomography solves start early and side by side; within a
chain each solve is lifted to its head's rank (:func:`~schlieren.workers.plan.chain_first_priorities`),
so the worker that advanced a block carries it on with the block's restriction it holds.

The client then follows the futures' states, which the scheduler pushes to it, and
fetches the receipts of finished tasks in batches (one ``gather`` per ``batch_interval``
seconds rather than one round trip per task): submitting task by task and fetching each
receipt on its own cost the client process CPU that the workers on the same machine need
(docs/tuning.md, "Scheduling").
"""

from __future__ import annotations

import logging
import time
from typing import Callable

from dask.task_spec import Task as GraphTask
from dask.task_spec import TaskRef
from distributed import Client

from schlieren.workers import interrupts
from schlieren.workers.plan import Plan, chain_first_priorities, critical_path_priorities
from schlieren.workers.tasks import run_tasks

log = logging.getLogger(__name__)

__all__ = ["run_graph", "worker_resources", "plan_graphs"]

_TERMINAL = frozenset({"finished", "error", "cancelled"})


def worker_resources(client: Client) -> set[str]:
    """Resource names advertised by at least one worker."""
    info = client.scheduler_info()
    names: set[str] = set()
    for w in info.get("workers", {}).values():
        names |= set((w.get("resources") or {}).keys())
    return names


def plan_graphs(store_path: str, plan: Plan, have: set[str]) -> list[tuple[dict | None, dict]]:
    """The plan as Dask graphs, one per distinct resource request: ``[(resources, graph)]``.

    Each node calls :func:`~schlieren.workers.tasks.run_tasks` with the store path, stage
    and the indices it covers, and takes the receipts of the tasks it waits for as extra arguments, so
    the scheduler orders the work. Resources nobody advertises are dropped.
    """
    groups: dict[tuple, dict] = {}
    for task in plan.tasks:
        res = tuple((k, v) for k, v in task.resources if k in have)
        groups.setdefault(res, {})[task.key] = GraphTask(
            task.key, run_tasks, str(store_path), task.stage, tuple(task.indices),
            *(TaskRef(d) for d in task.deps), run_token=plan.token)
    # each group is one update-graph: its dependencies must be in it or in an earlier group
    sent: set[str] = set()
    for dsk in groups.values():
        for key, node in dsk.items():
            late = [d for d in node.dependencies if d not in sent and d not in dsk]
            if late:  # pragma: no cover - the stage table orders resource stages last
                raise ValueError(f"task {key} depends on {late[0]}, submitted in a later graph")
        sent.update(dsk)
    return [(dict(res) or None, dsk) for res, dsk in groups.items()]


def run_graph(client: Client, store_path: str, plan: Plan, *,
              on_receipt: Callable[[dict], None] | None = None,
              on_failure: Callable[[str, str], None] | None = None,
              retries: int = 1, poll: float = 0.05,
              batch_interval: float = 0.25) -> tuple[list[dict], dict[str, str]]:
    """Submit every task of ``plan`` to ``client`` and wait for all of them.

    Parameters
    ----------
    retries : int
        Automatic reruns of a task that raised (a task that fails on its data fails again
        and is reported; a worker that died is handled by the scheduler regardless).
    poll : float
        Seconds between looks at the futures' states.
    batch_interval : float
        Least seconds between two receipt fetches (progress lags by at most this).

    Returns
    -------
    receipts : list of dict
    failures : dict
        Task key -> one-line error. Tasks downstream of a failure carry the upstream
        message prefixed with ``not run: depends on failed``.
    """
    have = worker_resources(client)
    if any(t.resources for t in plan.tasks) and not have:
        log.warning("no worker advertises the TOMO resource; solves are not limited per worker")
    # critical path first, a warm-start chain carried on by the worker that advanced it;
    # the scheduler calls the (picklable) dict.get once per key
    ranks = chain_first_priorities(plan, critical_path_priorities(plan))
    priority = {k: int(round(1e4 * r)) for k, r in ranks.items()}
    futures = {}
    for resources, dsk in plan_graphs(store_path, plan, have):
        got = client.get(dsk, list(dsk), resources=resources, retries=retries,
                         priority=priority.get, sync=False)
        futures.update(zip(dsk, got))
    order = [futures[t.key] for t in plan.tasks]
    receipts: list[dict] = []
    failures: dict[str, str] = {}
    first_error: dict[str, str] = {}
    remaining = order
    last_fetch = 0.0
    while remaining:
        interrupts.check()  # a Ctrl-C that was dropped on its way (workers/interrupts.py)
        states = [(f, f.status) for f in remaining]  # one look per future: states move on
        waiting = [f for f, st in states if st not in _TERMINAL]
        if len(waiting) == len(states) or (waiting and time.monotonic() - last_fetch < batch_interval):
            time.sleep(poll)
            continue
        remaining = waiting
        last_fetch = time.monotonic()
        finished = [f for f, st in states if st == "finished"]
        failed = [f for f, st in states if st in _TERMINAL and st != "finished"]
        # a result lost with its worker meanwhile is recomputed by the scheduler: gather waits
        for batch in client.gather(finished) if finished else ():
            for r in batch:
                receipts.append(r)
                if on_receipt:
                    on_receipt(r)
        for fut in failed:
            exc = fut.exception() if fut.status == "error" else None
            msg = " ".join(f"{type(exc).__name__}: {exc}".split()) if exc is not None else f"task {fut.status}"
            if msg.startswith("TaskFailed: "):
                msg = msg[len("TaskFailed: "):]
            origin = first_error.setdefault(msg, fut.key)
            failures[fut.key] = msg if origin == fut.key else f"not run: depends on failed {origin}"
            if on_failure:
                on_failure(fut.key, failures[fut.key])
    return receipts, failures
