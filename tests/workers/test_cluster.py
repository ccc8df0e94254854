"""Cluster setup: local process clusters and separately started schedulers, on 127.0.0.1 only."""

from __future__ import annotations

import json
import logging
import os
import socket
import time

import psutil
import pytest

from schlieren.workers.cluster import (
    THREAD_ENV,
    TOMO,
    ClusterOptions,
    SchlierenWorkerSetup,
    VersionMismatchError,
    check_versions,
    dashboard_link,
    loopback_dashboard_address,
    open_client,
    worker_thread_report,
)
from schlieren.workers.monitoring import JsonFormatter, configure_json_logging, log_receipt

THREAD_VARS = tuple(THREAD_ENV)


def _proc_environ(pid: int) -> dict[str, str]:
    """The environment a process was started with (not later os.environ edits)."""
    raw = open(f"/proc/{pid}/environ", "rb").read().split(b"\0")  # noqa: SIM115
    return dict(item.decode().split("=", 1) for item in raw if b"=" in item)


def _listening_hosts(pids: list[int]) -> set[str]:
    hosts = set()
    for pid in pids:
        for conn in psutil.Process(pid).net_connections(kind="inet"):
            if conn.status == psutil.CONN_LISTEN:
                hosts.add(conn.laddr.ip)
    return hosts


def _interval(seconds: float) -> tuple[float, float]:
    start = time.time()
    time.sleep(seconds)
    return start, time.time()


def _log_one(stage: str) -> int:
    logging.getLogger("schlieren.workers.tasks").info(
        "task done", extra={"stage": stage, "frame": 7, "camera": "cam0", "seconds": 0.25}
    )
    return os.getpid()


def _schlieren_json_handlers() -> int:
    return sum(bool(getattr(h, "_schlieren_json_handler", False)) for h in logging.getLogger("schlieren").handlers)


def _profile_callback_ms(dask_worker) -> float:
    return float(dask_worker.periodic_callbacks["profile"].callback_time)


# ---------------------------------------------------------------------------------------
# local mode


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    log_dir = tmp_path_factory.mktemp("worker-logs")
    opts = ClusterOptions(workers=2, memory_limit="1GiB", dashboard_address="127.0.0.1:0", worker_log_dir=str(log_dir))
    with open_client(opts) as (client, info):
        yield client, info, log_dir


@pytest.mark.timeout(120)
def test_local_cluster_workers_have_thread_caps_and_tomo_slots(local):
    client, info, _ = local
    assert info.mode == "local" and info.n_workers == 2 and info.tomo_slots == 2
    workers = client.scheduler_info(n_workers=-1)["workers"]
    assert all(w["resources"] == {TOMO: 1} and w["nthreads"] == 1 for w in workers.values())
    reports = client.run(worker_thread_report)
    assert len(reports) == 2
    for rep in reports.values():
        assert rep["cv2_threads"] == 1
        assert rep["pid"] != os.getpid()
        # set before the process started (pre-spawn-environ), not patched in afterwards
        started_with = _proc_environ(rep["pid"])
        for var in THREAD_VARS:
            assert started_with.get(var) == THREAD_ENV[var], var
    # the monitoring cadence of DASK_SETTINGS reached the worker processes (profile on,
    # sampled every 50 ms rather than Dask's 10 ms)
    cadence = client.run(_profile_callback_ms)
    assert set(cadence.values()) == {50.0}


@pytest.mark.timeout(120)
def test_local_cluster_listens_on_loopback_only(local):
    client, info, _ = local
    assert info.scheduler_address.startswith("tcp://127.0.0.1:")
    assert info.dashboard_link.startswith("http://127.0.0.1:")
    assert dashboard_link(client) == info.dashboard_link
    pids = [os.getpid(), *(r["pid"] for r in client.run(worker_thread_report).values())]
    hosts = _listening_hosts(pids)
    assert hosts == {"127.0.0.1"}, hosts


