"""The reference executor: run a :class:`~schlieren.workers.plan.Plan` in a plain loop.

Tasks run in plan order (stage table order, then index order), which respects every
declared dependency. A task that fails is recorded and everything that depends on it is
skipped; independent work goes on, so nothing that can be computed is lost.
"""

from __future__ import annotations

import logging
from typing import Callable

from schlieren.workers import interrupts
from schlieren.workers.kernel_threads import single_threaded_kernels
from schlieren.workers.plan import Plan
from schlieren.workers.tasks import TaskFailed, flush_writes, run_tasks

log = logging.getLogger(__name__)

__all__ = ["run_serial"]


def run_serial(store_path: str, plan: Plan, *, on_receipt: Callable[[dict], None] | None = None,
               on_failure: Callable[[str, str], None] | None = None) -> tuple[list[dict], dict[str, str]]:
    """Execute every task of ``plan`` in this process.

    Returns
    -------
    receipts : list of dict
    failures : dict
        Task key -> one-line error, for failed tasks and (``"upstream failed"``) tasks
        skipped because something they depend on failed.
    """
    receipts: list[dict] = []
    failures: dict[str, str] = {}
    with single_threaded_kernels():
        _loop(store_path, plan, receipts, failures, on_receipt, on_failure)
    return receipts, failures


def _loop(store_path, plan, receipts, failures, on_receipt, on_failure) -> None:
    try:
        _tasks(store_path, plan, receipts, failures, on_receipt, on_failure)
    finally:
        if plan.tasks:
            try:  # object stores: the writes still in flight (later tasks read them from memory)
                flush_writes(store_path, plan.token)
            except TaskFailed as exc:
                failures["store-writes"] = str(exc)
                if on_failure:
                    on_failure("store-writes", str(exc))


def _tasks(store_path, plan, receipts, failures, on_receipt, on_failure) -> None:
    for task in plan.tasks:
        interrupts.check()  # a Ctrl-C that was dropped on its way (workers/interrupts.py)
        bad = [d for d in task.deps if d in failures]
        if bad:
            failures[task.key] = f"not run: depends on failed {bad[0]}"
            if on_failure:
                on_failure(task.key, failures[task.key])
            continue
        try:
            got = run_tasks(store_path, task.stage, task.indices, run_token=plan.token, flush=False)
        except TaskFailed as exc:
            failures[task.key] = str(exc)
            if on_failure:
                on_failure(task.key, str(exc))
            continue
        for r in got:
            receipts.append(r)
            if on_receipt:
                on_receipt(r)
