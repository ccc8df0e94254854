"""Worker bootstrap in one place (DASK-ZARR.md recommendation 7): the worker plugins every
entry point registers, and a report of the thread settings a worker process ended up with.

* :class:`SchlierenWorkerSetup` caps BLAS/OpenMP/OpenCV/numba threads, sets zarr's
  concurrency and JSON logging in every worker process (the caps that matter at library
  load time are set earlier, by the nanny's ``pre-spawn-environ``, see
  :data:`~schlieren.workers.cluster.settings.DASK_SETTINGS`);
* :class:`TomoResource` gives a user's workers the ``TOMO`` resource that tomography tasks
  request;
* a worker process a nanny started ends as soon as its worker closed
  (:func:`exit_without_teardown`), well within the nanny's 4 s.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import functools
import logging
import multiprocessing
import os
import sys
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

from distributed import Client
from distributed.diagnostics.plugin import WorkerPlugin

from schlieren.workers.cluster.options import ClusterOptions
from schlieren.workers.cluster.settings import THREAD_ENV, TOMO
from schlieren.workers.monitoring import configure_worker_logging


class SchlierenWorkerSetup(WorkerPlugin):
    """Per-worker-process bootstrap, registered by every entry point.

    On each worker (and on every replacement worker the nanny restarts):

    * ``cv2.setNumThreads(threads)``; ``threadpoolctl.threadpool_limits(threads)`` when
      threadpoolctl is installed (BLAS libraries already loaded); the thread environment
      variables are set for any child process (the ones that matter at library load time
      are set earlier, by the nanny's ``pre-spawn-environ``);
    * zarr's ``async.concurrency`` and ``threading.max_workers`` (per process, so
      ``workers x concurrency`` stays bounded);
    * the ``schlieren`` logger writes JSON lines (:class:`~schlieren.workers.monitoring.JsonFormatter`)
      to ``log_dir/<worker name>.jsonl``, or plain lines to stderr (a local cluster's
      stderr is the user's console: one format there, the CLI's);
    * ``worker.close`` runs once (:func:`close_once`); when the worker closes, a process of
      its own ends at once (:func:`exit_without_teardown`).

    Registering it again is a no-op (``idempotent = True``).
    """

    idempotent = True
    name = "schlieren-worker-setup"

    def __init__(
        self,
        *,
        threads: int = 1,
        zarr_concurrency: int = 4,
        log_level: str | int = "INFO",
        log_dir: str | None = None,
    ) -> None:
        self.threads = int(threads)
        self.zarr_concurrency = int(zarr_concurrency)
        self.log_level = log_level
        self.log_dir = log_dir

    def setup(self, worker: Any) -> None:
        n = str(self.threads)
        for k, v in THREAD_ENV.items():
            os.environ[k] = n if v == "1" else v  # thread counts follow `threads`; policies as set
        try:
            import cv2

            cv2.setNumThreads(self.threads)
        except ImportError:  # pragma: no cover - cv2 is a hard dependency
            pass
        with contextlib.suppress(ImportError):
            import threadpoolctl

            threadpoolctl.threadpool_limits(self.threads)
        try:
            import zarr

            zarr.config.set(
                {"async.concurrency": self.zarr_concurrency, "threading.max_workers": self.zarr_concurrency}
            )
        except ImportError:  # pragma: no cover - zarr is a hard dependency
            pass
        if self.log_dir:
            name = str(getattr(worker, "name", None) or getattr(worker, "address", "worker"))
            safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
            configure_worker_logging("schlieren", level=self.log_level, path=Path(self.log_dir) / f"{safe}.jsonl")
        else:
            configure_worker_logging("schlieren", level=self.log_level)
        close_once(worker)
        logging.getLogger("distributed.worker").addFilter(_CLOSING_TRANSITION)
        if getattr(worker, "nanny", None) and multiprocessing.parent_process() is not None:  # one worker here
            _WhileLeaving.worker = weakref.ref(worker)
            for name in _WhileLeaving.LOGGERS:
                logging.getLogger(name).addFilter(_WHILE_LEAVING)
        logging.getLogger(__name__).debug("worker %s set up: %s thread(s)", getattr(worker, "address", "?"), n)

    def teardown(self, worker: Any) -> None:
        """The worker closes: its process, if a nanny started it for this worker alone,
        ends as soon as the worker has closed (see :func:`exit_without_teardown`)."""
        if getattr(worker, "nanny", None) and multiprocessing.parent_process() is not None:
            atexit.register(exit_without_teardown)  # should the task below not run
            with contextlib.suppress(RuntimeError):  # RuntimeError: no running loop
                self._exit_task = asyncio.get_running_loop().create_task(_exit_once_closed(worker))


class _ClosingTransition(logging.Filter):
    """Drops distributed's "Invalid Worker.status transition: Status.closing -> ..." error:
    the scheduler's "closing gracefully" reaching a worker that already closes (workers
    retiring together at their ``--lifetime``); the worker closes either way."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Invalid Worker.status transition: Status.closing ->")


_CLOSING_TRANSITION = _ClosingTransition()  # one instance: addFilter ignores a filter it has


