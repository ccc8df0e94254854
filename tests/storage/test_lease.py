"""One writer per store (storage/lease.py): a live holder refuses others with one line; a
holder that is gone (killed on this host, or silent past the timeout) is taken over."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import pytest

from schlieren.storage.lease import LeaseError, StoreLease, lease_path


def _fake(path, **info):
    lease_path(path).write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "token": "x",
                                            "purpose": "run", "started": "then", **info}))


def test_a_live_holder_refuses_a_second_writer_and_releases(tmp_path):
    store = tmp_path / "run.zarr"
    with StoreLease(store) as lease:
        assert lease_path(store).exists() and lease.held
        info = json.loads(lease_path(store).read_text())
        assert info["pid"] == os.getpid() and info["host"] == socket.gethostname()
        with pytest.raises(LeaseError) as err:
            StoreLease(store).acquire()
        msg = str(err.value)
        assert f"file {store}" in msg and "another run is writing this store" in msg
        assert f"pid {os.getpid()}" in msg and "\n" not in msg
    assert not lease_path(store).exists()
    StoreLease(store).acquire().release()


def test_the_lease_of_a_killed_run_on_this_host_is_taken_over_at_once(tmp_path):
    store = tmp_path / "run.zarr"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _fake(store, pid=dead.pid)
    with StoreLease(store) as lease:
        assert json.loads(lease_path(store).read_text())["token"] == lease.token
    # a pid reused by another process (started at another time) does not hold it either
    _fake(store, pid=os.getpid(), process_start=1.0)
    StoreLease(store).acquire().release()


def test_a_silent_holder_on_another_host_is_taken_over_after_the_timeout(tmp_path):
    store = tmp_path / "run.zarr"
    _fake(store, host="elsewhere.example", pid=1)
    with pytest.raises(LeaseError, match="host elsewhere.example"):
        StoreLease(store, timeout=60).acquire()
    old = time.time() - 120
    os.utime(lease_path(store), (old, old))
    StoreLease(store, timeout=60).acquire().release()
    # an unreadable lease (a writer killed while writing it) also ages out
    lease_path(store).write_text("{not json")
    with pytest.raises(LeaseError):
        StoreLease(store, timeout=60).acquire()
    os.utime(lease_path(store), (old, old))
    StoreLease(store, timeout=60).acquire().release()


def test_the_holder_keeps_its_lease_alive(tmp_path):
    store = tmp_path / "run.zarr"
    with StoreLease(store, heartbeat=0.05):
        old = time.time() - 100
        os.utime(lease_path(store), (old, old))
        time.sleep(0.3)
        assert time.time() - lease_path(store).stat().st_mtime < 5
