"""Worker bootstrap in one place (DASK-ZARR.md recommendation 7): the worker plugins every
entry point registers, and a report of the thread settings a worker process ended up with.

* :class:`SchlierenWorkerSetup` caps BLAS/OpenMP/OpenCV/numba threads, sets zarr's
  concurrency and JSON logging in every worker process (the caps that matter at library
  load time are set earlier, by the nanny's ``pre-spawn-environ``, see
  :data:`~schlieren.workers.cluster.settings.DASK_SETTINGS`);
* :class:`TomoResource` gives a user's workers the ``TOMO`` resource that tomography tasks
  request.
"""

from __future__ import annotations

import contextlib
import logging
import os
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
      stderr is the user's console: one format there, the CLI's).

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
        logging.getLogger(__name__).debug("worker %s set up: %s thread(s)", getattr(worker, "address", "?"), n)


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
