"""What every process of a schlieren cluster runs with: the ``TOMO`` resource name, the
thread caps and allocator settings of worker processes, and the Dask configuration.

Every cluster mode (local, running scheduler, SLURM/PBS, Kubernetes) reads them from here,
and ``deploy/`` repeats them for the processes it starts itself (``deploy/config/bos.yaml``,
the Containerfile's environment, the job scripts' exports; tests compare them).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

#: Name of the worker resource that tomography tasks request (``resources={TOMO: 1}``).
TOMO = "TOMO"

#: Thread caps set in every worker process before it starts. The nanny applies OMP, MKL
#: and OpenBLAS by default but not OpenCV (DASK-ZARR.md pitfall 9).
THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
    "NUMBA_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    # numba's OpenMP pool must not spin-wait between kernels: on a loaded node the default
    # active policy slows the fused tomography kernels badly (docs/tuning.md, "Cluster settings")
    "OMP_WAIT_POLICY": "passive",
}

#: glibc allocator settings for worker processes. Distributed's default
#: ``MALLOC_TRIM_THRESHOLD_=65536`` also freezes glibc's dynamic mmap threshold, so every
#: array over 128 KiB is mmapped and page-faulted afresh, which made the whole pipeline
#: markedly slower in a worker than in the serial loop. Large arrays from the heap (mmap
#: threshold at glibc's 32 MiB maximum) and trimming only past 256 MiB restore the serial
#: speed (docs/tuning.md, "Cluster settings").
MALLOC_ENV: dict[str, str] = {
    "MALLOC_TRIM_THRESHOLD_": "268435456",
    "MALLOC_MMAP_THRESHOLD_": "33554432",
}

#: Dask settings every schlieren cluster runs with (also in ``deploy/config/bos.yaml``,
#: which must stay equal to this; a test checks it). Scheduler-side keys only take effect
#: where the scheduler runs: here for local and batch clusters, through ``DASK_CONFIG``
#: for a separately started scheduler.
DASK_SETTINGS: dict[str, Any] = {
    # a tomography solve can take minutes: do not count its memory as "old" too early
    "distributed.worker.memory.recent-to-old-time": "120s",
    # a task whose worker died this many times is declared bad (KilledWorker)
    "distributed.scheduler.allowed-failures": 3,
    # queue root tasks on the scheduler, ceil(1.5 x threads) per worker: a killed worker
    # loses little, and a worker always holds its next task (at 1.0 a single-threaded
    # worker idles for a scheduler round trip after each small task; docs/tuning.md,
    # "Cluster settings")
    "distributed.scheduler.worker-saturation": 1.5,
    "distributed.dashboard.link": "{scheme}://{host}:{port}/status",
    # Monitoring cadence. Every node's event loop wakes for these and takes its
    # process's GIL; on a machine whose cores all run tasks, that CPU comes out of the
    # tasks. Dask's defaults (profile sample every 10 ms, tick every 20 ms, system
    # monitor every 500 ms) wake far more often than ours (their CPU cost: docs/tuning.md,
    # "Cluster settings"). The
    # dashboard keeps every page: our tasks run 0.1 s to minutes, so a 50 ms profile
    # sample still lands several times in each, and the system page updates every second.
    "distributed.worker.profile.interval": "50ms",
    "distributed.admin.tick.interval": "100ms",
    "distributed.admin.system-monitor.interval": "1s",
    **{f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in THREAD_ENV.items()},
    **{f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in MALLOC_ENV.items()},
}


def dask_settings(extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """:data:`DASK_SETTINGS` merged with ``extra`` (dotted keys), for ``dask.config.set``."""
    out = dict(DASK_SETTINGS)
    if extra:
        out.update(extra)
    return out
