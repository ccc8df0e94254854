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
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import os
import re
import secrets
import shlex
import socket
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dask
import dask.config
from distributed import Client
from distributed.diagnostics.plugin import WorkerPlugin
from distributed.security import Security

from schlieren.workers.monitoring import configure_json_logging
from schlieren.workers.security import (
    TLSFiles,
    cluster_security,
    make_security,
    tls_files_from_config,
)

log = logging.getLogger(__name__)

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
    # numba's OpenMP pool must not spin-wait between kernels (measured: up to 15x slower
    # fused tomography kernels on a loaded node with the default active policy)
    "OMP_WAIT_POLICY": "passive",
}

#: glibc allocator settings for worker processes. Distributed's default
#: ``MALLOC_TRIM_THRESHOLD_=65536`` also freezes glibc's dynamic mmap threshold, so every
#: array over 128 KiB is mmapped and page-faulted afresh: measured here, it made the
#: whole pipeline 38 % slower in a worker than in the serial loop (12.5 s -> 17.2 s on
#: benchmarks/scaling.py's session). Large arrays from the heap (mmap threshold at glibc's
#: 32 MiB maximum) and trimming only past 256 MiB restore the serial speed (12.5 s).
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
    # worker idled for a scheduler round trip after each of ~700 small tasks: +1.5 s on
    # the 8-camera x 16-frame scaling session, benchmarks/scaling.py)
    "distributed.scheduler.worker-saturation": 1.5,
    "distributed.dashboard.link": "{scheme}://{host}:{port}/status",
    # Monitoring cadence. Every node's event loop wakes for these and takes its
    # process's GIL; on a machine whose cores all run tasks, that CPU comes out of the
    # tasks. Dask's defaults (profile sample every 10 ms, tick every 20 ms, system
    # monitor every 500 ms) cost a 2-worker local cluster 1.8 s of CPU per idle 20 s and
    # about 2.9 s per 15 s run of benchmarks/scaling.py; these cost 0.8 s and 1.8 s. The
    # dashboard keeps every page: our tasks run 0.1 s to minutes, so a 50 ms profile
    # sample still lands several times in each, and the system page updates every second.
    "distributed.worker.profile.interval": "50ms",
    "distributed.admin.tick.interval": "100ms",
    "distributed.admin.system-monitor.interval": "1s",
    **{f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in THREAD_ENV.items()},
    **{f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in MALLOC_ENV.items()},
}

DEFAULT_DASHBOARD = "127.0.0.1:8787"
_LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


# ----------------------------------------------------------------------------------------
# options


@dataclass(frozen=True)
class ClusterOptions:
    """How to obtain the Dask cluster for a run.

    Exactly one of ``workers`` (start a local process cluster) and ``scheduler`` (connect
    to a running scheduler) may be set; with neither, a local cluster with one worker per
    core is started.

    Attributes
    ----------
    workers : int or None
        Number of local worker processes.
    scheduler : str or None
        Address of an existing scheduler, ``tcp://host:port`` or ``tls://host:port``.
    threads_per_worker : int
        Threads per local worker process (1: the kernels are single-threaded).
    memory_limit : str, int or None
        Per-worker memory limit of local workers (``"4GiB"``, bytes, ``"auto"``).
    dashboard_address : str
        ``host:port`` of the local scheduler's dashboard; the host must be a loopback
        address (reach it from elsewhere through an SSH tunnel). A taken port falls back
        to a free one.
    tomo_slots : int
        Value of the ``TOMO`` resource each local worker advertises: how many tomography
        tasks fit in one worker's memory at once.
    tls_dir : str or None
        Directory written by ``schlieren tls init`` (``ca.pem``, ``client.pem``, ...). In
        scheduler mode the client certificate is used; in local mode all three roles and
        the cluster talks ``tls://`` on loopback.
    tls_ca_file, tls_cert, tls_key : str or None
        Explicit client TLS files (scheduler mode); override the ones from ``tls_dir``.
    local_directory : str or None
        Scratch directory of local workers (spill files).
    connect_timeout : float
        Seconds to wait for the scheduler, and in scheduler mode for a first worker.
    worker_log_dir : str or None
        When set, each worker appends its JSON log lines to ``<dir>/<worker name>.jsonl``
        instead of writing them to its stderr.
    worker_log_level : str or None
        Level of the ``schlieren`` logger inside workers; default INFO with a
        ``worker_log_dir``, WARNING otherwise (worker stderr shares the terminal).
    """

    workers: int | None = None
    scheduler: str | None = None
    threads_per_worker: int = 1
    memory_limit: str | int | None = "auto"
    dashboard_address: str = DEFAULT_DASHBOARD
    tomo_slots: int = 1
    tls_dir: str | None = None
    tls_ca_file: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    local_directory: str | None = None
    connect_timeout: float = 60.0
    worker_log_dir: str | None = None
    worker_log_level: str | None = None

    def __post_init__(self) -> None:
        if self.workers is not None and self.scheduler is not None:
            raise ValueError("give either a number of local workers or a scheduler address, not both")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        if self.threads_per_worker < 1:
            raise ValueError(f"threads_per_worker must be at least 1, got {self.threads_per_worker}")
        if self.tomo_slots < 1:
            raise ValueError(f"tomo_slots must be at least 1, got {self.tomo_slots}")
        explicit = [self.tls_ca_file, self.tls_cert, self.tls_key]
        if any(explicit) and not all(explicit) and not self.tls_dir:
            raise ValueError("TLS needs a certificate directory (schlieren tls init DIR) or CA file, certificate and key together")

    @property
    def mode(self) -> str:
        """``"scheduler"`` or ``"local"``."""
        return "scheduler" if self.scheduler else "local"

    @property
    def tls_configured(self) -> bool:
        return bool(self.tls_dir or self.tls_cert)

    def client_tls_files(self) -> TLSFiles | None:
        """The client's TLS files, or None when TLS is not configured."""
        if not self.tls_configured:
            return None
        base = TLSFiles.from_dir(self.tls_dir, "client") if self.tls_dir else None
        return TLSFiles(
            ca_file=Path(self.tls_ca_file) if self.tls_ca_file else base.ca_file,  # type: ignore[union-attr]
            cert=Path(self.tls_cert) if self.tls_cert else base.cert,  # type: ignore[union-attr]
            key=Path(self.tls_key) if self.tls_key else base.key,  # type: ignore[union-attr]
        )


