"""The tiny session read from and written to a real S3-compatible server (moto on 127.0.0.1).

* a run from a session in a bucket to a store in a bucket equals the folder-store serial
  run bit for bit (every array, and every chunk object's bytes equal the chunk files);
* the same on a two-worker Dask cluster, whose workers read the frames from the bucket
  and stage the tomography geometry from it;
* ``schlieren run`` killed with SIGKILL midway and rerun resumes from the markers in the
  bucket and ends identical;
* ``evaluate``, ``report``, ``export`` and xarray work on the store in the bucket.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import xarray as xr

from schlieren.storage import location
from schlieren.storage.store import ResultStore
from schlieren.workers.run import run_session

from store_compare import assert_same_store, sigkill_when


@pytest.fixture(scope="module")
def s3_session(s3_server, tiny_session):
    """The tiny session uploaded to a bucket: its URL."""
    return s3_server.upload(tiny_session.session.parent, s3_server.bucket("session") + "/tiny")


@pytest.fixture(scope="module")
def s3_run(s3_server, s3_session, tmp_path_factory):
    """The tiny session in the bucket reconstructed serially into a store in a bucket:
    ``(store URL, summary, local staging folder)``."""
    cache = tmp_path_factory.mktemp("stage-cache")
    out = s3_server.bucket("store") + "/serial.zarr"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(location.CACHE_ENV, str(cache))
        summary = run_session(s3_session, out, serial=True)
    return out, summary, cache


def assert_same_chunk_bytes(folder, url) -> None:
    """Every chunk object of the store at ``url`` has the bytes of the folder store's chunk file."""
    files = {str(p.relative_to(folder)).replace(os.sep, "/"): p
             for p in folder.rglob("*") if p.is_file() and p.name != "zarr.json" and "_cache" not in p.parts}
    remote = [k for k in location.find(url) if not k.endswith("zarr.json") and not k.startswith("_cache/")]
    assert sorted(remote) == sorted(files)
    for k in remote:
        assert location.read_bytes(f"{url}/{k}") == files[k].read_bytes(), k


def _markers_set(url: str) -> int:
    return sum(1 for k in location.find(url + "/status") if "/c/" in k)


def test_session_and_store_on_s3_equal_the_folder_run_bit_for_bit(s3_run, s3_session, serial_store):
    out, summary, cache = s3_run
    assert summary.ok, summary.failures
    assert ResultStore.open(out, mode="r").attrs["session_path"] == s3_session + "/session.yaml"
    # the root keeps every array's metadata (one read opens the store) and the run's attributes
    root = json.loads(location.read_bytes(out + "/zarr.json"))
    assert {"refractivity", "status/tomography"} <= set(root["consolidated_metadata"]["metadata"])
    assert "stage_times" in ResultStore.open(out, mode="r").attrs
    assert_same_store(serial_store, out)
    assert_same_chunk_bytes(serial_store, out)
    # the geometry cache lives beside the store in the bucket and was mapped from a staged copy
    assert any(k.startswith("geometry-") and k.endswith("manifest.json") for k in location.find(out + ".cache"))
    assert list(cache.glob("staged/*/manifest.json"))
    # a rerun finds every marker in the bucket and computes nothing
    again = run_session(s3_session, out, serial=True)
    assert again.ok and again.tasks == 0


def test_dask_workers_read_the_session_and_write_the_store_in_the_bucket(s3_server, s3_session, serial_store):
    from schlieren.workers.cluster import ClusterOptions, open_client

    out = s3_server.bucket("store") + "/dask.zarr"
    with open_client(ClusterOptions(workers=2)) as (client, _info):
        summary = run_session(s3_session, out, client=client, frames_per_task=3)
    assert summary.ok, summary.failures
    assert summary.executor == "dask" and len({r["worker"] for r in summary.receipts}) == 2
    assert_same_store(serial_store, out)


