"""Diagnostics: -v lines naming stage/camera/frame, warnings with a likely cause, Ctrl-C."""

from __future__ import annotations

import shutil

import cv2
import numpy as np

import pytest

from schlieren.workers.diagnostics import diagnose


def test_warnings_name_camera_frames_and_a_likely_cause():
    receipts = ([{"stage": "hull", "frame": f, "voxels": 95} for f in (10, 11)]
                + [{"stage": "hull", "frame": 12, "voxels": 0}, {"stage": "hull", "frame": 13, "voxels": 40}]
                + [{"stage": "mask", "camera": "cam02", "frame": f, "fraction": 0.8} for f in range(20, 31)]
                + [{"stage": "mask", "camera": "cam01", "frame": 20, "fraction": 0.1}]
                + [{"stage": "deflection", "camera": "cam03", "frame": 7, "max_px": 9.5},
                   {"stage": "deflection", "camera": "cam03", "frame": 8, "max_px": 0.4},
                   {"stage": "hull", "frame": 14, "voxels": 100, "skipped": True}])
    w = diagnose(receipts, n_voxels=100)
    assert len(w) == 4, w
    assert w[0].startswith("frames 10, 11: the visual hull fills") and "camera moved" in w[0]
    assert w[1].startswith("frame 12: the visual hull is empty")
    assert w[2].startswith("camera cam02, frames 20, 21, 22, 23, 24, 25, 26, 27 (and 3 more): the flow mask")
    assert w[3].startswith("camera cam03, frame 7: deflections up to 9.5 px") and "bumped" in w[3]
    assert diagnose([{"stage": "hull", "frame": 1, "voxels": 40}], n_voxels=100) == []


def test_camera_motion_warned_once_per_camera_with_its_frames():
    from schlieren.pipeline.capture import FALLBACK, MOTION_APPLIED

    receipts = ([{"stage": "deflection", "camera": "cam01", "frame": f, "motion_px": 0.2 * f,
                  "capture_flags": MOTION_APPLIED} for f in range(1, 6)]
                + [{"stage": "deflection", "camera": "cam02", "frame": 3, "motion_px": 0.1,
                    "capture_flags": FALLBACK | MOTION_APPLIED}])
    w = diagnose(receipts, n_voxels=100, motion_warning=0.5)
    assert len(w) == 2, w
    assert w[0].startswith("camera cam01, frames 3, 4, 5: the background moved by up to 1 px") and "0.5 px" in w[0]
    assert w[1].startswith("camera cam02, frame 3: less of the image sees the background")
    assert diagnose(receipts[:1], n_voxels=100, motion_warning=0.5) == []
    assert len(diagnose(receipts, n_voxels=100)) == 1  # no threshold: only the fallback


def test_a_moved_camera_is_named_in_a_warning(tiny_session, tmp_path):
    """cam01's reference shifted by 8 pixels (the camera was bumped after recording it)."""
    from schlieren.workers.run import run_session

    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess, ignore=shutil.ignore_patterns("truth.zarr"))
    ref = sess / "cam01" / "reference.png"
    img = cv2.imread(str(ref), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(ref), np.roll(img, 8, axis=1))
    summary = run_session(sess, tmp_path / "out.zarr", serial=True)
    assert summary.ok
    named = [w for w in summary.warnings if w.startswith("camera cam01")]
    assert named and any("bumped" in w or "moved" in w for w in named), summary.warnings
    assert not any(w.startswith("camera cam00") for w in summary.warnings)


def test_verbose_lines_say_which_stage_camera_and_frame(tiny_session, serial_store, tmp_path, capsys):
    from schlieren.storage.store import ResultStore
    from schlieren.workers.cli import main

    store = tmp_path / "s.zarr"
    shutil.copytree(serial_store, store)
    st = ResultStore.open(store)
    frames = [int(v) for v in st.read("frame")]
    for k in range(len(frames)):
        st.unmark("integrate", k)
    assert main(["-v", "run", str(tiny_session.session), "--out", str(store), "--serial", "--no-progress"]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "schlieren.receipts" in ln]
    assert len(lines) == len(frames)
    for f, ln in zip(frames, lines):
        assert ln.startswith("INFO schlieren.receipts: task receipt: stage integrate, frame ") and f"frame {f}," in ln