@pytest.mark.system
@pytest.mark.timeout(120)
def test_a_taken_dashboard_port_is_no_warning(recwarn, caplog, monkeypatch):
    """The dashboard port is taken when the scheduler binds it (another run, a notebook's
    cluster): the cluster starts on another port without distributed's multi-line
    UserWarning on stderr (on Ctrl-C the run's stderr must stay the one-line message) and
    says so in the log (and in the run's "dashboard:" line, tests/workers/test_dashboard.py)."""
    monkeypatch.setattr(logging.getLogger("schlieren"), "propagate", True)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        opts = ClusterOptions(workers=1, memory_limit="1GiB", dashboard_address=f"127.0.0.1:{port}")
        with caplog.at_level(logging.INFO, logger="schlieren.workers.cluster"), open_client(opts) as (_client, info):
            assert info.dashboard_link.startswith("http://127.0.0.1:")
            assert f":{port}/" not in info.dashboard_link
    assert not [w for w in recwarn if "already in use" in str(w.message)], [str(w.message) for w in recwarn]
    assert any("already in use" in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]


@pytest.mark.timeout(120)
def test_worker_plugin_is_idempotent_and_logs_json(local):
    client, _, log_dir = local
    client.register_plugin(SchlierenWorkerSetup(log_dir=str(log_dir)))  # again: a no-op
    assert set(client.run(_schlieren_json_handlers).values()) == {1}
    pid = client.submit(_log_one, "deflection", key="deflection-log-000000", pure=False).result(timeout=30)
    deadline = time.monotonic() + 10
    lines: list[dict] = []
    while time.monotonic() < deadline and not lines:
        for path in log_dir.glob("*.jsonl"):
            lines += [json.loads(ln) for ln in path.read_text().splitlines() if '"task done"' in ln]
        time.sleep(0.1)
    assert len(lines) == 1, lines
    rec = lines[0]
    assert rec["stage"] == "deflection" and rec["frame"] == 7 and rec["camera"] == "cam0" and rec["seconds"] == 0.25
    assert rec["logger"] == "schlieren.workers.tasks" and rec["level"] == "INFO"
    assert pid != os.getpid()


@pytest.mark.system
@pytest.mark.timeout(120)
def test_tomo_resource_limits_concurrency_per_worker():
    # one worker with two threads but one TOMO slot: TOMO tasks never overlap, plain ones do
    with open_client(ClusterOptions(workers=1, threads_per_worker=2, memory_limit="1GiB", dashboard_address="127.0.0.1:0")) as (
        client,
        info,
    ):
        assert info.tomo_slots == 1
        tomo = client.map(_interval, [0.6, 0.6], key=["tomography-a-000000", "tomography-a-000001"], resources={TOMO: 1})
        a, b = sorted(client.gather(tomo))
        assert b[0] >= a[1] - 1e-3, (a, b)
        plain = client.map(_interval, [0.6, 0.6], key=["plain-a-000000", "plain-a-000001"])
        a, b = sorted(client.gather(plain))
        assert b[0] < a[1], (a, b)  # control: without the resource the two threads overlap


# ---------------------------------------------------------------------------------------
# scheduler mode


