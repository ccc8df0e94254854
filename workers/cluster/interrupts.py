"""Ctrl-C on a local cluster: the worker processes leave it to the client.

The client side of a Ctrl-C (a run stopped at the next task boundary, with one line on
the terminal) is :mod:`schlieren.workers.interrupts`; this module holds the worker side,
:class:`LocalInterrupts`, and the log filters that keep the cluster's closing errors out
of the terminal.
"""

from __future__ import annotations

import logging
import multiprocessing
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from schlieren.workers.cluster.worker_setup import exit_without_teardown


class _CancelledOnClose(logging.Filter):
    """Drops distributed's "Async instruction for <Task cancelled ...>" warnings: tasks the
    worker was running when the client closed the cluster (Ctrl-C); nothing is lost."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Task cancelled" not in record.getMessage()


class _AfterCtrlC(logging.Filter):
    """After a Ctrl-C reached this worker: drops the errors of the cluster closing under it,
    a peer gone mid-transfer, from either end: the sender's "failed during get data" and the
    receiver's "Worker stream died during communication" (with its traceback; seen once in
    a fresh-clone CI run), and a batched stream's "Batched Comm Closed" (INFO, with a
    traceback). Before it nothing is dropped."""

    interrupted = False
    MESSAGES = ("failed during get data", "Worker stream died during communication")
    #: logged at INFO with the CommClosedError traceback by a batched stream the closing cut
    CLOSED = "Batched Comm Closed"

    def filter(self, record: logging.LogRecord) -> bool:
        if not _AfterCtrlC.interrupted:
            return True
        msg = record.getMessage()
        if self.CLOSED in msg:
            return False
        return not (record.levelno >= logging.WARNING and any(m in msg for m in self.MESSAGES))


def _note_ctrl_c(signum, frame) -> None:  # a worker's SIGINT: the client stops the run
    _AfterCtrlC.interrupted = True


class LocalInterrupts(WorkerPlugin):
    """Workers of a local cluster leave Ctrl-C to the client process.

    A terminal's Ctrl-C reaches every process of its foreground group, the worker
    processes of a local cluster included: each printed a KeyboardInterrupt traceback
    before the client's one-line "interrupted" message. The client closes the cluster
    (which stops the workers) and keeps every completed chunk; the workers ignore SIGINT
    (they only note it, to keep the cluster's closing errors out of the terminal). Asked
    to close after a Ctrl-C, a worker process ends at once: its nanny would otherwise wait
    for the task it runs and, past 4 s, kill it with "Worker process still alive after 4.0
    seconds, killing" (that task's chunks and marker are not written; the rerun computes it).
    Registered only on local clusters (a worker started by hand keeps its Ctrl-C).
    """

    idempotent = True
    name = "schlieren-local-interrupts"

    def setup(self, worker: Any) -> None:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, _note_ctrl_c)  # ignored, but remembered for _AfterCtrlC
        logging.getLogger("distributed.worker.state_machine").addFilter(_CancelledOnClose())
        after = _AfterCtrlC()
        for name in ("distributed.worker", "distributed.batched"):  # the batched stream's "Batched Comm Closed"
            logging.getLogger(name).addFilter(after)

    def teardown(self, worker: Any) -> None:
        if _AfterCtrlC.interrupted and getattr(worker, "nanny", None) and multiprocessing.parent_process():
            exit_without_teardown()