@pytest.mark.system
def test_ctrl_c_on_a_local_cluster_prints_one_line_and_keeps_the_chunks(tiny_session, serial_store, tmp_path):
    """SIGINT to the whole process group (what a terminal's Ctrl-C does): no worker
    tracebacks, the one-line message, exit 130, and the rerun completes the same store."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from store_compare import assert_same_store

    out = tmp_path / "run.zarr"
    p = subprocess.Popen([sys.executable, "-m", "schlieren.workers.cli", "run", str(tiny_session.session),
                          "--out", str(out), "--workers", "2", "--no-progress"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not list((out / "status" / "deflection").glob("c/*/*")):
            time.sleep(0.05)
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("dashboard:")] == \
        ["schlieren run: interrupted; completed chunks are kept"]
    from schlieren.workers.run import run_session

    assert run_session(tiny_session.session, out, serial=True).ok
    assert_same_store(serial_store, out)


def test_submit_dry_run_needs_no_certificates(tmp_path, capsys):
    from pathlib import Path

    import yaml

    from schlieren.workers.cli import main

    repo = Path(__file__).resolve().parents[2]
    cfg = yaml.safe_load((repo / "deploy" / "slurm" / "jobqueue.yaml").read_text())
    cfg["schlieren"]["tls"] = {"dir": str(tmp_path / "no-certs-yet")}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["submit", str(tmp_path / "s"), "--out", str(tmp_path / "o.zarr"), "--cluster", "slurm",
                 "--config", str(tmp_path / "c.yaml"), "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert f"--tls-ca-file {tmp_path / 'no-certs-yet' / 'ca.pem'}" in captured.out
    assert "not found yet" in captured.err and "schlieren tls init" in captured.err


def test_cryptography_is_a_main_dependency():
    from importlib.metadata import requires

    reqs = [r for r in requires("schlieren") if r.startswith("cryptography")]
    assert reqs and not any("extra ==" in r for r in reqs)


def test_a_ctrl_c_dropped_on_its_way_still_stops_the_run(monkeypatch, capsys, tiny_session, tmp_path):
    """Python drops a KeyboardInterrupt raised in a garbage-collection callback ("Exception
    ignored"). The watched Ctrl-C is remembered: the executors' loops stop at the next task
    and main ends with the one line and 130; a command that never checks keeps its exit code."""
    import os
    import signal

    from schlieren.workers import cli, interrupts
    from schlieren.workers.run import run_session

    def swallow_ctrl_c():
        try:
            os.kill(os.getpid(), signal.SIGINT)  # what a terminal's Ctrl-C does
            for _ in range(1000):
                pass
        except KeyboardInterrupt:
            pass  # lost, as in a GC callback

    ran = []

    def a_run(args):
        swallow_ctrl_c()
        store = tmp_path / "run.zarr"
        run_session(tiny_session.session, store, serial=True,
                    on_receipt=lambda r: ran.append(r))  # the serial loop checks before each task
        return 0

    # Python's own Ctrl-C handler, as in a fresh `schlieren` process (another test's import,
    # dask_jobqueue's runner, may have replaced it in this one)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        monkeypatch.setattr(cli, "build_parser", lambda: _one_command_parser(a_run))
        assert cli.main(["probe"]) == 130
        assert ran == []  # stopped before the first task
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
        assert not interrupts.seen()
        err = capsys.readouterr().err
        assert err.strip().splitlines()[-1] == "schlieren probe: interrupted; completed chunks are kept"
        assert "Traceback" not in err
        # without a check after it, the command's own code comes back
        monkeypatch.setattr(cli, "build_parser", lambda: _one_command_parser(lambda a: (swallow_ctrl_c(), 3)[1]))
        assert cli.main(["probe"]) == 3
    finally:
        signal.signal(signal.SIGINT, before)


def _one_command_parser(func):
    import argparse

    p = argparse.ArgumentParser(prog="schlieren")
    p.add_argument("-v", "--verbose", action="count", default=0)
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("probe").set_defaults(func=func)
    return p


def test_worker_log_filter_drops_a_dying_peer_only_after_ctrl_c(monkeypatch):
    """The local workers' filter keeps every error before a Ctrl-C; after it, it drops the
    two ends of a transfer cut by the cluster closing (the sender's and the receiver's
    errors, the latter seen with a traceback in a CI run) and nothing else."""
    import logging

    from schlieren.workers.cluster import interrupts as cluster

    def rec(msg, level=logging.ERROR):
        return logging.LogRecord("distributed.worker", level, __file__, 1, msg, None, None)

    f = cluster._AfterCtrlC()
    monkeypatch.setattr(cluster._AfterCtrlC, "interrupted", False)
    died = rec("Worker stream died during communication: tcp://127.0.0.1:43183")
    sent = rec("failed during get data with tcp://127.0.0.1:1 -> tcp://127.0.0.1:2")
    other = rec("Compute Failed")
    assert f.filter(died) and f.filter(sent) and f.filter(other)
    monkeypatch.setattr(cluster._AfterCtrlC, "interrupted", True)
    assert not f.filter(died) and not f.filter(sent)
    assert f.filter(other) and f.filter(rec("Worker stream died during communication", logging.INFO))


def test_distributeds_failed_cancel_after_a_ctrl_c_is_not_printed(monkeypatch):
    """distributed's ``sync`` cancel callback can raise NameError when the Ctrl-C lands
    before its future exists; tornado logs it with a traceback (it failed a CI run of the
    Ctrl-C test above). After a watched Ctrl-C that record is dropped; before one, and any
    other record, still reaches the handlers."""
    import functools
    import logging
    import signal
    import threading

    from schlieren.workers import interrupts

    monkeypatch.setattr(interrupts, "_EVER", threading.Event())  # no Ctrl-C yet in this process
    got = []

    class Keep(logging.Handler):
        def emit(self, record):
            got.append(record.getMessage())

    log = logging.getLogger("tornado.application")
    handler = Keep()
    log.addHandler(handler)

    def sync():
        def cancel():
            pass
        return cancel

    cancel = functools.partial(sync())
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with interrupts.watch():
            log.error("Exception in callback %r", cancel)  # no Ctrl-C yet: printed
            try:
                interrupts._handler(signal.SIGINT, None)  # what the watched Ctrl-C runs
            except KeyboardInterrupt:
                pass
            log.error("Exception in callback %r", cancel)  # the race after a Ctrl-C: dropped
            log.error("Exception in callback %r", "something else")  # other errors: printed
        log.error("Exception in callback %r", cancel)  # later, on distributed's loop thread: dropped
    finally:
        signal.signal(signal.SIGINT, before)
        log.removeHandler(handler)
    assert len(got) == 2 and "sync.<locals>.cancel" in got[0] and "something else" in got[1], got


def test_batched_comm_closed_after_ctrl_c_is_not_printed():
    """The scheduler's (client process) and a worker's batched stream to a peer the Ctrl-C
    closes log "Batched Comm Closed" with a CommClosedError traceback at INFO (it failed one
    CI run of the Ctrl-C test above): dropped after the Ctrl-C, kept before it; other
    records of the logger kept."""
    import logging
    import signal

    from schlieren.workers import interrupts
    from schlieren.workers.cluster.interrupts import _AfterCtrlC

    def record(msg):
        return logging.LogRecord("distributed.batched", logging.INFO, __file__, 1, msg, (), None)

    closed = "Batched Comm Closed <TCP (closed)  local=tcp://127.0.0.1:1 remote=tcp://127.0.0.1:2>"
    worker_filter = _AfterCtrlC()
    before = _AfterCtrlC.interrupted
    try:
        _AfterCtrlC.interrupted = False
        assert worker_filter.filter(record(closed))
        _AfterCtrlC.interrupted = True
        assert not worker_filter.filter(record(closed)) and worker_filter.filter(record("something else"))
    finally:
        _AfterCtrlC.interrupted = before

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with interrupts.watch():
            try:
                interrupts._handler(signal.SIGINT, None)  # what the watched Ctrl-C runs
            except KeyboardInterrupt:
                pass
            flt = [f for f in logging.getLogger("distributed.batched").filters
                   if isinstance(f, interrupts._SyncCancelAfterCtrlC)]
            assert flt and not flt[0].filter(record(closed)) and flt[0].filter(record("something else"))
    finally:
        signal.signal(signal.SIGINT, previous)


def test_flash_lit_frames_get_no_deflection_warning():
    """The strobe flash lights frames the sync already excludes: their large deflections
    are the flash, not a bumped camera."""
    receipts = [{"stage": "deflection", "camera": "cam03", "frame": f, "max_px": 46.0} for f in (3, 4)] + \
               [{"stage": "deflection", "camera": "cam01", "frame": 3, "max_px": 40.0}]
    w = diagnose(receipts, n_voxels=100, flash_frames={"cam03": (3, 4), "cam01": (-1, -1)})
    assert len(w) == 1 and w[0].startswith("camera cam01, frame 3: deflections up to 40 px"), w


_SCRIPT = '''import schlieren

{body}
'''


def _run_script(tmp_path, name, body):
    import subprocess
    import sys

    script = tmp_path / name
    script.write_text(_SCRIPT.format(body=body))
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)


def test_a_script_without_the_main_guard_stops_with_one_line(tiny_session, tmp_path):
    """schlieren.run(..., workers=2) at the top level of a plain script: the spawned workers
    import the script again and start clusters of their own (before: ~500 lines of worker
    tracebacks ending in "Nanny failed to start"). It stops at once with one line naming the
    guard, before any worker starts or anything is written."""
    out = tmp_path / "unguarded.zarr"
    p = _run_script(tmp_path, "plain.py", f"ds = schlieren.run({str(tiny_session.session)!r}, {str(out)!r}, "
                                          "workers=2, progress=False)\nprint(ds)")
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1, p.stderr[-3000:]
    assert len(lines) == 1 and "Traceback" not in p.stderr, p.stderr[-3000:]
    assert 'if __name__ == "__main__":' in lines[0] and "plain.py, line 3" in lines[0], lines[0]
    assert not out.exists()


@pytest.mark.system  # starts a local Dask cluster
def test_a_script_with_the_main_guard_runs(tiny_session, serial_store, tmp_path):
    from store_compare import assert_same_store

    out = tmp_path / "guarded.zarr"
    body = (f"def main():\n    schlieren.run({str(tiny_session.session)!r}, {str(out)!r}, workers=2, progress=False)\n\n\n"
            "if __name__ == \"__main__\":\n    main()")
    p = _run_script(tmp_path, "guarded.py", body)
    assert p.returncode == 0, p.stderr[-3000:]
    assert_same_store(serial_store, out)