@pytest.mark.timeout(120)
def test_external_scheduler_run_and_worker_replacement(external_scheduler):
    cluster = external_scheduler
    assert cluster.address.startswith("tcp://127.0.0.1:")
    with open_client(ClusterOptions(scheduler=cluster.address, connect_timeout=30)) as (client, info):
        assert info.mode == "scheduler" and info.n_workers == 2 and info.tomo_slots == 2
        assert info.dashboard_link == f"http://127.0.0.1:{cluster.dashboard_port}/status"
        keys = [f"deflection-ext-cam0-{i:06d}" for i in range(4)]
        assert client.gather(client.map(lambda i: i * i, range(4), key=keys)) == [0, 1, 4, 9]
        before = client.run(worker_thread_report)
        for rep in before.values():
            assert rep["cv2_threads"] == 1  # the plugin
            started_with = _proc_environ(rep["pid"])  # deploy/config/bos.yaml via DASK_CONFIG
            assert all(started_with.get(v) == THREAD_ENV[v] for v in THREAD_VARS)
        assert set(cluster.worker_pids()) == {r["pid"] for r in before.values()}

        killed = cluster.kill_worker(0)
        killed_addr = next(a for a, r in before.items() if r["pid"] == killed)
        # wait on the scheduler's view (a broadcast to the dead address would retry until timeout)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            workers = client.scheduler_info(n_workers=-1)["workers"]
            if len(workers) == 2 and killed_addr not in workers:
                break
            time.sleep(0.2)
        assert len(workers) == 2 and killed_addr not in workers
        after = client.run(worker_thread_report)
        assert killed not in {r["pid"] for r in after.values()}
        # the replacement worker got the plugin and the thread caps as well
        assert all(r["cv2_threads"] == 1 for r in after.values())
        assert client.submit(sum, [1, 2], key="tomography-ext-000000", resources={TOMO: 1}).result(timeout=30) == 3


def test_cluster_options_validation():
    with pytest.raises(ValueError, match="not both"):
        ClusterOptions(workers=2, scheduler="tcp://127.0.0.1:8786")
    with pytest.raises(ValueError, match="at least 1"):
        ClusterOptions(workers=0)
    with pytest.raises(ValueError, match="certificate directory"):
        ClusterOptions(scheduler="tls://x:1", tls_cert="c.pem")
    assert ClusterOptions().mode == "local" and ClusterOptions(scheduler="tcp://h:1").mode == "scheduler"
    opts = ClusterOptions(scheduler="tls://h:1", tls_dir="/certs", tls_key="/other/k.pem")
    files = opts.client_tls_files()
    assert (str(files.ca_file), str(files.cert), str(files.key)) == ("/certs/ca.pem", "/certs/client.pem", "/other/k.pem")


def test_scheduler_tls_without_certificates_is_a_clear_error():
    with pytest.raises(ValueError, match="--tls DIR"):
        with open_client(ClusterOptions(scheduler="tls://127.0.0.1:9", connect_timeout=2)):
            pass


def test_loopback_dashboard_address():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        # a taken port is kept: the scheduler binds another and the run's line names it
        assert loopback_dashboard_address(f"localhost:{taken}") == f"127.0.0.1:{taken}"
    assert loopback_dashboard_address(":0").startswith("127.0.0.1:")
    assert loopback_dashboard_address("localhost:0").startswith("127.0.0.1:")
    for bad in ("0.0.0.0:8787", "192.168.1.5:8787"):
        with pytest.raises(ValueError, match="loopback"):
            loopback_dashboard_address(bad)


class _FakeVersions:
    def __init__(self, worker_numpy: str) -> None:
        self.worker_numpy = worker_numpy

    def get_versions(self, check: bool, packages: list[str]) -> dict:
        pk = {p: "1.0" for p in packages}
        return {
            "client": {"packages": pk},
            "scheduler": {"packages": pk},
            "workers": {"tcp://w": {"packages": {**pk, "numpy": self.worker_numpy}}},
        }


def test_check_versions_names_the_mismatch():
    assert check_versions(_FakeVersions("1.0"))["workers"]  # type: ignore[arg-type]
    with pytest.raises(VersionMismatchError, match="numpy: client has 1.0, worker tcp://w has 2.0"):
        check_versions(_FakeVersions("2.0"))  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------
# structured logs


