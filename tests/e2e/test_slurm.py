"""`schlieren submit --cluster slurm` against a real SLURM (system tier).

deploy/slurm/local/slurm.sh installs Debian's SLURM and munge if they are missing and
starts a one-node cluster on this machine (a few seconds); where that is impossible (not
root, no apt-get, the packages cannot be fetched) the tests skip with its one-line reason.
The cluster config is the shipped recipe, deploy/slurm/jobqueue.yaml, with only the lines
its comments say a site edits changed (partition, cores and memory of this node, the
network interface, the venv's python, the log folder) and TLS on: several worker
processes per job and `adapt`, as shipped.

Each run must end with a store bit-identical to the serial reference, also when a worker
job is killed with SIGKILL mid-run (scancel -s KILL) and when the workers retire at their
`--lifetime` (the batch walltime's stand-in) and their jobs are replaced.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from store_compare import assert_same_store

pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "deploy" / "slurm" / "local" / "slurm.sh"
CLI = [sys.executable, "-m", "schlieren.workers.cli"]


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    """A running one-node SLURM; yields the environment its clients need."""
    if os.name != "posix" or not shutil.which("bash"):
        pytest.skip("SLURM: needs a POSIX shell")
    folder = tmp_path_factory.mktemp("slurm")
    env = dict(os.environ, SCHLIEREN_SLURM_DIR=str(folder))
    t0 = time.monotonic()
    p = subprocess.run([str(SCRIPT), "start"], capture_output=True, text=True, timeout=900, env=env)
    if p.returncode == 3:
        pytest.skip((p.stderr.strip().splitlines() or ["SLURM unavailable"])[-1])
    assert p.returncode == 0, p.stderr
    print(f"\nSLURM up in {time.monotonic() - t0:.1f} s: {p.stderr.strip().splitlines()[-1]}")
    env["SLURM_CONF"] = str(folder / "slurm.conf")
    yield env
    subprocess.run([str(SCRIPT), "stop"], capture_output=True, text=True, timeout=60, env=env)


def _jobs(env) -> list[str]:
    """Job ids of this cluster's pending or running jobs."""
    out = subprocess.run(["squeue", "-h", "-o", "%i %T"], capture_output=True, text=True, env=env, timeout=30)
    return [line.split()[0] for line in out.stdout.splitlines() if line.split()[1:] in (["RUNNING"], ["PENDING"])]


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("tls") / "tls"
    p = subprocess.run(CLI + ["tls", "init", str(d), "--host", "127.0.0.1", "--host", "localhost"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return d


def _config(tmp_path: Path, tls_dir: Path, *, lifetime: str | None = None, wait_timeout: int = 300) -> Path:
    """The shipped recipe with the lines a site edits set for this one-node cluster."""
    cfg = yaml.safe_load((ROOT / "deploy" / "slurm" / "jobqueue.yaml").read_text())
    s = cfg["jobqueue"]["slurm"]
    assert s["processes"] > 1, "the shipped job shape runs several worker processes per job"
    s.update(cores=2, processes=2, memory="4GiB", queue="debug", walltime="00:20:00", interface="lo",
             python=sys.executable, **{"log-directory": str(tmp_path / "logs"), "local-directory": str(tmp_path)})
    s["job-extra-directives"] = []  # --exclusive: one job per node, and this cluster has one node
    s["job-script-prologue"] = [f'export DASK_CONFIG="{ROOT / "deploy" / "config"}"']
    s["scheduler-options"] = {"dashboard_address": "127.0.0.1:0", "interface": "lo"}
    if lifetime:
        s["worker-extra-args"] = ["--lifetime", lifetime, "--lifetime-stagger", "2s"]
    sch = cfg["schlieren"]
    sch["adapt"] = {"minimum": 1, "maximum": 1}
    sch["wait-timeout"] = wait_timeout
    sch["tls"] = {"dir": str(tls_dir)}
    path = tmp_path / "slurm.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _submit(session, out, config, env, **popen) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["submit", str(session), "--out", str(out), "--cluster", "slurm",
                                   "--config", str(config), "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, **popen)


def _markers(store: Path) -> int:
    return sum(1 for p in (store / "status").rglob("*") if p.is_file()) if (store / "status").exists() else 0


def test_submit_gives_the_serial_store(slurm, tls_dir, tiny_session, serial_store, tmp_path):
    out = tmp_path / "slurm.zarr"
    t0 = time.monotonic()
    proc = _submit(tiny_session.session, out, _config(tmp_path, tls_dir), slurm)
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 0, stderr
    print(f"\nsubmit: {time.monotonic() - t0:.1f} s wall; {stdout.strip().splitlines()[-1]}")
    assert_same_store(serial_store, out)
    assert "Traceback" not in stderr


def test_a_killed_worker_job_is_replaced_and_the_run_completes(slurm, tls_dir, tiny_session, serial_store, tmp_path):
    out = tmp_path / "killed.zarr"
    t0 = time.monotonic()
    proc = _submit(tiny_session.session, out, _config(tmp_path, tls_dir), slurm)
    try:
        # kill the worker job once it has done some work (its workers joined and wrote markers)
        while proc.poll() is None and _markers(out) < 6 and time.monotonic() - t0 < 600:
            time.sleep(0.2)
        jobs = _jobs(slurm)
        assert proc.poll() is None and jobs, "the run ended before a job could be killed"
        subprocess.run(["scancel", "-s", "KILL", *jobs], check=True, env=slurm, timeout=30)
        killed_at = time.monotonic() - t0
        stdout, stderr = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    print(f"\nkilled job(s) {', '.join(jobs)} at {killed_at:.1f} s; run complete at {time.monotonic() - t0:.1f} s")
    assert_same_store(serial_store, out)


def test_workers_retiring_at_their_lifetime_are_replaced(slurm, tls_dir, tiny_session, serial_store, tmp_path):
    out = tmp_path / "lifetime.zarr"
    t0 = time.monotonic()
    proc = _submit(tiny_session.session, out, _config(tmp_path, tls_dir, lifetime="12s"), slurm)
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 0, stderr
    logs = sorted((tmp_path / "logs").glob("*.err"))
    retired = sum("lifetime" in p.read_text(errors="replace").lower() for p in logs)
    print(f"\nlifetime 12 s: {len(logs)} worker job(s), {retired} retired at their lifetime; "
          f"run complete at {time.monotonic() - t0:.1f} s")
    assert len(logs) >= 2 and retired >= 1, "the run should have outlived its first job's workers"
    assert_same_store(serial_store, out)
