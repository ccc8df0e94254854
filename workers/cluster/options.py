"""How a run obtains its cluster: :class:`ClusterOptions` (local workers or a running
scheduler), the ``schlieren:`` section of a batch submit config (SLURM, PBS, Kubernetes),
and :class:`ClusterInfo`, what a client got connected to.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from schlieren.workers.cluster.dashboard import DEFAULT_DASHBOARD
from schlieren.workers.security import TLSFiles

#: cluster kinds of ``schlieren submit --cluster`` (:func:`~schlieren.workers.cluster.make_batch_cluster`)
BATCH_KINDS = ("slurm", "pbs", "kubernetes")


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
    """What :func:`~schlieren.workers.cluster.open_client` connected to.

    Attributes
    ----------
    mode : str
        ``"local"``, ``"scheduler"``, ``"slurm"``, ``"pbs"`` or ``"kubernetes"``.
    scheduler_address : str
    dashboard_link : str or None
        URL of the scheduler dashboard's status page, None if it has none.
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
# the submit config's `schlieren:` section (SLURM, PBS and Kubernetes alike)


def underscore_keys(mapping: Mapping[str, Any]) -> dict[str, Any]:
    """``mapping`` with ``-`` in its keys replaced by ``_`` (config files may use either)."""
    return {str(k).replace("-", "_"): v for k, v in mapping.items()}


def schlieren_section(config: Mapping[str, Any]) -> dict[str, Any]:
    """The ``schlieren:`` section of a submit config (keys with ``_``), defaults filled in.

    Keys: ``scale`` (jobs / pods to start, default 1), ``adapt`` (``{minimum: A, maximum: B}``
    jobs / pods: scale adaptively instead, replacing workers that reach their ``--lifetime``;
    ``--scale N`` on the command line drops it), ``tomo-slots`` (default 1),
    ``tls`` (a mapping for :func:`~schlieren.workers.security.tls_files_from_config`, or
    absent), ``dashboard-address`` (default ``127.0.0.1:8787``), ``wait-workers``
    (workers to wait for before running, default 1), ``wait-timeout`` (seconds without
    workers before the run fails, at the start and whenever the workers have left; default
    none: wait for the batch queue), ``stall-timeout`` (seconds with no worker and no job
    pending or running before the run fails, default 120), ``dask`` (extra Dask config,
    dotted keys).
    """
    raw = config.get("schlieren") or {}
    if not isinstance(raw, Mapping):
        raise ValueError("the 'schlieren' section of the config must be a mapping")
    sec = underscore_keys(raw)
    known = {"scale", "adapt", "tomo_slots", "tls", "dashboard_address", "wait_workers", "wait_timeout",
             "stall_timeout", "dask"}
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
        "stall_timeout": float(sec.get("stall_timeout", 120)),
        "dask": dict(sec.get("dask") or {}),
        "adapt": _adapt_bounds(sec.get("adapt")),
    }
    if out["scale"] < 1 or out["tomo_slots"] < 1:
        raise ValueError("scale and tomo-slots must be at least 1")
    if out["stall_timeout"] <= 0 or (out["wait_timeout"] is not None and float(out["wait_timeout"]) <= 0):
        raise ValueError("wait-timeout and stall-timeout must be positive numbers of seconds")
    if out["tls"] is not None and not isinstance(out["tls"], Mapping):
        raise ValueError("the 'tls' entry must be a mapping (dir, or ca-file/cert/key)")
    return out


def _adapt_bounds(raw: Any) -> tuple[int, int] | None:
    """``schlieren.adapt`` as ``(minimum, maximum)``, or None when absent."""
    if raw is None:
        return None
    if not isinstance(raw, Mapping):
        raise ValueError("the 'adapt' entry must be a mapping with minimum and maximum")
    a = underscore_keys(raw)
    unknown = set(a) - {"minimum", "maximum"}
    if unknown or "maximum" not in a:
        raise ValueError("the 'adapt' entry takes minimum (default 0) and maximum (required)")
    lo, hi = int(a.get("minimum", 0)), int(a["maximum"])
    if not 0 <= lo <= hi or hi < 1:
        raise ValueError(f"adapt needs 0 <= minimum <= maximum and maximum >= 1, got {lo} and {hi}")
    return lo, hi