def test_json_formatter_and_log_receipt():
    import io

    import numpy as np

    stream = io.StringIO()
    logger = logging.getLogger("schlieren.test-receipts")
    configure_json_logging("schlieren.test-receipts", stream=stream)
    configure_json_logging("schlieren.test-receipts", stream=stream)  # replaces, never duplicates
    assert sum(bool(getattr(h, "_schlieren_json_handler", False)) for h in logger.handlers) == 1
    log_receipt(
        {"stage": "tomography", "index": 3, "frame": np.int64(3), "seconds": np.float32(1.5),
         "iterations": 42, "residual": 1e-4, "name": "clash", "nan": float("nan")},
        logger=logger,
    )
    log_receipt({"stage": "deflection", "camera": "cam1", "frame": 5, "status": "failed", "error": "bad frame"}, logger=logger)
    first, second = (json.loads(line) for line in stream.getvalue().splitlines())
    assert first["message"] == "task receipt" and first["level"] == "INFO"
    assert (first["stage"], first["index"], first["frame"], first["iterations"]) == ("tomography", 3, 3, 42)
    assert first["seconds"] == 1.5 and first["residual"] == 1e-4
    assert first["receipt_name"] == "clash" and first["nan"] == "nan"
    assert list(first)[:4] == ["time", "level", "logger", "message"]
    assert second["level"] == "ERROR" and second["camera"] == "cam1" and second["error"] == "bad frame"
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        logger.exception("failed", extra={"stage": "integrate"})
    third = json.loads(stream.getvalue().splitlines()[2])
    assert third["stage"] == "integrate" and "RuntimeError: boom" in third["exc_info"]
    assert isinstance(JsonFormatter().format(logging.makeLogRecord({"msg": "x"})), str)


def test_run_log_writes_receipts_failures_and_the_end_and_appends(tmp_path):
    from schlieren.workers.monitoring import RunLog

    path = tmp_path / "logs" / "run.jsonl"
    with RunLog(path, session="plume") as rl:
        rl.receipt({"stage": "hull", "index": [1], "frame": 11, "seconds": 0.3, "voxels": 1200})
        rl.failure("deflection-abc-000002-000005", "deflection, camera cam2, frame 5: ValueError: bad frame")
        rl.finished(tasks=2, failed=1)
    with RunLog(path, session="plume") as rl:  # a resumed run appends
        rl.finished(tasks=0, failed=0)
    lines = [json.loads(x) for x in path.read_text().splitlines()]
    assert [x["message"] for x in lines] == ["task receipt", "task failed", "run finished", "run finished"]
    assert all(x["session"] == "plume" for x in lines)
    assert lines[0]["voxels"] == 1200 and lines[0]["level"] == "INFO"
    assert lines[1]["level"] == "ERROR" and lines[1]["stage"] == "deflection" and lines[1]["status"] == "failed"
    assert "camera cam2, frame 5" in lines[1]["error"]
    assert (lines[2]["tasks"], lines[2]["failed"]) == (2, 1)
    # without a path nothing is written and nothing fails
    with RunLog(None) as rl:
        rl.receipt({"stage": "hull"})
        rl.failure("hull-x-000000", "boom")
        rl.finished(tasks=1)
    assert not logging.getLogger("schlieren.run").handlers


# ---------------------------------------------------------------------------------------
# closing a local cluster


def _slow_interpreter_teardown(seconds: float = 8.0) -> int:
    """In a worker: make the process's exit as slow as a loaded machine makes Python's
    interpreter teardown (an exit handler registered now runs after the worker closed)."""
    import atexit

    atexit.register(time.sleep, seconds)
    return os.getpid()


def _executing(dask_worker) -> int:
    return len(dask_worker.state.executing)


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture
def nanny_log():
    """What the nannies (in this process, for a local cluster) log while the test runs."""
    handler = _Records()
    logger = logging.getLogger("distributed.nanny")
    logger.addHandler(handler)
    try:
        yield handler.messages
    finally:
        logger.removeHandler(handler)


