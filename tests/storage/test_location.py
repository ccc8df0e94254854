"""storage/location.py: one interface for local paths and fsspec URLs, and staging to local files.

The URL cases run against moto's S3 server on 127.0.0.1 (fixture ``s3_server``).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from schlieren.storage import arrays_cache, location


# ---------------------------------------------------------------------------------------
# names
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("loc, url", [
    ("s3://bucket/run.zarr", True), ("gs://b/x", True), ("az://c/x", True), ("memory://x", True),
    ("file:///tmp/run.zarr", False), ("/tmp/run.zarr", False), ("run.zarr", False),
    ("C:/data/run.zarr", False), ("C://data", False),
])
def test_is_url_tells_object_stores_from_local_paths(loc, url):
    assert location.is_url(loc) is url


def test_names_of_urls_and_paths(tmp_path):
    assert location.normalize("s3://b/run.zarr/") == "s3://b/run.zarr"
    assert location.normalize("file:///tmp/x") == "/tmp/x"
    assert location.join("s3://b/sess", "cam00/frames/%05d.png") == "s3://b/sess/cam00/frames/%05d.png"
    assert location.join("s3://b/sess/", "../other/x.mp4") == "s3://b/other/x.mp4"
    assert location.parent("s3://b/sess/session.yaml") == "s3://b/sess"
    assert location.basename("s3://b/sess/run.zarr") == "run.zarr"
    assert location.join(tmp_path, "a", "b") == os.path.join(str(tmp_path), "a", "b")
    assert location.display("s3://b/x/") == "s3://b/x"
    assert location.display(tmp_path / "x") == str((tmp_path / "x").resolve())


# ---------------------------------------------------------------------------------------
# files: the same answers locally and on S3
# ---------------------------------------------------------------------------------------
@pytest.fixture(params=["local", pytest.param("s3", marks=pytest.mark.system)])
def root(request, tmp_path):
    if request.param == "s3":
        return request.getfixturevalue("s3_server").bucket() + "/root"
    return str(tmp_path / "root")


def test_bytes_round_trip_listing_and_removal(root):
    a, b = location.join(root, "a.bin"), location.join(root, "sub", "b.bin")
    assert not location.exists(a) and not location.isfile(a)
    location.write_bytes(a, b"0123456789")
    location.write_many({b: b"xyz", location.join(root, "sub", "c.bin"): b""})
    assert location.read_bytes(a) == b"0123456789"
    assert location.read_bytes(a, 2, 5) == b"234"  # one ranged request on S3
    assert location.isfile(b) and not location.isfile(location.join(root, "sub"))
    assert sorted(location.listdir(root)) == ["a.bin", "sub"]
    assert sorted(location.find(root)) == ["a.bin", "sub/b.bin", "sub/c.bin"]
    location.write_bytes(a, b"new")  # replaced whole
    assert location.read_bytes(a) == b"new"
    location.remove(a)
    location.remove(a)  # a missing file is fine
    assert not location.exists(a)
    with pytest.raises(FileNotFoundError):
        location.read_bytes(a)
    assert location.find(location.join(root, "nothing")) == []


def test_exclusive_creation_lets_one_writer_win(root):
    """The primitive for a one-writer lease on a folder or an object store."""
    lease = location.join(root, "run.zarr.lease")
    assert location.create_exclusive(lease, b"holder A")
    assert not location.create_exclusive(lease, b"holder B")
    assert location.read_bytes(lease) == b"holder A"
    location.remove(lease)
    assert location.create_exclusive(lease, b"holder B")
    assert location.read_bytes(lease) == b"holder B"
    assert sorted(location.listdir(root)) == ["run.zarr.lease"]  # no temporary files left


def test_a_local_path_is_its_own_staged_copy(tmp_path):
    p = tmp_path / "v.avi"
    p.write_bytes(b"data")
    assert location.stage(p) == str(p)
    assert location.stage_folder(tmp_path, complete_marker="v.avi") == str(tmp_path)


def test_stage_copies_once_per_object_version(s3_server, tmp_path, monkeypatch):
    monkeypatch.setenv(location.CACHE_ENV, str(tmp_path / "cache"))
    url = s3_server.bucket() + "/videos/cam00.mp4"
    location.write_bytes(url, b"first version")
    fs, _ = location.filesystem(url)
    assert location.filesystem(url)[0] is fs  # fsspec keeps one instance per configuration
    fetched = []
    real_get = fs.get_file

    def counting_get(rpath, lpath, **kw):
        fetched.append(rpath)
        return real_get(rpath, lpath, **kw)

    monkeypatch.setattr(fs, "get_file", counting_get)
    first = location.stage(url)
    assert first.endswith("cam00.mp4") and first.startswith(str(tmp_path / "cache"))
    assert open(first, "rb").read() == b"first version"
    assert location.stage(url) == first and len(fetched) == 1  # cached: no second download
    location.write_bytes(url, b"second version")  # a new object version is fetched again
    second = location.stage(url)
    assert second != first and open(second, "rb").read() == b"second version" and len(fetched) == 2
    assert not [p for p in (tmp_path / "cache").rglob("*.partial")]


def test_arrays_cache_on_object_storage_is_uploaded_then_mapped_from_a_staged_copy(s3_server, tmp_path,
                                                                                     monkeypatch):
    monkeypatch.setenv(location.CACHE_ENV, str(tmp_path / "cache"))
    store = s3_server.bucket() + "/run.zarr"
    d = arrays_cache.cache_dir(store, "geometry", "abc123")
    assert d == store + ".cache/geometry-abc123"  # beside the store, as for folders
    arrays = {"S_data": np.arange(12, dtype=np.float32).reshape(3, 4), "idx": np.arange(5, dtype=np.int64),
              "fortran": np.asfortranarray(np.arange(6, dtype=">f8").reshape(2, 3)),
              "empty": np.zeros((0, 3), dtype=np.int32), "scalar": np.array(2.5), "n": 7}
    assert not arrays_cache.has_arrays(d)
    arrays_cache.save_arrays(d, arrays)
    assert arrays_cache.has_arrays(d)
    # two objects, not one per array: the pack, then the manifest naming each member's offset
    assert sorted(location.find(d)) == ["arrays.pack", "manifest.json"]
    assert not list((tmp_path / "cache").glob("upload/*"))  # the local upload copy is gone

    def check(got):
        assert got["n"] == 7
        assert isinstance(got["S_data"], np.memmap) and str(tmp_path / "cache") in str(got["S_data"].filename)
        for k, a in arrays.items():
            if k != "n":
                np.testing.assert_array_equal(got[k], a)
                assert got[k].dtype == a.dtype and got[k].shape == a.shape
        assert got["fortran"].flags.f_contiguous and got["S_data"].ctypes.data % 64 == 0
        assert not got["S_data"].flags.writeable

    check(arrays_cache.load_arrays(d))  # the writer's own copy, adopted as staged
    assert arrays_cache.verify_arrays(d) == []
    monkeypatch.setenv(location.CACHE_ENV, str(tmp_path / "cache2"))  # another machine: staged afresh
    tmp_path.joinpath("cache2").mkdir()
    got = arrays_cache.load_arrays(d)
    assert str(tmp_path / "cache2") in str(got["S_data"].filename)
    np.testing.assert_array_equal(arrays_cache.load_arrays(d, mmap=False)["fortran"], arrays["fortran"])
    # a flipped byte inside one member, then a truncated pack, staged by a third machine each:
    # found and named
    pack = location.read_bytes(d + "/arrays.pack")
    meta = json.loads(location.read_bytes(d + "/manifest.json"))
    at = meta["pack"]["offsets"]["idx.npy"] + meta["files"]["idx.npy"]["size"] - 1
    for k, (damaged, read, what) in enumerate([(pack[:at] + bytes([pack[at] ^ 1]) + pack[at + 1:], True, "CRC-32C"),
                                               (pack[:at], False, "truncated")]):
        location.write_bytes(d + "/arrays.pack", damaged)
        monkeypatch.setenv(location.CACHE_ENV, str(tmp_path / f"cache-damaged{k}"))
        bad = arrays_cache.verify_arrays(d, read=read)
        assert bad and "idx.npy" in bad[0] and all(what in b for b in bad), bad
        assert len(bad) == (1 if read else sum(o >= meta["pack"]["offsets"]["idx.npy"]
                                               for o in meta["pack"]["offsets"].values()))


def test_zarr_store_of_a_url_reads_what_zarr_open_group_wrote(s3_server):
    import zarr
    from zarr.storage import FsspecStore, LocalStore

    url = s3_server.bucket() + "/g.zarr"
    g = location.zarr_open_group(url, mode="w-", zarr_format=3)
    g.create_array("a", shape=(3,), chunks=(1,), dtype="i4")[...] = [1, 2, 3]
    store = location.zarr_store(url, read_only=True)
    assert isinstance(store, FsspecStore) and store.read_only
    np.testing.assert_array_equal(zarr.open_group(store, mode="r")["a"][...], [1, 2, 3])
    assert isinstance(location.zarr_store("/tmp/x.zarr", read_only=False), LocalStore)