class _WhileLeaving(logging.Filter):
    """While this process's worker is leaving (retiring at its ``--lifetime``, closing),
    drops the errors of connections cut under it, each with a traceback in the job log: a
    data transfer its peer, leaving at the same moment, cut short ("failed during get data",
    "Lost connection to ...": the workers of one batch job retire together), a heartbeat in
    flight when its own close shut the connection. The scheduler moves the data elsewhere;
    nothing is lost. Before the worker leaves, nothing is dropped."""

    LOGGERS = ("distributed.worker", "distributed.core")
    MESSAGES = ("failed during get data", "Lost connection to", "Worker stream died during communication",
                "Failed to communicate with scheduler during heartbeat")
    worker: Callable[[], Any] = staticmethod(lambda: None)

    def filter(self, record: logging.LogRecord) -> bool:
        w = _WhileLeaving.worker()
        status = getattr(getattr(w, "status", None), "name", "")
        if status not in ("closing_gracefully", "closing", "closed"):
            return True
        msg = record.getMessage()
        return not any(m in msg for m in self.MESSAGES)


_WHILE_LEAVING = _WhileLeaving()


def close_once(worker: Any) -> None:
    """Make ``worker.close`` run once: a second call waits for the first to end.

    distributed closes a worker a second time when its workers retire together (``--lifetime``
    on a job's worker processes): the scheduler aborts a retirement whose data has nowhere
    to go and sets the worker "running" again while it already closes, and the end of its
    scheduler connection then starts another close, which fails on the nanny's connection
    pool that the first one closed ("ConnectionPool is closed" and a traceback in the job
    log). Nothing is lost either way.
    """
    close = getattr(worker, "close", None)
    if close is None or getattr(close, "_schlieren_once", False):  # None: not a distributed Worker
        return
    started = False

    @functools.wraps(close)
    async def once(*args: Any, **kwargs: Any) -> Any:
        nonlocal started
        if started:
            await worker.finished()
            return None
        started = True
        return await close(*args, **kwargs)

    once._schlieren_once = True  # type: ignore[attr-defined]
    worker.close = once
    for table in (getattr(worker, "handlers", {}), getattr(worker, "stream_handlers", {})):
        for op in ("close", "terminate"):
            if table.get(op) == close:
                table[op] = once


async def _exit_once_closed(worker: Any) -> None:
    await worker.finished()
    exit_without_teardown()


def exit_without_teardown() -> None:
    """End a closed worker's process at once: flush the logs and streams, then ``os._exit(0)``.

    Called in a worker process a nanny started, once its worker has closed (and at exit,
    should that not happen first). Two things went wrong after the worker closed:

    * distributed's process wrapper waited 2 s for a stop message that a worker closing
      by itself (``--lifetime``, the scheduler's close) never gets, then closed the stop
      queue under the thread reading it, which logged "Worker process died unexpectedly"
      with a traceback into the job logs;
    * tearing the interpreter down (numba's and llvmlite's compiled code, scipy, OpenCV,
      zarr: 0.3-0.6 s of CPU measured here) took more than the nanny's 4 s on a loaded
      machine, and the nanny killed the process with "Worker process still alive after
      4.0 seconds, killing" at every normal shutdown.

    The worker has closed by then (its tasks' chunks and markers are written, its folder
    released) and nothing it holds needs Python's finalizers; multiprocessing's fork
    children end with ``os._exit`` the same way.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(0)


def worker_thread_report() -> dict[str, Any]:
    """Thread settings as seen inside the calling process (run it on workers with ``client.run``)."""
    import cv2

    out: dict[str, Any] = {"cv2_threads": cv2.getNumThreads(), "pid": os.getpid()}
    out["env"] = {k: os.environ.get(k) for k in THREAD_ENV}
    with contextlib.suppress(ImportError):
        import threadpoolctl

        out["threadpools"] = [
            {"api": i.get("internal_api"), "num_threads": i.get("num_threads")} for i in threadpoolctl.threadpool_info()
        ]
    return out


def register_worker_setup(client: Client, opts: ClusterOptions | None = None) -> None:
    """Register :class:`SchlierenWorkerSetup` on all current and future workers."""
    opts = opts or ClusterOptions()
    level = opts.worker_log_level or ("INFO" if opts.worker_log_dir else "WARNING")
    client.register_plugin(SchlierenWorkerSetup(threads=1, log_level=level, log_dir=opts.worker_log_dir))


class TomoResource(WorkerPlugin):
    """Give a worker the ``TOMO`` resource if it was started without one.

    Tomography tasks request ``resources={"TOMO": 1}``; on workers that do not advertise
    it they would wait forever. Registered by :func:`~schlieren.workers.cluster.adopt_client`
    on a user's cluster.
    """

    idempotent = True
    name = "schlieren-tomo-resource"

    def __init__(self, slots: float = 1) -> None:
        self.slots = float(slots)

    def setup(self, worker: Any):
        if TOMO in worker.state.total_resources:
            return None
        return worker.set_resources(**{TOMO: self.slots})
