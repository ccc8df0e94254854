"""Where the Dask workers come from: a local process cluster, an existing scheduler, or a
batch system (SLURM / PBS through dask-jobqueue, Kubernetes through the Dask operator).

Every entry point obtains its client from :func:`open_client` (or, for batch clusters,
:func:`make_batch_cluster` + :func:`connect`), which

* keeps a local cluster on ``127.0.0.1`` only (scheduler, workers, nannies, dashboards);
* caps BLAS/OpenMP/OpenCV/numba threads in every worker process, before it starts
  (``distributed.nanny.pre-spawn-environ``) and again inside it (:class:`SchlierenWorkerSetup`,
  a worker plugin that also sets ``cv2.setNumThreads(1)``, zarr's async concurrency and
  JSON logging);
* advertises the ``TOMO`` resource on every worker (``tomo_slots`` per worker), so that a
  tomography task submitted with ``resources={"TOMO": 1}`` never runs more copies on a
  worker than fit in its memory;
* checks that client, scheduler and workers run the same versions.

One module per mode, as distributed's ``deploy/``:

==============  ===========================================================================
settings        ``TOMO``, thread caps, allocator settings, the Dask config of every cluster
options         :class:`ClusterOptions`, :class:`ClusterInfo`, a submit config's ``schlieren:``
worker_setup    the worker plugins (:class:`SchlierenWorkerSetup`, :class:`TomoResource`)
dashboard       the dashboard link and line (the port taken, if any); a loopback address
scheduler       connecting to a running scheduler; the version check; preparing a client
local           the local process cluster
jobqueue        SLURM / PBS (dask-jobqueue): cluster arguments, job script, walltime checks
jobwatch        the batch jobs: the ones that end replaced; one line when none can run
kubernetes      the ``DaskCluster`` manifest (from dask-kubernetes' template) and KubeCluster
interrupts      Ctrl-C on a local cluster's workers
client          the entry points: :func:`open_client`, :func:`connect`, :func:`make_batch_cluster`
==============  ===========================================================================
"""

from __future__ import annotations

from schlieren.workers.cluster.client import adopt_client, connect, make_batch_cluster, open_client
from schlieren.workers.cluster.dashboard import (
    DEFAULT_DASHBOARD,
    dashboard_line,
    dashboard_link,
    loopback_dashboard_address,
)
from schlieren.workers.cluster.interrupts import LocalInterrupts
from schlieren.workers.cluster.jobqueue import job_script, jobqueue_cluster, jobqueue_kwargs
from schlieren.workers.cluster.jobwatch import ClusterStalled, WatchedJobs, stop_on_stall
from schlieren.workers.cluster.kubernetes import (
    IMAGE_UID,
    TLS_MOUNT,
    daskcluster_manifest,
    unique_cluster_config,
)
from schlieren.workers.cluster.options import BATCH_KINDS, ClusterInfo, ClusterOptions, schlieren_section
from schlieren.workers.cluster.scheduler import VersionMismatchError, check_versions, connect_error
from schlieren.workers.cluster.settings import DASK_SETTINGS, MALLOC_ENV, THREAD_ENV, TOMO, dask_settings
from schlieren.workers.cluster.worker_setup import (
    SchlierenWorkerSetup,
    TomoResource,
    register_worker_setup,
    worker_thread_report,
)

__all__ = [
    "BATCH_KINDS", "DASK_SETTINGS", "DEFAULT_DASHBOARD", "IMAGE_UID", "MALLOC_ENV", "THREAD_ENV", "TLS_MOUNT", "TOMO",
    "ClusterInfo", "ClusterOptions", "ClusterStalled", "LocalInterrupts", "SchlierenWorkerSetup", "TomoResource",
    "VersionMismatchError", "WatchedJobs", "adopt_client", "check_versions", "connect", "connect_error",
    "dashboard_line", "dashboard_link", "dask_settings", "daskcluster_manifest", "job_script", "jobqueue_cluster",
    "jobqueue_kwargs", "loopback_dashboard_address", "make_batch_cluster", "open_client", "register_worker_setup",
    "schlieren_section", "stop_on_stall", "unique_cluster_config", "worker_thread_report",
]
