"""The entry points: a client on the cluster a run asked for.

:func:`open_client` starts or reaches the cluster of a
:class:`~schlieren.workers.cluster.options.ClusterOptions` (local mode, or a running
scheduler); :func:`make_batch_cluster` creates a batch system's cluster (SLURM / PBS
through dask-jobqueue, Kubernetes through the Dask operator) and :func:`connect` puts a
client on it; :func:`adopt_client` prepares a client the user made. Every one registers
the worker setup plugin and checks versions.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from typing import Any

import dask
import dask.config
from distributed import Client
from distributed.security import Security

from schlieren.workers.cluster.jobqueue import scaled_jobqueue_cluster
from schlieren.workers.cluster.jobwatch import ClusterStalled, WatchedJobs
from schlieren.workers.cluster.kubernetes import kube_cluster
from schlieren.workers.cluster.local import local_client
from schlieren.workers.cluster.options import BATCH_KINDS, ClusterInfo, ClusterOptions, schlieren_section
from schlieren.workers.cluster.scheduler import prepare_client, scheduler_client
from schlieren.workers.cluster.settings import dask_settings
from schlieren.workers.cluster.worker_setup import TomoResource


@contextlib.contextmanager
def open_client(opts: ClusterOptions) -> Iterator[tuple[Client, ClusterInfo]]:
    """Start or connect to the cluster described by ``opts``; yield ``(client, info)``.

    Local mode starts ``LocalCluster(processes=True, host="127.0.0.1", ...)`` with the
    ``TOMO`` resource and thread caps; scheduler mode connects to ``opts.scheduler``
    (with mutual TLS when configured) and waits up to ``connect_timeout`` for a worker.
    Both register :class:`SchlierenWorkerSetup` and check versions. The Dask settings
    of :data:`DASK_SETTINGS` are active for the lifetime of the block (they also reach
    replacement workers started by the nannies). Everything started here is closed on
    exit.
    """
    with dask.config.set(dask_settings()):
        if opts.scheduler:
            with scheduler_client(opts) as pair:
                yield pair
        else:
            with local_client(opts) as pair:
                yield pair


@contextlib.contextmanager
def connect(cluster: Any, opts: ClusterOptions | None = None, *, mode: str = "batch",
            security: Security | None = None, wait_workers: int = 0,
            timeout: float | None = None) -> Iterator[tuple[Client, ClusterInfo]]:
    """A client on an already created cluster object (jobqueue, Kubernetes): yield ``(client, info)``.

    Registers :class:`SchlierenWorkerSetup` and checks versions like :func:`open_client`;
    waits for ``wait_workers`` workers first (batch jobs may queue: ``timeout`` None waits
    as long as it takes; past it :class:`ClusterStalled` says how many came and what the
    jobs do). Closes the client, not the cluster.
    """
    opts = opts or ClusterOptions()
    client = Client(cluster, security=security, set_as_default=True)
    try:
        if wait_workers:
            try:
                client.wait_for_workers(wait_workers, timeout=timeout)
            except TimeoutError:  # distributed's WorkerStartTimeoutError: "1 (120.0)" as text
                raise ClusterStalled(_no_workers_yet(cluster, client, wait_workers, timeout)) from None
        info = prepare_client(client, opts, mode)
        yield client, info
    finally:
        client.close()


def _no_workers_yet(cluster: Any, client: Client, wanted: int, timeout: float | None) -> str:
    """One line for a first wait that timed out: how many workers came, what the jobs do."""
    got = len(client.scheduler_info(n_workers=-1).get("workers", {}))
    jobs = ""
    if isinstance(cluster, WatchedJobs):
        with contextlib.suppress(Exception):
            jobs = f": {cluster.sync(cluster.jobs_summary_now)}"
    return f"{got} of {wanted} worker(s) joined within {timeout:g} s (schlieren.wait-timeout){jobs}"


def make_batch_cluster(kind: str, config: Mapping[str, Any]) -> Any:
    """Create (and scale) the cluster of a batch system from a submit config.

    * ``slurm`` / ``pbs``: ``dask_jobqueue.SLURMCluster`` / ``PBSCluster`` with
      :func:`jobqueue_kwargs`; the scheduler runs in this process (on the login node);
      ``scale`` jobs are submitted, or with ``adapt`` between its minimum and maximum.
    * ``kubernetes``: ``dask_kubernetes.operator.KubeCluster`` with the
      :func:`daskcluster_manifest` resource under a name unique to this call
      (:func:`unique_cluster_config`), created only (never connected to a leftover) and
      deleted when the cluster object closes; needs the Dask operator installed in the
      Kubernetes cluster and the ``dask-kubernetes`` package here. The operator's client
      side speaks plain ``tcp://`` to the scheduler, so a ``tls-secret`` manifest is meant
      for ``kubectl apply`` + ``schlieren run --scheduler tls://...`` instead (see
      ``deploy/GUIDE.md``); with it this function refuses.

    The Dask settings of :data:`DASK_SETTINGS` (plus ``schlieren.dask``) are applied
    while the cluster object is created, so the in-process scheduler uses them.
    """
    if kind not in BATCH_KINDS:
        raise ValueError(f"unknown cluster kind {kind!r}; expected one of {', '.join(BATCH_KINDS)}")
    sec = schlieren_section(config)
    with dask.config.set(dask_settings(sec["dask"])):
        if kind == "kubernetes":
            return kube_cluster(config)
        return scaled_jobqueue_cluster(kind, config)


def adopt_client(client: Client, opts: ClusterOptions | None = None) -> ClusterInfo:
    """Prepare a client the user made (``schlieren.run(client=...)``) like our own clusters.

    Registers :class:`SchlierenWorkerSetup` (thread caps, zarr concurrency, logging) and
    :class:`TomoResource` on every current and future worker, then checks versions.
    """
    client.register_plugin(TomoResource(1))
    return prepare_client(client, opts or ClusterOptions(), "client")