class _Counting:
    """``storage.location`` as seen by the frame readers (storage/readers/), recording the listings and reads."""

    def __init__(self, real):
        self._real = real
        self.listed: list[str] = []
        self.read: list[str] = []

    def __getattr__(self, name):
        return getattr(self._real, name)

    def listdir_sizes(self, loc):
        self.listed.append(loc)
        return self._real.listdir_sizes(loc)

    def read_bytes(self, loc, start=None, end=None):
        self.read.append(loc)
        return self._real.read_bytes(loc, start, end)

    def read_many(self, locs, start=None, end=None):
        self.read.extend(locs)
        return self._real.read_many(locs, start, end)


def test_a_serial_run_lists_and_fetches_each_frame_once(s3_server, s3_session, serial_store, monkeypatch, tmp_path):
    """The run's tasks read through the readers that checked the session (Session.opened):
    no second listing of a camera's frames, no second fetch of a frame (each a request)."""
    import importlib
    import pkgutil

    from schlieren.storage import readers

    counting = _Counting(location)
    for info in pkgutil.iter_modules(readers.__path__):  # every reader module's view of storage.location
        mod = importlib.import_module(f"{readers.__name__}.{info.name}")
        if hasattr(mod, "location"):
            monkeypatch.setattr(mod, "location", counting)
    monkeypatch.setenv(location.CACHE_ENV, str(tmp_path / "cache"))
    out = s3_server.bucket("store") + "/once.zarr"
    summary = run_session(s3_session, out, serial=True)
    assert summary.ok, summary.failures
    assert_same_store(serial_store, out)
    framed = [u for u in counting.read if "/frames/" in u]
    assert framed and max(framed.count(u) for u in framed) == 1, sorted(framed)
    assert len(counting.listed) == len(set(counting.listed)) == 4, counting.listed  # one per camera


def test_sigkill_then_rerun_resumes_from_the_bucket_and_matches(s3_server, s3_session, serial_store):
    out = s3_server.bucket("store") + "/killed.zarr"
    cmd = [sys.executable, "-m", "schlieren.workers.cli", "run", s3_session, "--out", out, "--serial",
           "--no-progress"]
    before = sigkill_when(cmd, lambda: _markers_set(out), 30)
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"store: {out}" in proc.stderr and "already complete" in proc.stderr
    skipped = int(proc.stderr.split(" already complete")[0].rsplit(", ", 1)[1])
    assert skipped >= before
    assert_same_store(serial_store, out)
    assert_same_chunk_bytes(serial_store, out)


def test_evaluate_report_export_and_xarray_read_the_store_in_the_bucket(s3_run, serial_store, tiny_session,
                                                                        tmp_path):
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.report import generate_export, make_report

    out = s3_run[0]
    truth = tiny_session.truth
    assert evaluate(out, truth)["overall"] == evaluate(serial_store, truth)["overall"]

    ds = xr.open_zarr(out, consolidated=False)
    ref = xr.open_zarr(serial_store, consolidated=False)
    np.testing.assert_array_equal(ds["refractivity"].values, ref["refractivity"].values)
    assert ds["refractivity"].dims == ("frame", "z", "y", "x")
    import schlieren

    api = schlieren.open(out)  # the Python API, through the consolidated metadata in the bucket
    np.testing.assert_array_equal(api["temperature"].values, ref["temperature"].values)

    index = make_report(out, tmp_path / "report")
    page = index.read_text()
    # the camera frames shown were read from the session in the bucket
    assert out in page and "(%05d.png, capture frame" in page and "not readable" not in page

    res = generate_export(out, tmp_path / "raw", format="raw", quantity="density")
    ref_res = generate_export(serial_store, tmp_path / "raw_ref", format="raw", quantity="density")
    assert [p.name for p in res.files] == [p.name for p in ref_res.files]
    for a, b in zip(res.files, ref_res.files):
        assert a.read_bytes() == b.read_bytes() or a.suffix == ".mhd"


def test_a_second_writer_on_a_store_in_the_bucket_is_refused(s3_server, s3_session):
    """One writer per store on S3 too: the lease object beside the store."""
    from schlieren.storage.errors import StoreError
    from schlieren.storage.lease import ObjectStoreLease

    out = s3_server.bucket("store") + "/leased.zarr"
    with ObjectStoreLease(out):
        with pytest.raises(StoreError, match="another run is writing this store"):
            run_session(s3_session, out, serial=True)
        assert not location.exists(out + "/zarr.json")  # refused before the store was created
