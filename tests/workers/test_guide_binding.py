"""deploy/GUIDE.md: the scheduler and worker commands it gives bind every listener to the
interface they name and no dashboard beyond loopback. The guide's own commands are run,
with the placeholders set to 127.0.0.1, and the processes' listening sockets inspected."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from conftest import _kill_group, subprocess_env  # tests/workers/conftest.py

GUIDE = Path(__file__).resolve().parents[2] / "deploy" / "GUIDE.md"


def _guide_commands(prog: str) -> list[str]:
    """Every ``dask scheduler`` / ``dask worker`` command in the guide's code blocks."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", GUIDE.read_text(), re.S):
        text = block.replace("\\\n", " ")
        for line in text.splitlines():
            line = line.split("#", 1)[0].strip()
            if line.startswith(f"dask {prog}"):
                out.append(" ".join(line.split()))
    return out


def test_every_guide_worker_command_names_its_interface_and_no_open_dashboard():
    workers = _guide_commands("worker")
    assert workers
    for cmd in workers:
        assert "--host" in cmd or "--interface" in cmd or "--listen-address" in cmd, cmd
        # the worker's HTTP server runs even with --no-dashboard: it must bind loopback
        assert re.search(r"--dashboard-address 127\.0\.0\.1", cmd), cmd
    for cmd in _guide_commands("scheduler"):
        assert "--host" in cmd or "--interface" in cmd, cmd
        assert re.search(r"--dashboard-address 127\.0\.0\.1", cmd), cmd


def _listeners(pids) -> list[tuple[str, int]]:
    out = []
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind="inet")
        except psutil.NoSuchProcess:
            continue
        out += [(c.laddr.ip, c.laddr.port, psutil.Process(pid).cmdline()[-6:]) for c in conns if c.status == psutil.CONN_LISTEN]
    return out


@pytest.mark.system
@pytest.mark.timeout(120)
def test_the_guides_scheduler_and_worker_listen_on_the_named_interface_only(tmp_path):
    sched_cmd = _guide_commands("scheduler")[0]
    worker_cmd = _guide_commands("worker")[0]
    sched_file = tmp_path / "scheduler.json"
    sched_args = shlex.split(sched_cmd.replace("SERVER", "127.0.0.1"))[2:]
    sched_args = [a.replace("127.0.0.1:8787", "127.0.0.1:0") for a in sched_args]  # no fixed ports in tests
    env = subprocess_env()
    procs = []
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", *sched_args,
                                       "--port", "0", "--scheduler-file", str(sched_file), "--no-show"],
                                      env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      start_new_session=True))
        deadline = time.monotonic() + 60
        while not sched_file.exists() or not sched_file.read_text().strip():
            assert time.monotonic() < deadline and procs[0].poll() is None
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        args = shlex.split(worker_cmd.replace("tcp://SERVER:8786", address).replace("WORKER", "127.0.0.1"))[2:]
        args = ["1" if prev == "--nworkers" else a for prev, a in zip([""] + args, args)]  # one is enough
        args = ["1GiB" if prev == "--memory-limit" else a for prev, a in zip([""] + args, args)]
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", *args,
                                       "--local-directory", str(tmp_path / "w")], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True))
        from distributed import Client

        with Client(address, timeout=30) as client:
            client.wait_for_workers(1, timeout=60)
        family = [p.pid for p in procs]
        for p in procs:
            family += [c.pid for c in psutil.Process(p.pid).children(recursive=True)]
        worker_side = [p.pid for p in psutil.Process(procs[1].pid).children(recursive=True)] + [procs[1].pid]
        listening = _listeners(family)
        bad = [x for x in listening if x[0] != "127.0.0.1"]
        assert listening and not bad, "\n".join(map(str, bad))
        # the worker side: the nanny's and the worker's comms and the worker's HTTP endpoint
        assert len(_listeners(worker_side)) == 3, _listeners(worker_side)
    finally:
        for p in reversed(procs):
            _kill_group(p)
