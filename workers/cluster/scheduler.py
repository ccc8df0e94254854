"""Clients on a scheduler: connecting to a running one (``--scheduler``, with mutual TLS when
configured), the version check, and the preparation every client gets once connected
(worker setup plugin, versions, a :class:`~schlieren.workers.cluster.options.ClusterInfo`).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

from distributed import Client
from distributed.security import Security

from schlieren.workers.cluster.dashboard import dashboard_link
from schlieren.workers.cluster.options import ClusterInfo, ClusterOptions
from schlieren.workers.cluster.settings import TOMO
from schlieren.workers.cluster.worker_setup import register_worker_setup
from schlieren.workers.security import make_security

log = logging.getLogger(__name__)

_VERSION_PACKAGES = ("schlieren", "numpy", "zarr", "opencv-contrib-python-headless", "scipy")


class VersionMismatchError(RuntimeError):
    """Client, scheduler and workers run different versions of a package that matters."""


def check_versions(client: Client, packages: tuple[str, ...] = _VERSION_PACKAGES) -> dict:
    """Compare package versions of the client, the scheduler and every worker.

    Raises ``VersionMismatchError`` naming the first package whose version differs
    between the client and a worker (our own packages, numpy, zarr, OpenCV, scipy), or
    distributed's own required-package mismatch (``Client.get_versions(check=True)``).

    Returns
    -------
    dict
        ``{"client": ..., "scheduler": ..., "workers": {address: ...}}``.
    """
    try:
        versions = client.get_versions(check=True, packages=list(packages))
    except ValueError as exc:
        raise VersionMismatchError(" ".join(str(exc).split())) from exc
    mine = versions["client"]["packages"]
    for addr, info in (versions.get("workers") or {}).items():
        if not isinstance(info, dict) or "packages" not in info:
            continue
        for pkg in packages:
            theirs = info["packages"].get(pkg)
            if mine.get(pkg) != theirs:
                raise VersionMismatchError(
                    f"package {pkg}: client has {mine.get(pkg)}, worker {addr} has {theirs}; install the same versions"
                )
    return versions


def _summarise(client: Client, mode: str, versions: dict) -> ClusterInfo:
    info = client.scheduler_info(n_workers=-1)
    workers = info.get("workers", {})
    slots = sum(float(w.get("resources", {}).get(TOMO, 0)) for w in workers.values())
    return ClusterInfo(
        mode=mode,
        scheduler_address=info.get("address", client.scheduler.address),
        dashboard_link=dashboard_link(client),
        n_workers=len(workers),
        tomo_slots=slots,
        versions=versions,
    )


def prepare_client(client: Client, opts: ClusterOptions, mode: str) -> ClusterInfo:
    """Register the worker setup plugin, check versions, and describe the cluster.

    What every client gets, whatever started its cluster (``mode`` names it in the
    returned :class:`~schlieren.workers.cluster.options.ClusterInfo`).
    """
    register_worker_setup(client, opts)
    versions = check_versions(client)
    info = _summarise(client, mode, versions)
    if info.n_workers and not info.tomo_slots:
        log.warning(
            "no worker advertises the %s resource: tomography tasks will wait forever; "
            "start workers with `--resources %s=1`",
            TOMO,
            TOMO,
        )
    return info


def connect_error(opts: ClusterOptions, exc: BaseException) -> str:
    """One line for a cluster that could not be started or reached, with the likely fix."""
    reason = " ".join(str(exc).split()) or type(exc).__name__
    if not opts.scheduler:
        return f"cannot start the local cluster: {reason}"
    address = opts.scheduler
    tls = address.startswith("tls://")
    low = reason.lower()
    if isinstance(exc, ValueError):
        return reason
    if tls and ("certificate" in low or "ssl" in low or "handshake" in low):
        hint = ("the certificates in --tls are not from this cluster's CA (or were refused): use the directory "
                "`schlieren tls init` made for it")
    elif tls:
        hint = "check the address and that --tls holds this cluster's ca.pem, client.pem and client-key.pem"
    else:
        hint = ("if the scheduler uses TLS, give its tls:// address and --tls DIR; otherwise check the "
                "address and that the scheduler runs")
    return f"cannot connect to the scheduler {address}: {reason} ({hint})"


def _client_security(opts: ClusterOptions) -> Security | None:
    """The client's ``Security`` for ``opts.scheduler``: from ``opts``' TLS files, else from
    the Dask config for a ``tls://`` address, else None (plain ``tcp://``)."""
    address = opts.scheduler or ""
    scheme = address.split("://", 1)[0] if "://" in address else "tcp"
    files = opts.client_tls_files()
    if files is not None:
        if scheme != "tls":
            raise ValueError(f"TLS certificates were given but the scheduler address {address!r} is not tls://")
        return make_security(files, "client")
    if scheme != "tls":
        return None
    # fall back to distributed.comm.tls.* from the Dask config (DASK_CONFIG)
    security = Security()
    if not security.get_tls_config_for_role("client").get("cert"):
        raise ValueError(
            f"scheduler {address} uses TLS: give the certificate directory (--tls DIR, made by `schlieren tls init DIR`)"
        )
    return security


@contextlib.contextmanager
def scheduler_client(opts: ClusterOptions) -> Iterator[tuple[Client, ClusterInfo]]:
    """A client on the running scheduler ``opts.scheduler``; waits up to ``connect_timeout``
    for a first worker. Closes the client (not the cluster) on exit."""
    client = Client(opts.scheduler, security=_client_security(opts), timeout=opts.connect_timeout, set_as_default=True)
    try:
        client.wait_for_workers(1, timeout=opts.connect_timeout)
        info = prepare_client(client, opts, "scheduler")
        log.info("connected to scheduler %s with %d worker(s)", info.scheduler_address, info.n_workers)
        yield client, info
    finally:
        client.close()
