"""SLURM and PBS through dask-jobqueue: the keyword arguments of its cluster objects, built
from a submit config (``deploy/slurm/jobqueue.yaml``), the job script they submit, and the
checks that keep a batch job from killing its workers mid-task (walltime vs ``--lifetime``).
The cluster classes have :mod:`~schlieren.workers.cluster.jobwatch`'s job watch mixed in.

The scheduler runs in the submitting process (on the login node); each batch job starts
worker processes that join it.
"""

from __future__ import annotations

import functools
import shlex
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from distributed.security import Security

from schlieren.workers.cluster.dashboard import port_warnings_logged
from schlieren.workers.cluster.jobwatch import WatchedJobs, WatchSettings, recording_job_class
from schlieren.workers.cluster.options import schlieren_section, underscore_keys
from schlieren.workers.cluster.settings import THREAD_ENV, TOMO
from schlieren.workers.security import cluster_security, tls_files_from_config

JOBQUEUE_KINDS = ("slurm", "pbs")

# keys of a jobqueue section that belong to the cluster object, not to the job
_JOBQUEUE_CLUSTER_KEYS = {"scheduler_options", "shared_temp_directory", "n_workers", "silence_logs"}


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
    tls_u = underscore_keys(tls)
    if tls_u.get("dir") and set(tls_u) == {"dir"}:
        return cluster_security(Path(tls_u["dir"]).expanduser(), check=check)
    files = {role: tls_files_from_config(tls, role) for role in ("scheduler", "worker", "client")}
    kwargs: dict[str, str] = {"tls_ca_file": str(files["client"].ca_file)}
    for role, f in files.items():
        kwargs[f"tls_{role}_cert"] = str(f.cert)
        kwargs[f"tls_{role}_key"] = str(f.key)
    return Security(require_encryption=True, **kwargs)


def _job_options(kind: str, jq: Mapping[str, Any], tomo_slots: int) -> dict[str, Any]:
    """The ``jobqueue.<kind>`` section as job keyword arguments, with our workers' settings
    (one thread per process, ``TOMO``, thread caps exported, lifetime checked)."""
    kw = {k: v for k, v in underscore_keys(jq).items() if v is not None}
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
        extra_args += ["--resources", f"{TOMO}={tomo_slots}"]
    kw["worker_extra_args"] = extra_args
    _check_lifetime(kind, kw.get("walltime"), extra_args)
    if "local_directory" in kw:
        kw["local_directory"] = _shell_word(str(kw["local_directory"]), f"jobqueue.{kind}.local-directory")

    prologue = [str(line) for line in (kw.pop("job_script_prologue", None) or [])]
    exports = [f"export {k}={v}" for k, v in THREAD_ENV.items()]
    kw["job_script_prologue"] = [e for e in exports if e not in prologue] + prologue
    return kw


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
    if kind not in JOBQUEUE_KINDS:
        raise ValueError(f"not a jobqueue kind: {kind!r} (expected slurm or pbs)")
    jq = (config.get("jobqueue") or {}).get(kind)
    if not isinstance(jq, Mapping):
        raise ValueError(f"the config has no 'jobqueue: {kind}:' section")
    sec = schlieren_section(config)
    kw = _job_options(kind, jq, sec["tomo_slots"])

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
    """dask-jobqueue's cluster class for ``kind`` with :class:`WatchedJobs` mixed in."""
    try:
        import dask_jobqueue
    except ImportError as exc:
        raise RuntimeError("dask-jobqueue is not installed: pip install 'schlieren[cluster]'") from exc
    return _watched({"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[kind])


@functools.lru_cache(maxsize=None)
def _watched(base: type) -> type:
    return type(f"Watched{base.__name__}", (WatchedJobs, base), {"job_cls": recording_job_class(base.job_cls)})


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


def jobqueue_cluster(kind: str, config: Mapping[str, Any]) -> Any:
    """The dask-jobqueue cluster object for ``kind``, with its scheduler started, no job submitted yet.

    Its jobs are watched (:class:`~schlieren.workers.cluster.jobwatch.WatchedJobs`): the ones
    that end are replaced, and ``stalled`` says when none can run.
    """
    job_kw, cluster_kw = jobqueue_kwargs(kind, config)
    sec = schlieren_section(config)
    wait = sec["wait_timeout"]
    watch = WatchSettings(kind=kind, stall_timeout=float(sec["stall_timeout"]),
                          wait_timeout=float(wait) if wait is not None else None,
                          log_directory=job_kw.get("log_directory"))
    cls = _jobqueue_class(kind)
    with port_warnings_logged():  # a taken dashboard port: the run's "dashboard:" line says so
        return cls(watch=watch, **cluster_kw, **{k: v for k, v in job_kw.items() if k not in cluster_kw})


def scaled_jobqueue_cluster(kind: str, config: Mapping[str, Any]) -> Any:
    """:func:`jobqueue_cluster` with its jobs submitted: ``schlieren.scale`` of them, or
    adaptively between ``schlieren.adapt``'s minimum and maximum."""
    sec = schlieren_section(config)
    cluster = jobqueue_cluster(kind, config)
    if sec["adapt"] is not None:
        # jobs whose workers retire at --lifetime are replaced, up to maximum
        cluster.adapt(minimum_jobs=sec["adapt"][0], maximum_jobs=sec["adapt"][1])
    else:
        cluster.scale(jobs=sec["scale"])
    return cluster
