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


# -- stores on S3: the lease object, with conditional requests (moto's server) ---------------

def _s3_lease_info(url):
    import fsspec

    return json.loads(fsspec.open(url + ".lease", "rb").open().read())


def _age_s3_lease(url, **info):
    """Replace the lease object by one from a holder on another host, last touched long ago
    (moto cannot backdate LastModified: the test's clock moves forward instead)."""
    import fsspec

    with fsspec.open(url + ".lease", "wb") as f:
        f.write(json.dumps({"host": "elsewhere.example", "pid": 1, "token": "x", "purpose": "run",
                            "started": "then", **info}).encode())


def test_a_store_on_s3_has_one_writer(s3_server, monkeypatch):
    from schlieren.storage.lease import ObjectStoreLease, lease_for

    url = s3_server.bucket("lease") + "/run.zarr"
    lease = lease_for(url)
    assert isinstance(lease, ObjectStoreLease)
    with lease:
        info = _s3_lease_info(url)
        assert info["pid"] == os.getpid() and info["token"] == lease.token
        with pytest.raises(LeaseError) as err:
            ObjectStoreLease(url).acquire()
        msg = str(err.value)
        assert "another run is writing this store" in msg and f"pid {os.getpid()}" in msg and "\n" not in msg
    import fsspec

    fs = fsspec.filesystem("s3")
    assert not fs.exists(url.removeprefix("s3://") + ".lease")
    # a holder on another host: refused while it is fresh, taken over once silent
    _age_s3_lease(url)
    with pytest.raises(LeaseError, match="host elsewhere.example"):
        ObjectStoreLease(url, timeout=60).acquire()
    real = time.time
    monkeypatch.setattr(time, "time", lambda: real() + 120)
    with ObjectStoreLease(url, timeout=60) as taker:
        assert _s3_lease_info(url)["token"] == taker.token
    monkeypatch.setattr(time, "time", real)


def test_racing_takers_of_a_stale_s3_lease_cannot_both_win(s3_server, monkeypatch):
    """Both see the same stale lease; the conditional PUT on its ETag lets only one replace it."""
    from schlieren.storage.lease import ObjectStoreLease

    url = s3_server.bucket("lease") + "/run.zarr"
    _age_s3_lease(url)
    a, b = ObjectStoreLease(url, timeout=0), ObjectStoreLease(url, timeout=60)
    data, etag, _ = b._head()  # b reads the stale lease ...
    a.acquire()  # ... a takes it over meanwhile
    try:
        original = b._head
        calls = []

        def stale_view():  # b's first look is the lease it saw (silent for 1000 s) before a replaced it
            calls.append(1)
            return (data, etag, 1000.0) if len(calls) == 1 else original()
        monkeypatch.setattr(b, "_head", stale_view)
        # b's takeover is conditional on the stale lease's ETag: refused; b re-reads a's fresh
        # lease and gives up (an unconditional PUT would have replaced a's lease)
        with pytest.raises(LeaseError, match="another run is writing this store"):
            b.acquire()
        assert _s3_lease_info(url)["token"] == a.token and len(calls) == 2
    finally:
        a.release()


def test_the_s3_holder_keeps_its_lease_and_notices_a_takeover(s3_server, caplog):
    from schlieren.storage.lease import ObjectStoreLease

    url = s3_server.bucket("lease") + "/run.zarr"
    lease = ObjectStoreLease(url, heartbeat=0.05).acquire()
    try:
        first = lease._etag
        time.sleep(0.5)
        assert lease._etag != first  # rewritten by the heartbeat (conditional on its own ETag)
        _age_s3_lease(url)  # someone else replaced it
        with caplog.at_level("ERROR", logger="schlieren.storage.lease"):
            time.sleep(0.5)
        assert "was taken over by elsewhere.example" in caplog.text
    finally:
        lease.release()
    assert _s3_lease_info(url)["host"] == "elsewhere.example"  # release never deletes another's lease


def test_the_lease_is_keyed_by_the_resolved_path(tmp_path):
    """Two runs on one store through a symbolic link (to the store, or to a folder above
    it): the second is refused."""
    store = tmp_path / "real" / "run.zarr"
    store.mkdir(parents=True)
    (tmp_path / "link.zarr").symlink_to(store)
    (tmp_path / "alias").symlink_to(tmp_path / "real")
    assert lease_path(tmp_path / "link.zarr") == lease_path(store) == lease_path(tmp_path / "alias" / "run.zarr")
    with StoreLease(store):
        for other in (tmp_path / "link.zarr", tmp_path / "alias" / "run.zarr"):
            with pytest.raises(LeaseError, match="another run is writing this store"):
                StoreLease(other).acquire()
    with StoreLease(tmp_path / "link.zarr"):  # and the other way round
        with pytest.raises(LeaseError):
            StoreLease(store).acquire()