@dataclass(frozen=True)
class ClusterInfo:
    """What :func:`open_client` connected to.

    Attributes
    ----------
    mode : str
        ``"local"``, ``"scheduler"``, ``"slurm"``, ``"pbs"`` or ``"kubernetes"``.
    scheduler_address : str
    dashboard_link : str or None
        URL of the scheduler's dashboard status page, None if it has none.
    n_workers : int
        Workers connected when the client was opened.
    tomo_slots : int
        Sum of the ``TOMO`` resource over those workers.
    versions : dict
        Package versions of client, scheduler and workers (``Client.get_versions``).
    """

    mode: str
    scheduler_address: str
    dashboard_link: str | None
    n_workers: int
    tomo_slots: float
    versions: dict = field(default_factory=dict, repr=False, compare=False)


# ----------------------------------------------------------------------------------------
# worker bootstrap


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
      to stderr or to ``log_dir/<worker name>.jsonl``.

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
            configure_json_logging("schlieren", level=self.log_level, path=Path(self.log_dir) / f"{safe}.jsonl")
        else:
            configure_json_logging("schlieren", level=self.log_level)
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


# ----------------------------------------------------------------------------------------
# clients


def dashboard_link(client: Client) -> str | None:
    """URL of the scheduler dashboard's status page, or None when the scheduler runs none.

    Formatted with the ``distributed.dashboard.link`` template. For a remote scheduler the
    host is the scheduler's own host name: open an SSH tunnel to reach it.
    """
    try:
        services = client.scheduler_info(n_workers=0).get("services", {})
    except TypeError:  # older distributed without n_workers
        services = client.scheduler_info().get("services", {})
    if "dashboard" not in services:
        return None
    return client.dashboard_link


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


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _port_is_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
        return True


