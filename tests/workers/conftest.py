"""Fixtures: Dask schedulers and workers started as separate processes on 127.0.0.1.

``external_cluster_factory(n_workers=2, tls_dir=None, ...)`` starts ``dask scheduler``
and ``dask worker`` (with a nanny) subprocesses and returns an :class:`ExternalCluster`;
``external_scheduler`` is the plain two-worker case. Ports are chosen by the scheduler
itself (``--port 0``) and read back from its ``--scheduler-file``, so tests never race
for a port. Every process is started in its own session and the whole process group is
terminated (then killed) at teardown, so no worker outlives the test.

The subprocesses load ``deploy/config/bos.yaml`` through ``DASK_CONFIG`` (like a lab's
deployment does) and do not inherit the thread-cap variables of the test process, so a
test can tell that the deployment config, not the environment, capped the threads.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[2]
DEPLOY_CONFIG_DIR = REPO / "deploy" / "config"

THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
    "NUMBA_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)


def subprocess_env(**extra: str) -> dict[str, str]:
    """Environment for scheduler/worker subprocesses: ours minus thread caps, plus DASK_CONFIG."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS and not k.startswith("DASK_")}
    env["DASK_CONFIG"] = str(DEPLOY_CONFIG_DIR)
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


def _kill_group(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """SIGTERM then SIGKILL the process group led by ``proc`` (started with start_new_session)."""
    if proc.poll() is None:
        try:
            family = [proc.pid] + [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
        except psutil.NoSuchProcess:
            family = [proc.pid]
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pass
        for pid in family:  # stragglers (a worker whose nanny died first)
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=timeout)


def _spawned_children(pid: int) -> list[int]:
    """Worker processes a nanny spawned (multiprocessing ``spawn_main``; not its resource tracker)."""
    try:
        kids = psutil.Process(pid).children(recursive=False)
    except psutil.NoSuchProcess:
        return []
    out = []
    for k in kids:
        try:
            if "spawn_main" in " ".join(k.cmdline()):
                out.append(k.pid)
        except psutil.NoSuchProcess:
            continue
    return out


@dataclass
class ExternalCluster:
    """A scheduler and workers running as separate processes on 127.0.0.1."""

    address: str
    dashboard_port: int
    scheduler: subprocess.Popen
    nannies: list[subprocess.Popen]
    tls_dir: Path | None
    log_dir: Path
    extra_procs: list[subprocess.Popen] = field(default_factory=list)

    @property
    def dashboard_url(self) -> str:
        return f"http://127.0.0.1:{self.dashboard_port}"

    def worker_pids(self) -> list[int]:
        """PIDs of the worker processes (spawned children of the ``dask worker`` nanny processes)."""
        pids: list[int] = []
        for nanny in self.nannies:
            pids += _spawned_children(nanny.pid)
        return pids

    def kill_worker(self, index: int = 0, sig: int = signal.SIGKILL) -> int:
        """Kill the worker process of the ``index``-th nanny (the nanny restarts it); return its PID."""
        kids = _spawned_children(self.nannies[index].pid)
        if not kids:
            raise RuntimeError(f"nanny {index} has no worker process")
        os.kill(kids[0], sig)
        return kids[0]

    def spawn(self, cmd: list[str], log_name: str, *, env: dict[str, str] | None = None) -> subprocess.Popen:
        """Start another process (e.g. a job script) that is stopped with the cluster."""
        proc = _spawn(cmd, self.log_dir / f"{log_name}.log", env if env is not None else subprocess_env())
        self.extra_procs.append(proc)
        return proc

    def security(self, role: str = "client"):
        from schlieren.workers.security import TLSFiles, make_security

        if self.tls_dir is None:
            return None
        return make_security(TLSFiles.from_dir(self.tls_dir, role), role)

    def logs(self) -> str:
        return "\n".join(f"== {p.name}\n{p.read_text(errors='replace')[-3000:]}" for p in sorted(self.log_dir.glob("*.log")))

    def stop(self) -> None:
        for proc in [*self.extra_procs, *self.nannies, self.scheduler]:
            _kill_group(proc)


def _spawn(cmd: list[str], log_path: Path, env: dict[str, str]) -> subprocess.Popen:
    fh = open(log_path, "wb")  # noqa: SIM115 - closed by the OS when the child exits; we keep no handle
    try:
        return subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    finally:
        fh.close()


def start_external_cluster(
    workdir: Path,
    *,
    n_workers: int = 2,
    tls_dir: Path | None = None,
    tomo_slots: int = 1,
    memory_limit: str = "1GiB",
    timeout: float = 60.0,
    env: dict[str, str] | None = None,
) -> ExternalCluster:
    """Start ``dask scheduler`` + ``n_workers`` ``dask worker`` processes; wait until all connected."""
    workdir.mkdir(parents=True, exist_ok=True)
    log_dir = workdir / "logs"
    log_dir.mkdir(exist_ok=True)
    sched_file = workdir / "scheduler.json"
    env = env or subprocess_env()
    tls_sched: list[str] = []
    tls_work: list[str] = []
    if tls_dir is not None:
        tls_sched = ["--protocol", "tls", "--tls-ca-file", str(tls_dir / "ca.pem"),
                     "--tls-cert", str(tls_dir / "scheduler.pem"), "--tls-key", str(tls_dir / "scheduler-key.pem")]
        tls_work = ["--tls-ca-file", str(tls_dir / "ca.pem"),
                    "--tls-cert", str(tls_dir / "worker.pem"), "--tls-key", str(tls_dir / "worker-key.pem")]
    scheduler = _spawn(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
         "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(sched_file), "--no-show", *tls_sched],
        log_dir / "scheduler.log",
        env,
    )
    cluster = ExternalCluster(address="", dashboard_port=0, scheduler=scheduler, nannies=[], tls_dir=tls_dir, log_dir=log_dir)
    try:
        deadline = time.monotonic() + timeout
        info = None
        while time.monotonic() < deadline:
            if scheduler.poll() is not None:
                raise RuntimeError(f"dask scheduler exited with {scheduler.returncode}\n{cluster.logs()}")
            if sched_file.exists():
                try:
                    info = json.loads(sched_file.read_text())
                    break
                except json.JSONDecodeError:
                    pass
            time.sleep(0.1)
        if info is None:
            raise RuntimeError(f"dask scheduler did not start in {timeout} s\n{cluster.logs()}")
        cluster.address = info["address"]
        cluster.dashboard_port = int(info["services"]["dashboard"])
        for i in range(n_workers):
            cluster.nannies.append(
                _spawn(
                    [sys.executable, "-m", "distributed.cli.dask_worker", cluster.address,
                     "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1", "--name", f"w{i}",
                     "--memory-limit", memory_limit, "--resources", f"TOMO={tomo_slots}",
                     "--local-directory", str(workdir / f"w{i}"), "--no-dashboard", *tls_work],
                    log_dir / f"worker-{i}.log",
                    env,
                )
            )
        _wait_for_workers(cluster, n_workers, deadline)
        return cluster
    except BaseException:
        cluster.stop()
        raise


def _wait_for_workers(cluster: ExternalCluster, n: int, deadline: float) -> None:
    from distributed import Client

    with Client(cluster.address, security=cluster.security("client"), timeout=30) as client:
        while time.monotonic() < deadline:
            for p in cluster.nannies:
                if p.poll() is not None:
                    raise RuntimeError(f"dask worker exited with {p.returncode}\n{cluster.logs()}")
            if len(client.scheduler_info(n_workers=-1)["workers"]) >= n:
                return
            time.sleep(0.1)
    raise RuntimeError(f"{n} workers did not connect in time\n{cluster.logs()}")


@pytest.fixture
def external_cluster_factory(tmp_path: Path) -> Iterator:
    """Call it to start a subprocess cluster; every cluster started is stopped at teardown."""
    started: list[ExternalCluster] = []

    def factory(**kwargs) -> ExternalCluster:
        workdir = tmp_path / f"cluster{len(started)}"
        c = start_external_cluster(workdir, **kwargs)
        started.append(c)
        return c

    yield factory
    for c in started:
        c.stop()


@pytest.fixture
def external_scheduler(external_cluster_factory) -> ExternalCluster:
    """A separately started ``dask scheduler`` plus two ``dask worker`` processes (TOMO=1 each).

    ``.address`` is the ``tcp://127.0.0.1:PORT`` to pass to ``schlieren run --scheduler``.
    """
    return external_cluster_factory(n_workers=2)
