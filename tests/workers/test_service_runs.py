"""Real session runs on a separately started scheduler: the distributed service end to end.

Scheduler and workers are subprocesses on 127.0.0.1 (fixture ``external_scheduler``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest
import zarr
from distributed import Client

from schlieren.workers.run import run_session
from store_compare import assert_same_store


def _markers(store, stage) -> int:
    try:
        return int(np.asarray(zarr.open_group(str(store), mode="r")[f"status/{stage}"][...]).sum())
    except Exception:
        return 0


@pytest.mark.timeout(600)
def test_cli_run_on_an_external_scheduler_matches_serial(external_scheduler, tiny_session,
                                                         serial_store, tmp_path):
    out = tmp_path / "ext.zarr"
    proc = subprocess.run([sys.executable, "-m", "schlieren.workers.cli", "run", str(tiny_session.session),
                           "--out", str(out), "--scheduler", external_scheduler.address, "--no-progress",
                           "--report", str(tmp_path / "perf.html"), "--log", str(tmp_path / "run.jsonl")],
                          capture_output=True, text=True, timeout=500)
    assert proc.returncode == 0, proc.stderr + external_scheduler.logs()
    assert "dashboard: http://127.0.0.1:" in proc.stderr
    # --log: one JSON line per stage and index, naming the worker that ran it, then the end
    lines = [json.loads(x) for x in (tmp_path / "run.jsonl").read_text().splitlines()]
    receipts, last = lines[:-1], lines[-1]
    g = zarr.open_group(str(out), mode="r")
    assert len(receipts) == sum(int(np.asarray(m[...]).size) for _, m in g["status"].arrays())
    assert len({(r["stage"], tuple(r["index"])) for r in receipts}) == len(receipts)
    assert all(r["worker"].startswith("tcp://127.0.0.1:") and 0 <= r["cpu_seconds"] for r in receipts)
    solves = [r for r in receipts if r["stage"] == "tomography"]
    assert solves and all(r["iterations"] > 0 and r["residual"] >= 0 for r in solves)
    assert last["message"] == "run finished" and last["failed"] == 0 and last["tasks"] > 0
    # the Dask performance report was written and shows our stages
    perf = (tmp_path / "perf.html").read_text()
    assert "deflection" in perf and "tomography" in perf
    assert "cdn.bokeh.org" not in perf and "Bokeh" in perf  # BokehJS inline: readable offline
    assert_same_store(serial_store, out)
    # the scheduler's dashboard answers and knows our stages by name
    with urllib.request.urlopen(f"{external_scheduler.dashboard_url}/status", timeout=10) as r:
        assert r.status == 200
    with Client(external_scheduler.address, timeout=30) as c:
        prefixes = c.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
    assert {"deflection", "resample", "mask", "hull", "tomography", "integrate"} <= set(prefixes)


@pytest.mark.timeout(600)
def test_a_worker_killed_mid_run_still_gives_the_identical_store(external_scheduler, tiny_session,
                                                                  serial_store, tmp_path):
    out = tmp_path / "chaos.zarr"
    result = {}

    def drive():
        with Client(external_scheduler.address, timeout=30) as client:
            result["summary"] = run_session(tiny_session.session, out, client=client)

    t = threading.Thread(target=drive)
    t.start()
    deadline = time.time() + 300
    while _markers(out, "deflection") < 6 and t.is_alive() and time.time() < deadline:
        time.sleep(0.1)
    assert t.is_alive(), "the run finished before a worker could be killed"
    killed = external_scheduler.kill_worker(0)
    t.join(500)
    assert not t.is_alive()
    summary = result["summary"]
    assert summary.ok, summary.failures
    assert killed not in external_scheduler.worker_pids()  # the nanny started a new worker process
    assert_same_store(serial_store, out)