def loopback_dashboard_address(address: str | None) -> str:
    """Normalise a dashboard ``host:port`` to a loopback host and a free port.

    ``":8787"`` and ``"8787"`` become ``"127.0.0.1:8787"``; a non-loopback host raises
    ``ValueError`` (the dashboard shows code and data: reach it through an SSH tunnel);
    a taken port is replaced by a free one.
    """
    address = (address or DEFAULT_DASHBOARD).strip()
    if "://" in address:
        address = address.split("://", 1)[1]
    host, sep, port_s = address.rpartition(":")
    if not sep:
        host, port_s = "", address
    host = host.strip("[]") or "127.0.0.1"
    if host not in _LOOPBACK_HOSTS:
        raise ValueError(
            f"the local dashboard binds loopback only, got host {host!r}; use an SSH tunnel to view it remotely"
        )
    if host == "localhost":
        host = "127.0.0.1"
    try:
        port = int(port_s)
    except ValueError as exc:
        raise ValueError(f"bad dashboard address {address!r}: expected HOST:PORT") from exc
    if port == 0 or not _port_is_free(host, port):
        new = _free_port(host)
        if port:
            log.info("dashboard port %d is taken; using %d", port, new)
        port = new
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def dask_settings(extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """:data:`DASK_SETTINGS` merged with ``extra`` (dotted keys), for ``dask.config.set``."""
    out = dict(DASK_SETTINGS)
    if extra:
        out.update(extra)
    return out


def register_worker_setup(client: Client, opts: ClusterOptions | None = None) -> None:
    """Register :class:`SchlierenWorkerSetup` on all current and future workers."""
    opts = opts or ClusterOptions()
    level = opts.worker_log_level or ("INFO" if opts.worker_log_dir else "WARNING")
    client.register_plugin(SchlierenWorkerSetup(threads=1, log_level=level, log_dir=opts.worker_log_dir))


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


def _prepare(client: Client, opts: ClusterOptions, mode: str) -> ClusterInfo:
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
            with _scheduler_client(opts) as pair:
                yield pair
        else:
            with _local_client(opts) as pair:
                yield pair


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


@contextlib.contextmanager
def _scheduler_client(opts: ClusterOptions) -> Iterator[tuple[Client, ClusterInfo]]:
    address = opts.scheduler or ""
    scheme = address.split("://", 1)[0] if "://" in address else "tcp"
    files = opts.client_tls_files()
    security: Security | None = None
    if files is not None:
        if scheme != "tls":
            raise ValueError(f"TLS certificates were given but the scheduler address {address!r} is not tls://")
        security = make_security(files, "client")
    elif scheme == "tls":
        # fall back to distributed.comm.tls.* from the Dask config (DASK_CONFIG)
        security = Security()
        if not security.get_tls_config_for_role("client").get("cert"):
            raise ValueError(
                f"scheduler {address} uses TLS: give the certificate directory (--tls DIR, made by `schlieren tls init DIR`)"
            )
    client = Client(address, security=security, timeout=opts.connect_timeout, set_as_default=True)
    try:
        client.wait_for_workers(1, timeout=opts.connect_timeout)
        info = _prepare(client, opts, "scheduler")
        log.info("connected to scheduler %s with %d worker(s)", info.scheduler_address, info.n_workers)
        yield client, info
    finally:
        client.close()


@contextlib.contextmanager
def _local_client(opts: ClusterOptions) -> Iterator[tuple[Client, ClusterInfo]]:
    from distributed import LocalCluster

    n_workers = opts.workers or max(1, os.cpu_count() or 1)
    kwargs: dict[str, Any] = {}
    if opts.tls_dir:
        kwargs["security"] = cluster_security(opts.tls_dir)
        kwargs["protocol"] = "tls://"
    elif opts.tls_cert:
        raise ValueError("a local TLS cluster needs a certificate directory (--tls DIR) with scheduler, worker and client certificates")
    # the nannies run in this process and export pre-spawn-environ into os.environ before
    # spawning each worker; put this process's own environment back when done
    saved_env = {k: os.environ.get(k) for k in THREAD_ENV}
    with warnings.catch_warnings(record=True) as caught:
        # a dashboard port already taken (another run, a notebook's cluster) is not an error:
        # distributed picks a free one and says so as a multi-line UserWarning on stderr;
        # the run reports the dashboard it got ("dashboard: ..." and the log line below)
        warnings.filterwarnings("always", message=r"Port \d+ is already in use", category=UserWarning)
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
        if re.search(r"Port \d+ is already in use", str(w.message)):
            log.info("dashboard port of %s already in use; the scheduler chose another", opts.dashboard_address)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    try:
        client = Client(cluster, set_as_default=True)
        try:
            client.wait_for_workers(n_workers, timeout=opts.connect_timeout)
            client.register_plugin(LocalInterrupts())
            info = _prepare(client, opts, "local")
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


@contextlib.contextmanager
def connect(cluster: Any, opts: ClusterOptions | None = None, *, mode: str = "batch",
            security: Security | None = None, wait_workers: int = 0,
            timeout: float | None = None) -> Iterator[tuple[Client, ClusterInfo]]:
    """A client on an already created cluster object (jobqueue, Kubernetes): yield ``(client, info)``.

    Registers :class:`SchlierenWorkerSetup` and checks versions like :func:`open_client`;
    waits for ``wait_workers`` workers first (batch jobs may queue: ``timeout`` None waits
    as long as it takes). Closes the client, not the cluster.
    """
    opts = opts or ClusterOptions()
    client = Client(cluster, security=security, set_as_default=True)
    try:
        if wait_workers:
            client.wait_for_workers(wait_workers, timeout=timeout)
        info = _prepare(client, opts, mode)
        yield client, info
    finally:
        client.close()


# ----------------------------------------------------------------------------------------
# batch clusters

BATCH_KINDS = ("slurm", "pbs", "kubernetes")

# keys of a jobqueue section that belong to the cluster object, not to the job
_JOBQUEUE_CLUSTER_KEYS = {"scheduler_options", "shared_temp_directory", "n_workers", "silence_logs"}


def _underscore(mapping: Mapping[str, Any]) -> dict[str, Any]:
    return {str(k).replace("-", "_"): v for k, v in mapping.items()}


def schlieren_section(config: Mapping[str, Any]) -> dict[str, Any]:
    """The ``schlieren:`` section of a submit config (keys with ``_``), defaults filled in.

    Keys: ``scale`` (jobs / pods to start, default 1), ``adapt`` (``{minimum: A, maximum: B}``
    jobs / pods: scale adaptively instead, replacing workers that reach their ``--lifetime``;
    ``--scale N`` on the command line drops it), ``tomo-slots`` (default 1),
    ``tls`` (a mapping for :func:`~schlieren.workers.security.tls_files_from_config`, or
    absent), ``dashboard-address`` (default ``127.0.0.1:8787``), ``wait-workers``
    (workers to wait for before running, default 1), ``wait-timeout`` (seconds, default
    none: wait for the batch queue), ``dask`` (extra Dask config, dotted keys).
    """
    raw = config.get("schlieren") or {}
    if not isinstance(raw, Mapping):
        raise ValueError("the 'schlieren' section of the config must be a mapping")
    sec = _underscore(raw)
    known = {"scale", "adapt", "tomo_slots", "tls", "dashboard_address", "wait_workers", "wait_timeout", "dask"}
    unknown = set(sec) - known
    if unknown:
        raise ValueError(f"unknown key(s) in the 'schlieren' section: {', '.join(sorted(unknown))}")
    out = {
        "scale": int(sec.get("scale", 1)),
        "tomo_slots": int(sec.get("tomo_slots", 1)),
        "tls": sec.get("tls"),
        "dashboard_address": str(sec.get("dashboard_address", DEFAULT_DASHBOARD)),
        "wait_workers": int(sec.get("wait_workers", 1)),
        "wait_timeout": sec.get("wait_timeout"),
        "dask": dict(sec.get("dask") or {}),
        "adapt": _adapt_bounds(sec.get("adapt")),
    }
    if out["scale"] < 1 or out["tomo_slots"] < 1:
        raise ValueError("scale and tomo-slots must be at least 1")
    if out["tls"] is not None and not isinstance(out["tls"], Mapping):
        raise ValueError("the 'tls' entry must be a mapping (dir, or ca-file/cert/key)")
    return out


def _adapt_bounds(raw: Any) -> tuple[int, int] | None:
    """``schlieren.adapt`` as ``(minimum, maximum)``, or None when absent."""
    if raw is None:
        return None
    if not isinstance(raw, Mapping):
        raise ValueError("the 'adapt' entry must be a mapping with minimum and maximum")
    a = _underscore(raw)
    unknown = set(a) - {"minimum", "maximum"}
    if unknown or "maximum" not in a:
        raise ValueError("the 'adapt' entry takes minimum (default 0) and maximum (required)")
    lo, hi = int(a.get("minimum", 0)), int(a["maximum"])
    if not 0 <= lo <= hi or hi < 1:
        raise ValueError(f"adapt needs 0 <= minimum <= maximum and maximum >= 1, got {lo} and {hi}")
    return lo, hi


def _walltime_seconds(walltime: Any, kind: str) -> float:
    """Seconds of a batch walltime, as the batch system reads it.

    SLURM: ``M``, ``M:S``, ``H:M:S``, ``D-H``, ``D-H:M``, ``D-H:M:S``; PBS: ``S``, ``M:S``,
    ``H:M:S``. Anything else is read as a Dask duration (``"2h"``).
    """
    text = str(walltime).strip()
    try:
        if kind == "slurm" and "-" in text:
            d, rest = text.split("-", 1)
            hms = [float(x) for x in rest.split(":")] + [0.0, 0.0]
            return int(d) * 86400 + hms[0] * 3600 + hms[1] * 60 + hms[2]
        parts = [float(x) for x in text.split(":")]
    except ValueError:
        from dask.utils import parse_timedelta

        return float(parse_timedelta(text))
    if len(parts) == 1:
        return parts[0] * (60 if kind == "slurm" else 1)
    if len(parts) > 3:
        raise ValueError(f"jobqueue.{kind}.walltime: cannot read {walltime!r}")
    parts = [0.0] * (3 - len(parts)) + parts
    return parts[0] * 3600 + parts[1] * 60 + parts[2]


def _flag_value(args: list[str], flag: str) -> str | None:
    """Value of ``--flag V`` or ``--flag=V`` in an argument list (the last one wins, as in click)."""
    value = None
    for i, a in enumerate(args):
        if a == flag and i + 1 < len(args):
            value = args[i + 1]
        elif a.startswith(flag + "="):
            value = a.split("=", 1)[1]
    return value


def _check_lifetime(kind: str, walltime: Any, extra_args: list[str]) -> None:
    """Workers must leave (``--lifetime`` + ``--lifetime-stagger``) before the batch system kills them."""
    if walltime is None:
        return
    from dask.utils import parse_timedelta

    wall = _walltime_seconds(walltime, kind)
    lifetime = _flag_value(extra_args, "--lifetime")
    if lifetime is None:
        raise ValueError(
            f"jobqueue.{kind}.walltime is {walltime} but worker-extra-args has no --lifetime: the batch system "
            "would kill workers mid-task; add --lifetime (a few minutes less than the walltime) and --lifetime-stagger"
        )
    stagger = _flag_value(extra_args, "--lifetime-stagger") or "0s"
    total = float(parse_timedelta(lifetime)) + float(parse_timedelta(stagger))
    if total >= wall:
        raise ValueError(
            f"jobqueue.{kind}: --lifetime {lifetime} + --lifetime-stagger {stagger} must end before the "
            f"walltime {walltime}"
        )


def _shell_word(value: str, where: str) -> str:
    """``value`` as one word of the job script's shell command line; ``$VARS`` still expand there."""
    if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
        return value
    if "$" in value:
        if any(c in value for c in '"`\\'):
            raise ValueError(f"{where}: cannot quote {value!r} for the job script; remove quotes, backquotes, backslashes")
        return f'"{value}"'
    return shlex.quote(value)


def _tls_security(sec: Mapping[str, Any], check: bool = True) -> Security | None:
    """``Security`` with all three roles for a cluster whose scheduler runs with the client."""
    tls = sec.get("tls")
    if not tls:
        return None
    tls_u = _underscore(tls)
    if tls_u.get("dir") and set(tls_u) == {"dir"}:
        return cluster_security(Path(tls_u["dir"]).expanduser(), check=check)
    files = {role: tls_files_from_config(tls, role) for role in ("scheduler", "worker", "client")}
    kwargs: dict[str, str] = {"tls_ca_file": str(files["client"].ca_file)}
    for role, f in files.items():
        kwargs[f"tls_{role}_cert"] = str(f.cert)
        kwargs[f"tls_{role}_key"] = str(f.key)
    return Security(require_encryption=True, **kwargs)


def jobqueue_kwargs(kind: str, config: Mapping[str, Any], *,
                    check_files: bool = True) -> tuple[dict[str, Any], dict[str, Any]]:
    """Keyword arguments for a dask-jobqueue cluster built from a submit config.

    ``config["jobqueue"][kind]`` holds dask-jobqueue's own settings (the same keys as its
    ``jobqueue.yaml``, ``-`` or ``_``). On top of them:

    * each worker process has one thread (``processes`` defaults to ``cores``);
    * workers advertise ``--resources TOMO=<tomo-slots>``;
    * the job script exports the thread caps of :data:`THREAD_ENV` before anything starts;
    * with a ``schlieren.tls`` section, scheduler and workers use ``tls://`` with the
      project certificates;
    * the scheduler's dashboard binds loopback (reach it through an SSH tunnel);
    * ``interface`` is the workers' network only: the scheduler (in this process, on the
      login node) does not inherit it; give it ``scheduler-options: {interface: ...}`` or
      ``{host: ...}``, else it listens on all interfaces and advertises the host's address;
    * ``local-directory`` is one shell word in the job script (``"${TMPDIR:-/tmp}"`` expands
      on the compute node and survives an empty or spaced ``$TMPDIR``);
    * with a ``walltime``, ``worker-extra-args`` must hold a ``--lifetime`` (+ stagger) that
      ends before it, so workers leave gracefully instead of being killed mid-task.

    Returns
    -------
    (job_kwargs, cluster_kwargs)
        ``job_kwargs`` configure the job (they are what ``Job`` classes take);
        ``cluster_kwargs`` the cluster object (scheduler options, security, protocol).
    """
    if kind not in ("slurm", "pbs"):
        raise ValueError(f"not a jobqueue kind: {kind!r} (expected slurm or pbs)")
    jq = (config.get("jobqueue") or {}).get(kind)
    if not isinstance(jq, Mapping):
        raise ValueError(f"the config has no 'jobqueue: {kind}:' section")
    sec = schlieren_section(config)
    kw = {k: v for k, v in _underscore(jq).items() if v is not None}
    for required in ("cores", "memory"):
        if required not in kw:
            raise ValueError(f"jobqueue.{kind}.{required} is required")
    if "name" in kw:  # jobqueue.<kind>.name is the batch job's name
        kw["job_name"] = kw.pop("name")
    cores = int(kw["cores"])
    kw.setdefault("processes", cores)
    if cores % int(kw["processes"]):
        raise ValueError(f"jobqueue.{kind}: cores ({cores}) must be a multiple of processes ({kw['processes']})")

    extra_args = [str(a) for a in (kw.pop("worker_extra_args", None) or [])]
    if "--resources" not in extra_args:
        extra_args += ["--resources", f"{TOMO}={sec['tomo_slots']}"]
    kw["worker_extra_args"] = extra_args
    _check_lifetime(kind, kw.get("walltime"), extra_args)
    if "local_directory" in kw:
        kw["local_directory"] = _shell_word(str(kw["local_directory"]), f"jobqueue.{kind}.local-directory")

    prologue = [str(line) for line in (kw.pop("job_script_prologue", None) or [])]
    exports = [f"export {k}={v}" for k, v in THREAD_ENV.items()]
    kw["job_script_prologue"] = [e for e in exports if e not in prologue] + prologue

    cluster_kw: dict[str, Any] = {}
    for key in list(kw):
        if key in _JOBQUEUE_CLUSTER_KEYS:
            cluster_kw[key] = kw.pop(key)
    sched = dict(cluster_kw.get("scheduler_options") or {})
    sched.setdefault("dashboard_address", sec["dashboard_address"])
    if "host" not in sched and "interface" not in sched:
        # dask-jobqueue would give the scheduler the workers' interface (ib0 on the compute
        # nodes), which the login node may not have; host None: all interfaces
        sched["host"] = None
    cluster_kw["scheduler_options"] = sched
    security = _tls_security(sec, check=check_files)
    if security is not None:
        kw["protocol"] = "tls://"
        kw["security"] = security
        cluster_kw["security"] = security
        cluster_kw["protocol"] = "tls://"
    kw["config_name"] = kind
    return kw, cluster_kw


def _jobqueue_class(kind: str) -> type:
    try:
        import dask_jobqueue
    except ImportError as exc:
        raise RuntimeError("dask-jobqueue is not installed: pip install 'schlieren[cluster]'") from exc
    return {"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[kind]


def job_script(kind: str, config: Mapping[str, Any], *, scheduler_address: str | None = None,
               check_files: bool = True) -> str:
    """The batch script dask-jobqueue would submit for one worker job, without starting anything.

    Built by the jobqueue ``Job`` class from :func:`jobqueue_kwargs`, exactly as the
    cluster object does for its preview (``JobQueueCluster.job_script``).
    ``check_files=False`` renders the TLS paths without requiring the certificates yet.
    """
    job_kw, cluster_kw = jobqueue_kwargs(kind, config, check_files=check_files)
    cls = _jobqueue_class(kind)
    scheme = "tls" if cluster_kw.get("protocol") == "tls://" else "tcp"
    address = scheduler_address or f"{scheme}://<insert-scheduler-address-here>:8786"
    kw = dict(job_kw)
    # the job builds its --tls-* flags from the workers' part of the Security object
    job = cls.job_cls(address, name="dummy-name", **kw)
    return job.job_script()


#: uid/gid of the ``schlieren`` user in the image (deploy/Containerfile); pods run as it.
IMAGE_UID = 10001
#: where a ``tls-secret`` is mounted in the pods
TLS_MOUNT = "/etc/schlieren/tls"
#: Kubernetes names: RFC 1123 labels (DaskCluster names become Service names)
_K8S_NAME = re.compile(r"^[a-z]([-a-z0-9]*[a-z0-9])?$")
#: longest ``kubernetes.name``: it gets a ``-xxxxxx`` suffix per submit, and the operator
#: names worker deployments ``<name>-default-worker-<10 chars>`` (63 at most)
_MAX_NAME = 32


def _volumes(raw: Any) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``kubernetes.volumes`` as (pod volumes, container volumeMounts).

    Each entry is a Kubernetes volume (``name`` and one source such as
    ``persistentVolumeClaim``, ``nfs``, ``secret``, ``csi``) plus ``mount-path`` (required),
    ``read-only`` and ``sub-path``.
    """
    if raw is None:
        return [], []
    if not isinstance(raw, list):
        raise ValueError("kubernetes.volumes must be a list of volumes (name, mount-path and one volume source)")
    volumes, mounts, paths = [], [], set()
    for i, item in enumerate(raw):
        where = f"kubernetes.volumes[{i}]"
        if not isinstance(item, Mapping):
            raise ValueError(f"{where}: expected a mapping with name, mount-path and a volume source")
        entry = {str(k): v for k, v in item.items()}
        name = str(entry.pop("name", ""))
        mount_path = entry.pop("mount-path", entry.pop("mountPath", None))
        read_only = entry.pop("read-only", entry.pop("readOnly", False))
        sub_path = entry.pop("sub-path", entry.pop("subPath", None))
        if not _K8S_NAME.match(name) or name == "tls":
            raise ValueError(f"{where}.name: {name!r} is not a volume name (lowercase letters, digits, '-'; not 'tls')")
        if not isinstance(mount_path, str) or not mount_path.startswith("/"):
            raise ValueError(f"{where}.mount-path: expected an absolute path inside the pods, got {mount_path!r}")
        if mount_path in paths or mount_path.rstrip("/") == TLS_MOUNT:
            raise ValueError(f"{where}.mount-path: {mount_path} is already mounted")
        paths.add(mount_path)
        if len(entry) != 1:
            raise ValueError(
                f"{where}: expected exactly one volume source (persistentVolumeClaim, nfs, secret, ...), "
                f"got {', '.join(sorted(entry)) or 'none'}"
            )
        volumes.append({"name": name, **entry})
        mount: dict[str, Any] = {"name": name, "mountPath": mount_path}
        if read_only:
            mount["readOnly"] = True
        if sub_path:
            mount["subPath"] = str(sub_path)
        mounts.append(mount)
    return volumes, mounts


def daskcluster_manifest(config: Mapping[str, Any]) -> dict[str, Any]:
    """A ``DaskCluster`` resource (Dask Kubernetes operator, ``kubernetes.dask.org/v1``).

    From ``config["kubernetes"]``: ``name``, ``image``, ``workers`` (replicas, overridden
    by ``schlieren.scale``), ``worker-memory`` / ``worker-cpu`` (requests = limits),
    ``scheduler-memory`` / ``scheduler-cpu``, ``env`` (mapping), ``volumes`` (see
    :func:`_volumes`: the session and store, mounted in every worker), ``tls-secret``
    (name of a Secret holding the files of ``schlieren tls init``; with it scheduler and
    workers talk ``tls://`` and mount it read-only at ``/etc/schlieren/tls``),
    ``image-pull-policy``, ``service-account``, ``namespace``, ``idle-timeout`` (seconds
    after which the operator deletes an idle cluster; 0: never), ``run-as-user`` (the
    image's uid, 10001).

    Pods run as that uid and gid with it as ``fsGroup`` (mounted secrets are group-readable,
    mode 0440), ``seccompProfile: RuntimeDefault``, every capability dropped and no
    privilege escalation (the "restricted" Pod Security Standard). Workers run one thread,
    advertise ``TOMO=<tomo-slots>``, get the thread caps as environment variables and a
    memory limit equal to their request.
    """
    k8s = config.get("kubernetes")
    if not isinstance(k8s, Mapping):
        raise ValueError("the config has no 'kubernetes:' section")
    kc = _underscore(k8s)
    known = {
        "name", "image", "workers", "worker_memory", "worker_cpu", "scheduler_memory", "scheduler_cpu",
        "env", "tls_secret", "image_pull_policy", "service_account", "namespace", "volumes", "idle_timeout",
        "run_as_user",
    }
    unknown = set(kc) - known
    if unknown:
        raise ValueError(f"unknown key(s) in the 'kubernetes' section: {', '.join(sorted(unknown))}")
    sec = schlieren_section(config)
    name = str(kc.get("name", "schlieren"))
    if not _K8S_NAME.match(name) or len(name) > _MAX_NAME + 7:
        raise ValueError(
            f"kubernetes.name {name!r}: lowercase letters, digits and '-', starting with a letter, at most {_MAX_NAME}"
        )
    image = kc.get("image")
    if not image:
        raise ValueError("kubernetes.image is required (the image built from deploy/Containerfile)")
    raw_sec = _underscore(config.get("schlieren") or {})
    replicas = int(raw_sec.get("scale", kc.get("workers", 2)))
    wmem = str(kc.get("worker_memory", "4Gi"))
    wcpu = str(kc.get("worker_cpu", "1"))
    smem = str(kc.get("scheduler_memory", "2Gi"))
    scpu = str(kc.get("scheduler_cpu", "1"))
    env = {**THREAD_ENV, **{str(k): str(v) for k, v in (kc.get("env") or {}).items()}}
    env_list = [{"name": k, "value": v} for k, v in env.items()]
    tls_secret = kc.get("tls_secret")
    pull = str(kc.get("image_pull_policy", "IfNotPresent"))
    uid = int(kc.get("run_as_user", IMAGE_UID))
    if uid < 1:
        raise ValueError("kubernetes.run-as-user must be a non-root uid (the image's is 10001)")
    data_volumes, data_mounts = _volumes(kc.get("volumes"))

    def tls_args(role: str) -> list[str]:
        if not tls_secret:
            return []
        return [
            "--tls-ca-file", f"{TLS_MOUNT}/ca.pem",
            "--tls-cert", f"{TLS_MOUNT}/{role}.pem",
            "--tls-key", f"{TLS_MOUNT}/{role}-key.pem",
        ]

    # 0440 + fsGroup: the kubelet makes the files root:<uid>, readable by the pod's group only
    tls_volumes = [{"name": "tls", "secret": {"secretName": str(tls_secret), "defaultMode": 0o440}}] if tls_secret else []
    tls_mounts = [{"name": "tls", "mountPath": TLS_MOUNT, "readOnly": True}] if tls_secret else []
    pod_security = {
        "runAsNonRoot": True,
        "runAsUser": uid,
        "runAsGroup": uid,
        "fsGroup": uid,
        # chown a volume only when its root is not yet ours: a store holds millions of chunk files
        "fsGroupChangePolicy": "OnRootMismatch",
        "seccompProfile": {"type": "RuntimeDefault"},
    }
    container_security = {
        "runAsNonRoot": True,
        "allowPrivilegeEscalation": False,
        "capabilities": {"drop": ["ALL"]},
    }

    worker_args = ["dask", "worker"]
    if tls_secret:
        # the operator's DASK_SCHEDULER_ADDRESS is tcp://; name the tls:// service address instead
        worker_args.append(f"tls://{name}-scheduler:8786")
    worker_args += [
        "--name", "$(DASK_WORKER_NAME)",
        "--nthreads", "1",
        "--memory-limit", wmem.replace("Gi", "GiB").replace("Mi", "MiB"),
        "--resources", f"{TOMO}={sec['tomo_slots']}",
        "--dashboard-address", "8788",
        *tls_args("worker"),
    ]
    scheduler_args = ["dask", "scheduler", "--host", "0.0.0.0", "--dashboard-address", ":8787"]
    if tls_secret:
        scheduler_args += ["--protocol", "tls", *tls_args("scheduler")]

    def pod(container: dict[str, Any], volumes: list[dict[str, Any]]) -> dict[str, Any]:
        spec: dict[str, Any] = {"securityContext": pod_security, "containers": [container]}
        if volumes:
            spec["volumes"] = volumes
        if kc.get("service_account"):
            spec["serviceAccountName"] = str(kc["service_account"])
        return spec

    worker = {
        "name": "worker",
        "image": image,
        "imagePullPolicy": pull,
        "args": worker_args,
        "env": env_list,
        "resources": {"requests": {"cpu": wcpu, "memory": wmem}, "limits": {"cpu": wcpu, "memory": wmem}},
        "ports": [{"name": "http-dashboard", "containerPort": 8788, "protocol": "TCP"}],
        "securityContext": container_security,
    }
    scheduler = {
        "name": "scheduler",
        "image": image,
        "imagePullPolicy": pull,
        "args": scheduler_args,
        "env": env_list,
        "resources": {"requests": {"cpu": scpu, "memory": smem}, "limits": {"cpu": scpu, "memory": smem}},
        "ports": [
            {"name": "tcp-comm", "containerPort": 8786, "protocol": "TCP"},
            {"name": "http-dashboard", "containerPort": 8787, "protocol": "TCP"},
        ],
        "readinessProbe": {
            "httpGet": {"port": "http-dashboard", "path": "/health"},
            "initialDelaySeconds": 0,
            "periodSeconds": 1,
            "timeoutSeconds": 300,
        },
        "livenessProbe": {"httpGet": {"port": "http-dashboard", "path": "/health"}, "initialDelaySeconds": 15, "periodSeconds": 20},
        "securityContext": container_security,
    }
    if tls_mounts or data_mounts:
        worker["volumeMounts"] = tls_mounts + data_mounts
    if tls_mounts:
        scheduler["volumeMounts"] = tls_mounts
    spec: dict[str, Any] = {}
    if kc.get("idle_timeout") is not None:
        spec["idleTimeout"] = int(kc["idle_timeout"])
    spec["worker"] = {"replicas": replicas, "spec": pod(worker, tls_volumes + data_volumes)}
    spec["scheduler"] = {
        "spec": pod(scheduler, tls_volumes),
        "service": {
            "type": "ClusterIP",
            "selector": {"dask.org/cluster-name": name, "dask.org/component": "scheduler"},
            "ports": [
                {"name": "tcp-comm", "protocol": "TCP", "port": 8786, "targetPort": "tcp-comm"},
                {"name": "http-dashboard", "protocol": "TCP", "port": 8787, "targetPort": "http-dashboard"},
            ],
        },
    }
    manifest: dict[str, Any] = {
        "apiVersion": "kubernetes.dask.org/v1",
        "kind": "DaskCluster",
        "metadata": {"name": name},
        "spec": spec,
    }
    if kc.get("namespace"):
        manifest["metadata"]["namespace"] = str(kc["namespace"])
    return json.loads(json.dumps(manifest))  # no shared sub-objects (YAML anchors when dumped)


def unique_cluster_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """``config`` with ``kubernetes.name`` made unique for one submit (``<name>-<6 hex>``).

    ``schlieren submit`` creates a fresh DaskCluster each time instead of connecting to a
    leftover one of the same name (whose workers may run other code or versions).
    """
    out = copy.deepcopy(dict(config))
    k8s = out.get("kubernetes")
    if not isinstance(k8s, dict):
        raise ValueError("the config has no 'kubernetes:' section")
    base = str(k8s.get("name", "schlieren"))
    if not _K8S_NAME.match(base) or len(base) > _MAX_NAME:
        raise ValueError(
            f"kubernetes.name {base!r}: lowercase letters, digits and '-', starting with a letter, at most {_MAX_NAME}"
        )
    k8s["name"] = f"{base}-{secrets.token_hex(3)}"
    return out


def jobqueue_cluster(kind: str, config: Mapping[str, Any]) -> Any:
    """The dask-jobqueue cluster object for ``kind``, with its scheduler started, no job submitted yet."""
    job_kw, cluster_kw = jobqueue_kwargs(kind, config)
    cls = _jobqueue_class(kind)
    return cls(**cluster_kw, **{k: v for k, v in job_kw.items() if k not in cluster_kw})


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
        if kind in ("slurm", "pbs"):
            cluster = jobqueue_cluster(kind, config)
            if sec["adapt"] is not None:
                # jobs whose workers retire at --lifetime are replaced, up to maximum
                cluster.adapt(minimum_jobs=sec["adapt"][0], maximum_jobs=sec["adapt"][1])
            else:
                cluster.scale(jobs=sec["scale"])
            return cluster
        manifest = daskcluster_manifest(unique_cluster_config(config))
        if _underscore(config["kubernetes"]).get("tls_secret"):
            raise ValueError(
                "KubeCluster cannot talk TLS to the scheduler: apply the manifest with kubectl and use "
                "`schlieren run --scheduler tls://...` (deploy/GUIDE.md)"
            )
        try:
            from dask_kubernetes.operator import KubeCluster
            from dask_kubernetes.operator.kubecluster.kubecluster import CreateMode
        except ImportError as exc:
            raise RuntimeError("dask-kubernetes is not installed: pip install dask-kubernetes") from exc
        namespace = _underscore(config["kubernetes"]).get("namespace")
        # a new cluster every time (never a leftover of the same name), deleted when closed
        cluster = KubeCluster(
            custom_cluster_spec=manifest,
            namespace=namespace,
            create_mode=CreateMode.CREATE_ONLY,
            shutdown_on_close=True,
        )
        if sec["adapt"] is not None:
            cluster.adapt(minimum=sec["adapt"][0], maximum=sec["adapt"][1])
        return cluster


class TomoResource(WorkerPlugin):
    """Give a worker the ``TOMO`` resource if it was started without one.

    Tomography tasks request ``resources={"TOMO": 1}``; on workers that do not advertise
    it they would wait forever. Registered by :func:`adopt_client` on a user's cluster.
    """

    idempotent = True
    name = "schlieren-tomo-resource"

    def __init__(self, slots: float = 1) -> None:
        self.slots = float(slots)

    def setup(self, worker: Any):
        if TOMO in worker.state.total_resources:
            return None
        return worker.set_resources(**{TOMO: self.slots})


def adopt_client(client: Client, opts: ClusterOptions | None = None) -> ClusterInfo:
    """Prepare a client the user made (``schlieren.run(client=...)``) like our own clusters.

    Registers :class:`SchlierenWorkerSetup` (thread caps, zarr concurrency, logging) and
    :class:`TomoResource` on every current and future worker, then checks versions.
    """
    client.register_plugin(TomoResource(1))
    return _prepare(client, opts or ClusterOptions(), "client")


class _CancelledOnClose(logging.Filter):
    """Drops distributed's "Async instruction for <Task cancelled ...>" warnings: tasks the
    worker was running when the client closed the cluster (Ctrl-C); nothing is lost."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Task cancelled" not in record.getMessage()


class _AfterCtrlC(logging.Filter):
    """After a Ctrl-C reached this worker: drops the errors of the cluster closing under it,
    a peer gone mid-transfer, from either end: the sender's "failed during get data" and the
    receiver's "Worker stream died during communication" (with its traceback; seen once in
    a fresh-clone CI run). Before it nothing is dropped."""

    interrupted = False
    MESSAGES = ("failed during get data", "Worker stream died during communication")

    def filter(self, record: logging.LogRecord) -> bool:
        if not (_AfterCtrlC.interrupted and record.levelno >= logging.WARNING):
            return True
        msg = record.getMessage()
        return not any(m in msg for m in self.MESSAGES)


def _note_ctrl_c(signum, frame) -> None:  # a worker's SIGINT: the client stops the run
    _AfterCtrlC.interrupted = True


class LocalInterrupts(WorkerPlugin):
    """Workers of a local cluster leave Ctrl-C to the client process.

    A terminal's Ctrl-C reaches every process of its foreground group, the worker
    processes of a local cluster included: each printed a KeyboardInterrupt traceback
    before the client's one-line "interrupted" message. The client closes the cluster
    (which stops the workers) and keeps every completed chunk; the workers ignore SIGINT
    (they only note it, to keep the cluster's closing errors out of the terminal).
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
        logging.getLogger("distributed.worker").addFilter(_AfterCtrlC())