@pytest.mark.system
@pytest.mark.timeout(120)
def test_closing_a_local_cluster_does_not_wait_for_the_interpreter_teardown(nanny_log):
    """A closed worker's process ends at once: before, Python tore its interpreter down
    (0.3-0.6 s of CPU, more than the nanny's 4 s on a loaded machine) and the nanny killed
    it with "Worker process still alive after 4.0 seconds, killing" at a normal shutdown."""
    opts = ClusterOptions(workers=2, memory_limit="1GiB", dashboard_address="127.0.0.1:0")
    with open_client(opts) as (client, _info):
        pids = client.run(_slow_interpreter_teardown)
        t0 = time.monotonic()
    closed = time.monotonic() - t0
    assert not [m for m in nanny_log if "still alive" in m], nanny_log
    assert closed < 4.0, closed
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE for p in pids.values())


@pytest.mark.system
@pytest.mark.timeout(120)
def test_after_ctrl_c_workers_do_not_wait_for_their_running_task(nanny_log):
    """A terminal's Ctrl-C reaches the worker processes too; when the client then closes
    the cluster, a worker in the middle of a long task ends at once instead of being killed
    by its nanny after 4 s (and the nanny's warning on the terminal)."""
    import signal

    opts = ClusterOptions(workers=1, memory_limit="1GiB", dashboard_address="127.0.0.1:0")
    with open_client(opts) as (client, _info):
        fut = client.submit(time.sleep, 60, key="sleep-ctrl-c-000000", pure=False)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and sum(client.run(_executing).values()) == 0:
            time.sleep(0.05)
        for pid in client.run(os.getpid).values():
            os.kill(pid, signal.SIGINT)
        time.sleep(0.5)
        del fut
        t0 = time.monotonic()
    closed = time.monotonic() - t0
    assert not [m for m in nanny_log if "still alive" in m], nanny_log
    assert closed < 4.0, closed


def _sleep(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


@pytest.mark.system
@pytest.mark.timeout(180)
def test_workers_retiring_together_at_their_lifetime_log_no_errors(capfd):
    """The worker processes of a batch job retire at about the same time (``--lifetime``):
    distributed aborted the retirements (no worker left to take the data), set the closing
    workers "running" again and closed them a second time, which logged "ConnectionPool is
    closed" with a traceback (and an "Invalid Worker.status transition" error) into the job
    logs. With the worker setup each worker closes once, quietly."""
    from distributed import Client, LocalCluster

    from schlieren.workers.cluster import register_worker_setup

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                      host="127.0.0.1", lifetime="6s", lifetime_stagger="1s", silence_logs=logging.INFO) as cluster, \
            Client(cluster) as client:
        register_worker_setup(client)
        futures = client.map(_sleep, [2.5] * 12, pure=False)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(client.scheduler_info(n_workers=-1)["workers"]) == 2:
            time.sleep(0.2)
        time.sleep(4)  # both retired, their processes gone
        del futures
    err = capfd.readouterr().err
    assert "worker-lifetime-reached" in err
    for noise in ("ConnectionPool is closed", "Invalid Worker.status transition", "Worker process died unexpectedly"):
        assert noise not in err, noise


def test_a_leaving_workers_cut_transfers_are_not_logged(monkeypatch):
    """The two workers of a batch job retire together: the transfer one was serving the
    other breaks, and distributed logs it with tracebacks into the job log. Dropped while
    this process's worker is leaving, kept before."""
    import weakref

    from distributed.core import Status

    from schlieren.workers.cluster import worker_setup

    class FakeWorker:
        status = Status.running

    w = FakeWorker()
    monkeypatch.setattr(worker_setup._WhileLeaving, "worker", weakref.ref(w))

    def record(msg: str) -> logging.LogRecord:
        return logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, msg, (), None)

    cut = record("failed during get data with tls://a:1 -> tls://b:2")
    other = record("Compute Failed")
    leaving = worker_setup._WHILE_LEAVING
    assert leaving.filter(cut) and leaving.filter(other)
    w.status = Status.closing_gracefully
    assert not leaving.filter(cut) and leaving.filter(other)
