"""`schlieren submit --cluster slurm` against a real SLURM (system tier).

deploy/slurm/local/slurm.sh installs Debian's SLURM and munge if they are missing and
starts a one-node cluster on this machine (a few seconds); where that is impossible (not
root, no apt-get, the packages cannot be fetched) the tests skip with its one-line reason.
The cluster config is the shipped recipe, deploy/slurm/jobqueue.yaml, with only the lines
its comments say a site edits changed (partition, cores and memory of this node, the
network interface, the venv, the DASK_CONFIG path, the log folder) and TLS on: several
worker processes per job and `adapt`, as shipped.

Each run must end with a store bit-identical to the serial reference, also when a worker
job is killed with SIGKILL mid-run (scancel -s KILL), when a job is killed before its
workers joined, and when the workers retire at their `--lifetime` (the batch walltime's
stand-in) and their jobs are replaced. A cluster that cannot run the session (the batch
system refuses the jobs, the jobs die at once, the workers are gone and the replacement
waits in the queue) ends the submit with one line, not a hang. Run with `-s` to see the
timings.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from store_compare import assert_same_store

pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "deploy" / "slurm" / "local" / "slurm.sh"
CLI = [sys.executable, "-m", "schlieren.workers.cli"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


#: Seconds `slurm.sh start` may take, installing the packages included (6 s here, a few
#: seconds more on a slow mirror); the script bounds each of its own waits too.
START_TIMEOUT = 300


def _start(env: dict) -> tuple[int | None, str]:
    """Run ``slurm.sh start``; its exit code (None if it overran) and its stderr."""
    proc = subprocess.Popen([str(SCRIPT), "start"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=START_TIMEOUT)
        return proc.returncode, err
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the script and the client calls it waits on
        _, err = proc.communicate(timeout=30)
        subprocess.run([str(SCRIPT), "stop"], capture_output=True, text=True, timeout=60, env=env)
        return None, err


@pytest.fixture(scope="module")
def slurm():
    """A running one-node SLURM; yields the environment its clients need.

    With ``SCHLIEREN_SLURM_DIR`` set (``.ci/run`` starts one there) that cluster is used
    and left running; otherwise the tests start their own in a fresh folder, on free
    ports (a SLURM on the default ports may already run here), and stop it at the end.
    """
    if os.name != "posix" or not shutil.which("bash"):
        pytest.skip("SLURM: needs a POSIX shell")
    if os.environ.get("SCHLIEREN_SLURM_FAILED"):  # .ci/run tried and says why
        pytest.fail(f"SLURM: {os.environ['SCHLIEREN_SLURM_FAILED']}", pytrace=False)
    given = os.environ.get("SCHLIEREN_SLURM_DIR")
    # under /tmp, never pytest's tmp folders: they are 0700 and slurmctld runs as the slurm user
    folder = Path(given) if given else Path(tempfile.mkdtemp(prefix="schlieren-slurm-", dir="/tmp"))
    if not given:
        folder.chmod(0o755)
    env = dict(os.environ, SCHLIEREN_SLURM_DIR=str(folder))
    if not given:
        env.update(SCHLIEREN_SLURMCTLD_PORT=str(_free_port()), SCHLIEREN_SLURMD_PORT=str(_free_port()))
    t0 = time.monotonic()
    code, err = _start(env)
    said = " / ".join(err.strip().splitlines()[-3:]) or "(nothing on stderr)"
    if code is None:
        pytest.fail(f"SLURM: slurm.sh start did not end within {START_TIMEOUT} s: {said}", pytrace=False)
    if code == 3:
        pytest.skip(f"SLURM: {said}")
    assert code == 0, f"slurm.sh start exited {code}: {err}"
    print(f"\nSLURM up in {time.monotonic() - t0:.1f} s: {err.strip().splitlines()[-1]}")
    env["SLURM_CONF"] = str(folder / "slurm.conf")
    yield env
    if not given:
        subprocess.run([str(SCRIPT), "stop"], capture_output=True, text=True, timeout=60, env=env)
        shutil.rmtree(folder, ignore_errors=True)


def _jobs(env, states=("RUNNING", "PENDING")) -> list[str]:
    """Job ids of this cluster's jobs in ``states``."""
    out = subprocess.run(["squeue", "-h", "-o", "%i %T"], capture_output=True, text=True, env=env, timeout=30)
    return [line.split()[0] for line in out.stdout.splitlines() if line.split()[1:2] and line.split()[1] in states]


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("tls") / "tls"
    p = subprocess.run(CLI + ["tls", "init", str(d), "--host", "127.0.0.1", "--host", "localhost"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return d


def _config(tmp_path: Path, tls_dir: Path, *, lifetime: str | None = None, wait_timeout: int = 300,
            **schlieren) -> Path:
    """The shipped recipe with the lines a site edits set for this one-node cluster."""
    cfg = yaml.safe_load((ROOT / "deploy" / "slurm" / "jobqueue.yaml").read_text())
    s = cfg["jobqueue"]["slurm"]
    assert s["processes"] > 1, "the shipped job shape runs several worker processes per job"
    s.update(cores=2, processes=2, memory="4GiB", queue="debug", walltime="00:20:00", interface="lo",
             python="python", **{"log-directory": str(tmp_path / "logs"), "local-directory": str(tmp_path)})
    s["job-extra-directives"] = []  # --exclusive: one job per node, and this cluster has one node
    module, dask_config, venv = s["job-script-prologue"]
    assert "command -v module" in module and "DASK_CONFIG" in dask_config and "activate" in venv
    s["job-script-prologue"] = [module, f'export DASK_CONFIG="{ROOT / "deploy" / "config"}"',
                                f'source "{Path(sys.executable).parent / "activate"}"']
    s["scheduler-options"] = {"dashboard_address": "127.0.0.1:0", "interface": "lo"}
    # the workers leave before the walltime, as the recipe's comments ask
    s["worker-extra-args"] = ["--lifetime", lifetime or "15m", "--lifetime-stagger", "2s" if lifetime else "1m"]
    sch = cfg["schlieren"]
    sch["adapt"] = {"minimum": 1, "maximum": 1}
    sch["wait-timeout"] = wait_timeout
    sch["tls"] = {"dir": str(tls_dir)}
    sch.update(schlieren)
    path = tmp_path / "slurm.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


class Submit:
    """``schlieren submit`` in a subprocess, its stderr lines timed as they come."""

    def __init__(self, session, out, config, env):
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(CLI + ["submit", str(session), "--out", str(out), "--cluster", "slurm",
                                            "--config", str(config), "--no-progress"],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        self.lines: list[tuple[float, str]] = []
        self.dashboard: tuple[int, str] | str | None = None  # what the printed link answered
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append((time.monotonic() - self.t0, line.rstrip("\n")))
            if line.startswith("dashboard: http") and self.dashboard is None:
                self.dashboard = _get(line.split()[1].replace("/status", "/health"))

    def now(self) -> float:
        return time.monotonic() - self.t0

    def wait(self, timeout: float = 900) -> int:
        try:
            self.proc.wait(timeout=timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
        self._reader.join(timeout=10)
        self.proc.stdout.close()
        self.ended = self.now()
        return self.proc.returncode

    @property
    def stderr(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def at(self, prefix: str) -> float:
        """Seconds after the start when a stderr line starting with ``prefix`` came."""
        return next(t for t, line in self.lines if line.startswith(prefix))

    def report(self) -> str:
        """Cluster start (first workers joined: the dashboard line), run time, total."""
        store = next(line for _, line in self.lines if line.startswith("store:"))
        run = re.search(r"([\d.]+) s, \S+ executor\)", store).group(1)
        return (f"cluster started (first workers joined) at {self.at('dashboard:'):.1f} s, run {run} s, "
                f"submit ended at {self.ended:.1f} s")


def _get(url: str) -> tuple[int, str] | str:
    """(HTTP status, body) of ``url``, or the error that stopped the request."""
    try:
        with urllib.request.urlopen(url, timeout=10) as resp:
            return resp.status, resp.read().decode(errors="replace")
    except OSError as exc:
        return f"{url}: {exc}"


def _marker_chunks(store: Path) -> int:
    """Completion markers written so far (chunk files under status/, not metadata)."""
    status = store / "status"
    return sum(1 for p in status.rglob("*") if p.is_file() and "c" in p.relative_to(status).parts) \
        if status.exists() else 0


def _job_logs(tmp_path: Path) -> list[Path]:
    return sorted((tmp_path / "logs").glob("*.err"))


def test_submit_gives_the_serial_store_and_quiet_job_logs(slurm, tls_dir, tiny_session, serial_store, tmp_path):
    out = tmp_path / "slurm.zarr"
    run = Submit(tiny_session.session, out, _config(tmp_path, tls_dir), slurm)
    assert run.wait() == 0, run.stderr
    print(f"\nplain run: {run.report()}")
    assert_same_store(serial_store, out)
    assert "Traceback" not in run.stderr
    assert run.dashboard == (200, "ok"), f"the printed dashboard link: {run.dashboard}"
    logs = _job_logs(tmp_path)
    assert logs
    for log in logs:  # the job logs: no tracebacks of a cluster closing under its workers
        text = log.read_text(errors="replace")
        for noise in ("Traceback", "command not found", "still alive after", "CANCELLED"):
            assert noise not in text, f"{log.name}: {noise}\n{text[-3000:]}"


def test_a_killed_worker_job_is_replaced_and_the_run_completes(slurm, tls_dir, tiny_session, serial_store, tmp_path):
    out = tmp_path / "killed.zarr"
    run = Submit(tiny_session.session, out, _config(tmp_path, tls_dir), slurm)
    try:
        # kill the worker job once its workers did some work (markers written)
        while run.proc.poll() is None and _marker_chunks(out) < 3 and run.now() < 600:
            time.sleep(0.2)
        jobs = _jobs(slurm)
        assert run.proc.poll() is None and jobs, "the run ended before a job could be killed"
        subprocess.run(["scancel", "-s", "KILL", *jobs], check=True, env=slurm, timeout=30)
        killed_at, markers = run.now(), _marker_chunks(out)
    finally:
        code = run.wait()
    assert code == 0, run.stderr
    print(f"\nkilled job {', '.join(jobs)} at {killed_at:.1f} s ({markers} markers written); {run.report()}; "
          f"{len(_job_logs(tmp_path))} worker jobs")
    assert len(_job_logs(tmp_path)) >= 2
    assert_same_store(serial_store, out)


def test_a_job_killed_before_its_workers_joined_is_replaced(slurm, tls_dir, tiny_session, serial_store, tmp_path):
    """No worker ever left the scheduler: only the batch system knows the job is gone."""
    out = tmp_path / "early.zarr"
    run = Submit(tiny_session.session, out, _config(tmp_path, tls_dir), slurm)
    try:
        while run.proc.poll() is None and not _jobs(slurm, ("RUNNING",)) and run.now() < 300:
            time.sleep(0.1)
        jobs = _jobs(slurm, ("RUNNING",))
        assert jobs and not any(line.startswith("dashboard:") for _, line in run.lines)
        subprocess.run(["scancel", "-s", "KILL", *jobs], check=True, env=slurm, timeout=30)
        killed_at = run.now()
    finally:
        code = run.wait()
    assert code == 0, run.stderr
    print(f"\njob {', '.join(jobs)} killed at {killed_at:.1f} s before its workers joined; {run.report()}")
    assert_same_store(serial_store, out)


# Seconds. A new worker first spends a few seconds importing and loading numba's compiled
# kernels, so a much shorter lifetime leaves it time for a task or two and the run turns
# into a churn of jobs. The run must outlive its first job's workers on a quiet machine as
# on a loaded one: the session is sized from a measured serial run (below).
LIFETIME = 20
#: Seconds of serial work the lifetime session should take: with the test's two worker
#: processes (two CPUs per job) the cluster run takes longer than LIFETIME on a quiet or loaded
#: machine, so the first job's workers retire mid-run.
SERIAL_TARGET = 50
#: Frames of the lifetime session at most (the tiny session's serial run: about 0.12 s each).
MAX_FRAMES = 480


@pytest.fixture(scope="module")
def longer_session(tmp_path_factory, tiny_spec):
    """The tiny session with enough frames to outlive a LIFETIME on this machine now (its
    serial run timed, then the frames scaled towards SERIAL_TARGET until a run reaches 80 %
    of it: the first, short run's time is dominated by loading compiled kernels), and its
    serial store."""
    from schlieren.workers.run import run_session
    from schlieren.workers.synth import synthesize

    frames = 8
    for _ in range(4):
        res = synthesize(tmp_path_factory.mktemp("longer") / "session", **{**tiny_spec, "frames": frames})
        ref = tmp_path_factory.mktemp("longer-serial") / "store.zarr"
        summary = run_session(res.session, ref, serial=True)
        assert summary.ok
        if summary.seconds >= SERIAL_TARGET * 0.8 or frames >= MAX_FRAMES:
            break
        frames = min(MAX_FRAMES, int(frames * SERIAL_TARGET / max(summary.seconds, 1.0)) + 1)
    print(f"\nlifetime session: {frames} frames, serial run {summary.seconds:.1f} s")
    return res.session, ref


def test_workers_retiring_at_their_lifetime_are_replaced(slurm, tls_dir, longer_session, tmp_path):
    session, serial_store = longer_session
    out = tmp_path / "lifetime.zarr"
    run = Submit(session, out, _config(tmp_path, tls_dir, lifetime=f"{LIFETIME}s"), slurm)
    assert run.wait() == 0, run.stderr
    logs = _job_logs(tmp_path)
    texts = [p.read_text(errors="replace") for p in logs]
    retired = sum("worker-lifetime-reached" in t for t in texts)
    noisy = sum("Traceback" in t for t in texts)
    print(f"\nlifetime {LIFETIME} s: {run.report()}; {len(logs)} worker jobs, {retired} retired at their lifetime, "
          f"{noisy} job log(s) with a traceback")
    for t in texts:  # each traceback: the line before it and its error line (a connection race; see below)
        lines = t.splitlines()
        for i in (i for i, line in enumerate(lines) if line.startswith("Traceback")):
            error = next((x for x in lines[i + 1:] if not x.startswith(" ")), "")
            print(f"  traceback after {lines[i - 1][:160]!r}: {error[:160]}")
    assert len(logs) >= 2 and retired >= 1, "the run should have outlived its first job's workers"
    # retiring workers close once and quietly (worker_setup.close_once and its log filters;
    # a connection race distributed logs with a traceback is counted above, not failed on)
    for noise in ("still alive after", "ConnectionPool is closed", "Invalid Worker.status transition"):
        assert not [p.name for p, t in zip(logs, texts) if noise in t], noise
    assert_same_store(serial_store, out)


def _one_line_failure(run: Submit) -> str:
    lines = [line for _, line in run.lines if line.startswith("schlieren submit: error:")]
    assert run.proc.returncode == 2 and len(lines) == 1, run.stderr
    assert "Traceback" not in run.stderr, run.stderr
    return lines[0]


def test_jobs_the_batch_system_refuses_end_the_submit_with_one_line(slurm, tls_dir, tiny_session, tmp_path):
    cfg = _config(tmp_path, tls_dir, wait_timeout=None, **{"stall-timeout": 20})
    data = yaml.safe_load(cfg.read_text())
    data["jobqueue"]["slurm"]["queue"] = "nosuchpartition"
    cfg.write_text(yaml.safe_dump(data))
    run = Submit(tiny_session.session, tmp_path / "refused.zarr", cfg, slurm)
    run.wait(300)
    line = _one_line_failure(run)
    print(f"\nrefused jobs: ended at {run.ended:.1f} s: {line}")
    assert "for 20 s (schlieren.stall-timeout)" in line and "invalid partition" in line, line


def test_jobs_pending_for_good_end_the_submit_with_one_line(slurm, tls_dir, tiny_session, tmp_path):
    """A job asking for more cores than any node has is accepted and pends for
    ``PartitionConfig`` forever: the watch reads squeue's reason and ends the submit."""
    cfg = _config(tmp_path, tls_dir, wait_timeout=None, **{"stall-timeout": 20})
    data = yaml.safe_load(cfg.read_text())
    data["jobqueue"]["slurm"]["cores"] = 64
    cfg.write_text(yaml.safe_dump(data))
    run = Submit(tiny_session.session, tmp_path / "held.zarr", cfg, slurm)
    run.wait(300)
    line = _one_line_failure(run)
    print(f"\njobs pending for good: ended at {run.ended:.1f} s: {line}")
    assert "pending for 20 s (schlieren.stall-timeout)" in line and "PartitionConfig" in line, line
    assert _jobs(slurm) == [], "closing the cluster cancels its pending job"


def test_jobs_that_die_at_once_end_the_submit_with_one_line(slurm, tls_dir, tiny_session, tmp_path):
    cfg = _config(tmp_path, tls_dir, wait_timeout=None)
    data = yaml.safe_load(cfg.read_text())
    data["jobqueue"]["slurm"]["python"] = "/bin/false"  # the worker command fails at once
    cfg.write_text(yaml.safe_dump(data))
    run = Submit(tiny_session.session, tmp_path / "dying.zarr", cfg, slurm)
    run.wait(600)
    line = _one_line_failure(run)
    print(f"\njobs dying at once: ended at {run.ended:.1f} s: {line}")
    assert "3 worker jobs in a row ended before any of their workers joined" in line, line
    assert f"see their logs in {tmp_path / 'logs'}" in line, line


def test_workers_gone_longer_than_wait_timeout_end_the_submit_with_one_line(slurm, tls_dir, tiny_session, tmp_path):
    """wait-timeout is not only the first wait: the job is killed mid-run and its
    replacement cannot start (the partition is down)."""
    out = tmp_path / "gone.zarr"
    run = Submit(tiny_session.session, out, _config(tmp_path, tls_dir, wait_timeout=25), slurm)
    partition = ["scontrol", "update", "PartitionName=debug"]
    try:
        while run.proc.poll() is None and _marker_chunks(out) < 3 and run.now() < 600:
            time.sleep(0.2)
        subprocess.run(partition + ["State=DOWN"], check=True, env=slurm, timeout=30)
        jobs = _jobs(slurm)
        subprocess.run(["scancel", "-s", "KILL", *jobs], check=True, env=slurm, timeout=30)
        killed_at = run.now()
        run.wait(600)
    finally:
        subprocess.run(partition + ["State=UP"], env=slurm, timeout=30)
    line = _one_line_failure(run)
    print(f"\nworkers gone at {killed_at:.1f} s, replacement held: ended at {run.ended:.1f} s: {line}")
    assert "no worker for 25 s (schlieren.wait-timeout)" in line and "1 worker job(s) pending" in line, line
    assert _jobs(slurm) == [], "closing the cluster cancels its pending job"


# --------------------------------------------------------------------------------------
# slurm.sh start itself: it ends, within seconds, with one line saying why, whatever goes
# wrong (CI once waited 900 s on it with no output: its folder was under pytest's 0700
# tmp folder, slurmctld died at once, and each sinfo against the dead controller blocked)
# --------------------------------------------------------------------------------------
def _start_here(tmp_path: Path, folder: Path, fake: dict[str, str] | None = None, **env) -> tuple[int, str, float]:
    """``slurm.sh start`` on free ports with ``fake`` commands first on PATH; its exit
    code, stderr and wall time. Skips where SLURM cannot be installed or started at all."""
    if os.name != "posix" or os.geteuid() != 0:
        pytest.skip("slurm.sh start: needs root")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    for name, body in (fake or {}).items():
        (bin_dir / name).write_text(f"#!/bin/bash\n{body}\n")
        (bin_dir / name).chmod(0o755)
    e = dict(os.environ, PATH=f"{bin_dir}:{os.environ['PATH']}", SCHLIEREN_SLURM_DIR=str(folder),
             SCHLIEREN_SLURMCTLD_PORT=str(_free_port()), SCHLIEREN_SLURMD_PORT=str(_free_port()), **env)
    t0 = time.monotonic()
    code, err = _start(e)
    took = time.monotonic() - t0
    subprocess.run([str(SCRIPT), "stop"], capture_output=True, text=True, timeout=60, env=e)
    assert code is not None, f"slurm.sh start did not end within {START_TIMEOUT} s: {err}"
    if code == 3 and ("installing" in err or "needs root" in err or "apt-get" in err):
        pytest.skip(f"SLURM: {err.strip().splitlines()[-1]}")
    return code, err, took


def _no_daemon_of(folder: Path) -> bool:
    """No process names ``folder`` and none of its pid files names a live process."""
    ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True, timeout=30).stdout
    for pid_file in (folder / "run").glob("*.pid"):
        status = Path(f"/proc/{pid_file.read_text().strip()}/status")
        if status.exists() and "\nState:\tZ" not in status.read_text():
            return False
    return str(folder) not in ps


def test_start_refuses_a_folder_the_slurm_user_cannot_reach(tmp_path):
    private = tmp_path / "private"
    private.mkdir(mode=0o700)
    folder = private / "slurm"
    code, err, took = _start_here(tmp_path, folder)
    print(f"\nfolder under a 0700 folder: exit {code} after {took:.1f} s: {err.strip()}")
    assert code == 3 and len(err.strip().splitlines()) == 1, err
    assert f"the slurm user cannot write {folder}/state" in err and "SCHLIEREN_SLURM_DIR" in err, err
    assert took < 30 and _no_daemon_of(folder)


def _public_folder() -> Path:
    folder = Path(tempfile.mkdtemp(prefix="schlieren-slurm-", dir="/tmp"))
    folder.chmod(0o755)
    return folder


def test_a_controller_that_dies_is_reported_at_once_with_its_last_log_line(tmp_path):
    folder = _public_folder()
    try:
        code, err, took = _start_here(tmp_path, folder, {
            "slurmctld": 'echo "slurmctld: fatal: Unable to stat state save loc: it is gone" >&2; exit 1',
            "slurmd": f'echo $$ > {folder}/run/slurmd.pid; exec -a "slurmd $*" sleep 300'})
        print(f"\ncontroller dying: exit {code} after {took:.1f} s: {err.strip()}")
        assert code == 3 and "slurmctld exited after" in err and "fatal: Unable to stat state save loc" in err, err
        assert took < 20 and _no_daemon_of(folder), "the start is over at once and leaves no daemon"
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def test_a_controller_that_does_not_answer_ends_the_start_after_its_wait(tmp_path):
    folder = _public_folder()
    try:
        code, err, took = _start_here(tmp_path, folder, {
            "slurmctld": f'echo $$ > {folder}/run/slurmctld.pid; exec -a "slurmctld $*" sleep 300',
            "slurmd": f'echo $$ > {folder}/run/slurmd.pid; exec -a "slurmd $*" sleep 300',
            "sinfo": "exec sleep 300"},  # each call blocks, as against a controller that hangs
            SCHLIEREN_SLURM_WAIT="4", SCHLIEREN_SLURM_CALL_TIMEOUT="1")
        print(f"\ncontroller not answering: exit {code} after {took:.1f} s: {err.strip()}")
        assert code == 3 and "the node did not come up within 4 s" in err, err
        assert took < 20 and _no_daemon_of(folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
