"""The local mode: a ``LocalCluster`` of worker processes on ``127.0.0.1`` only (scheduler,
workers, nannies, dashboards), with the ``TOMO`` resource and the thread caps, optionally
talking ``tls://`` with the certificates of ``schlieren tls init``
(DASK-ZARR.md recommendation 8).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import warnings
from collections.abc import Iterator
from typing import Any

from distributed import Client

from schlieren.workers.cluster.dashboard import loopback_dashboard_address
from schlieren.workers.cluster.interrupts import LocalInterrupts
from schlieren.workers.cluster.options import ClusterInfo, ClusterOptions
from schlieren.workers.cluster.scheduler import prepare_client
from schlieren.workers.cluster.settings import THREAD_ENV, TOMO
from schlieren.workers.security import cluster_security

log = logging.getLogger(__name__)

_PORT_IN_USE = r"Port \d+ is already in use"


def _start_local_cluster(opts: ClusterOptions, n_workers: int) -> Any:
    """The ``LocalCluster`` of ``opts``, started; a taken dashboard port is logged, not warned."""
    from distributed import LocalCluster

    kwargs: dict[str, Any] = {}
    if opts.tls_dir:
        kwargs["security"] = cluster_security(opts.tls_dir)
        kwargs["protocol"] = "tls://"
    elif opts.tls_cert:
        raise ValueError("a local TLS cluster needs a certificate directory (--tls DIR) with scheduler, worker and client certificates")
    with warnings.catch_warnings(record=True) as caught:
        # a dashboard port already taken (another run, a notebook's cluster) is not an error:
        # distributed picks a free one and says so as a multi-line UserWarning on stderr;
        # the run reports the dashboard it got ("dashboard: ..." and the log line below)
        warnings.filterwarnings("always", message=_PORT_IN_USE, category=UserWarning)
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=opts.threads_per_worker,
            processes=True,
            host="127.0.0.1",
            dashboard_address=loopback_dashboard_address(opts.dashboard_address),
            memory_limit=opts.memory_limit,
            resources={TOMO: opts.tomo_slots},
            local_directory=opts.local_directory,
            silence_logs=logging.WARNING,
            **kwargs,
        )
    for w in caught:
        if re.search(_PORT_IN_USE, str(w.message)):
            log.info("dashboard port of %s already in use; the scheduler chose another", opts.dashboard_address)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return cluster


@contextlib.contextmanager
def local_client(opts: ClusterOptions) -> Iterator[tuple[Client, ClusterInfo]]:
    """Start the local cluster of ``opts`` and yield ``(client, info)``; close both on exit."""
    n_workers = opts.workers or max(1, os.cpu_count() or 1)
    # the nannies run in this process and export pre-spawn-environ into os.environ before
    # spawning each worker; put this process's own environment back when done
    saved_env = {k: os.environ.get(k) for k in THREAD_ENV}
    cluster = _start_local_cluster(opts, n_workers)
    try:
        client = Client(cluster, set_as_default=True)
        try:
            client.wait_for_workers(n_workers, timeout=opts.connect_timeout)
            client.register_plugin(LocalInterrupts())
            info = prepare_client(client, opts, "local")
            log.info("local cluster with %d worker(s), dashboard %s", info.n_workers, info.dashboard_link)
            yield client, info
        finally:
            client.close()
    finally:
        cluster.close()
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
