"""Chunk integrity of the result store (storage/integrity.py): every reader refuses a chunk
that fails its checksum, does not decode, or is missing under a set completion marker,
with one line naming the store, the array and the chunk; scans find each kind of damage;
stores of the older version (no checksums) stay readable and are not resumed."""

from __future__ import annotations

import asyncio
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from schlieren.pipeline.geometry import Grid
from schlieren.storage.store import template as store_template
from schlieren.storage.errors import ChunkError, StoreError
from schlieren.storage.integrity import open_dataset, scan_store
from schlieren.storage.layout import result_layout, stage_markers
from schlieren.storage.store import ResultStore, fingerprint

CAMS = ["cam00", "cam01"]
NF = 3
FLOW = (4, 5)
GRID = Grid((-0.05, -0.04, 0.0), (0.05, 0.04, 0.06), 0.02)
PRODUCERS = {"flow": "resample", "mask": "mask", "hull": "hull", "refractivity": "integrate",
             "density": "integrate", "temperature": "integrate", "time": "clock", "mask_threshold": "threshold"}


def _layout():
    return result_layout(camera_names=CAMS, n_frames=NF, flow_shape=FLOW, grid=GRID, first_frame=5)


def _attrs():
    return {"fingerprint": fingerprint({"session": "integrity"}), "session": {"name": "t"}, "version": "0"}


def _vol(k):
    nz, ny, nx = GRID.shape
    return (2.9e-4 + 1e-6 * k + 1e-7 * np.arange(nz * ny * nx).reshape(nz, ny, nx)).astype(np.float32)


def _make(path: Path, producers=PRODUCERS) -> ResultStore:
    """A finished little store: flows, masks (one all-False: the fill value), volumes, markers."""
    s = ResultStore.create(path, _layout(), attrs=_attrs(), markers=stage_markers(), producers=producers)
    rng = np.random.default_rng(0)
    for c in range(len(CAMS)):
        for k in range(NF):
            s.write("flow", (c, k), rng.standard_normal((*FLOW, 2)))
            s.mark_done("resample", (c, k))
            s.write("mask", (c, k), np.zeros(FLOW, bool) if (c, k) == (1, 1) else rng.random(FLOW) < 0.5)
            s.mark_done("mask", (c, k))
    s.write("time", (), np.arange(NF) / 60.0)
    s.mark_done("clock", ())
    for k in range(NF):
        s.write("hull", (k,), np.ones(GRID.shape, bool))
        s.mark_done("hull", k)
        for name in ("refractivity", "density", "temperature"):
            s.write(name, (k,), _vol(k))
        s.mark_done("integrate", k)
    return s


def _chunk(path: Path, name: str, *coords) -> Path:
    return path.joinpath(*name.split("/"), "c", *(str(c) for c in coords))


def _flip(f: Path) -> None:
    b = bytearray(f.read_bytes())
    b[len(b) // 3] ^= 0x01
    f.write_bytes(bytes(b))


@pytest.fixture
def finished(tmp_path):
    path = tmp_path / "run.zarr"
    _make(path)
    return path


def test_a_fill_valued_chunk_of_a_finished_task_is_stored(finished):
    """All-False mask: zarr's default would drop it, making 'deleted' look like 'empty'."""
    assert _chunk(finished, "mask", 1, 1, 0, 0).is_file()
    s = ResultStore.open(finished)
    assert not s.read("mask", (1, 1)).any()
    assert scan_store(s, full=True).ok


@pytest.mark.parametrize("damage", ["delete", "flip", "truncate"])
def test_every_read_path_refuses_a_damaged_chunk_naming_array_and_chunk(finished, damage):
    f = _chunk(finished, "refractivity", 1, 0, 0, 0)
    if damage == "delete":
        f.unlink()
    elif damage == "flip":
        _flip(f)
    else:
        f.write_bytes(f.read_bytes()[:10])
    expect = "is missing although stage integrate is marked complete" if damage == "delete" else "checksum"
    s = ResultStore.open(finished, mode="r")
    readers = {
        "task read (direct file)": lambda: s.read("refractivity", (1,)),
        "zarr through the store": lambda: s.array("refractivity")[...],
        "xarray (open_dataset)": lambda: open_dataset(finished)["refractivity"].values,
        "xarray, dask-backed": lambda: open_dataset(finished, chunks={})["refractivity"].isel(frame=1).compute(),
    }
    from schlieren.storage.report import ReportReader

    readers["report reader"] = lambda: ReportReader(finished).volume("refractivity", 1)
    for what, read in readers.items():
        with pytest.raises(ChunkError) as info:
            read()
        msg = str(info.value)
        assert f"file {finished}" in msg and "field refractivity" in msg, what
        assert "chunk (1, 0, 0, 0)" in msg and expect in msg and "\n" not in msg, what
        assert info.value.chunk == (1, 0, 0, 0)
    # frames that are fine still read
    np.testing.assert_array_equal(s.read("refractivity", (0,)), _vol(0))


def test_export_refuses_a_lost_volume(finished, tmp_path):
    from schlieren.storage.export import export

    _chunk(finished, "temperature", 2, 0, 0, 0).unlink()
    with pytest.raises(ChunkError, match=r"field temperature: chunk \(2, 0, 0, 0\) is missing"):
        export(finished, tmp_path / "out", format="raw", quantity="temperature")
    # refractivity is intact: exported
    res = export(finished, tmp_path / "ok", format="raw", quantity="refractivity")
    assert len(res.entry_points) == NF


def test_a_missing_chunk_of_an_unfinished_task_reads_as_not_computed(tmp_path):
    s = ResultStore.create(tmp_path / "r.zarr", _layout(), attrs=_attrs(), markers=stage_markers(),
                           producers=PRODUCERS)
    assert np.isnan(s.read("refractivity", (0,))).all()
    assert np.isnan(np.asarray(s.array("flow")[0, 1])).all()
    assert not s.read("mask", (0, 0)).any()


def test_a_corrupt_marker_counts_as_not_done_and_is_a_problem(finished, caplog):
    _flip(_chunk(finished, "status/hull", 2))
    s = ResultStore.open(finished)
    with caplog.at_level(logging.WARNING, logger="schlieren.storage.store"):
        assert not s.is_done("hull", 2)
    assert "status/hull" in caplog.text and "chunk (2,)" in caplog.text
    np.testing.assert_array_equal(s.done("hull"), [True, True, False])
    res = scan_store(s)
    assert [(p.array, p.kind, p.stage, p.index) for p in res.problems] == \
        [("status/hull", "corrupt-marker", "hull", (2,))]
    assert (2,) not in res.done["hull"]


def test_scans_find_lost_corrupt_stray_and_orphaned_chunks(finished):
    _chunk(finished, "flow", 1, 2, 0, 0, 0).unlink()  # lost under a set marker
    _flip(_chunk(finished, "mask", 0, 1, 0, 0))  # corrupt under a set marker
    _chunk(finished, "time", 0).unlink()
    s = ResultStore.open(finished)
    s.unmark("hull", 0)
    _flip(_chunk(finished, "hull", 0, 0, 0, 0))  # corrupt, but its task is not done: stray
    (finished / "flow" / "c" / "0" / "0" / "0" / "0" / "0.1234.partial").write_bytes(b"half")
    quick = scan_store(s)
    assert sorted((p.array, p.chunk, p.kind, p.stage, p.index) for p in quick.problems) == [
        ("flow", (1, 2, 0, 0, 0), "missing", "resample", (1, 2)),
        ("time", (0,), "missing", "clock", ()),
    ]
    assert len(quick.partial_files) == 1 and quick.chunks_read == sum(len(v) for v in quick.done.values())
    full = scan_store(s, full=True)
    assert sorted((p.array, p.chunk, p.kind, p.stage) for p in full.problems) == [
        ("flow", (1, 2, 0, 0, 0), "missing", "resample"),
        ("hull", (0, 0, 0, 0), "stray", None),
        ("mask", (0, 1, 0, 0), "corrupt", "mask"),
        ("time", (0,), "missing", "clock"),
    ]
    assert all("\n" not in str(p) for p in full.problems)


def test_static_coordinate_chunks_are_checked_and_rewritten_on_resume(finished):
    _chunk(finished, "x", 0).unlink()
    _flip(_chunk(finished, "camera", 0))
    s = ResultStore.open(finished)
    with pytest.raises(ChunkError, match=r"field x: chunk \(0,\) is missing"):
        s.array("x")[...]
    with pytest.raises(ChunkError, match=r"field camera: chunk \(0,\)"):
        s.array("camera")[...]
    assert {p.array for p in scan_store(s, full=True).problems} == {"x", "camera"}
    again = ResultStore.create(finished, _layout(), attrs=_attrs(), markers=stage_markers(), producers=PRODUCERS)
    assert scan_store(again, full=True).ok
    assert list(np.asarray(again.array("camera")[...])) == CAMS


def test_producers_must_be_covered_by_their_marker(tmp_path):
    with pytest.raises(ValueError, match="marker dimension"):
        ResultStore.create(tmp_path / "a.zarr", _layout(), attrs=_attrs(), markers=stage_markers(),
                           producers={"time": "resample"})


# ---------------------------------------------------------------------------------------
# stores of the older version: no checksums, fill chunks dropped
# ---------------------------------------------------------------------------------------
@pytest.fixture
def legacy(tmp_path, monkeypatch):
    """A store as the version before checksums wrote it."""
    from zarr.codecs import ZstdCodec

    path = tmp_path / "old.zarr"
    with monkeypatch.context() as m:
        m.setattr(store_template, "_COMPRESSORS", (ZstdCodec(level=3),))
        s = _make(path, producers={})
        g = zarr.open_group(path, mode="r+")
        attrs = dict(g.attrs)
        attrs.pop("integrity")
        g.attrs.clear()
        g.attrs.update(attrs)
    assert s.array("flow").metadata.codecs[-1].__class__.__name__ == "ZstdCodec"
    return path


def test_an_older_store_is_read_but_not_resumed(legacy, tmp_path):
    from schlieren.storage.export import export

    s = ResultStore.open(legacy, mode="r")
    assert s.integrity is None
    np.testing.assert_array_equal(s.read("refractivity", (2,)), _vol(2))
    res = export(legacy, tmp_path / "out", format="raw")
    assert len(res.entry_points) == NF
    assert open_dataset(legacy)["refractivity"].shape[0] == NF
    # an older store's missing chunk is its fill value, as its writer meant (no coverage)
    shutil.rmtree(legacy / "mask" / "c" / "1")
    assert not s.read("mask", (1, 1)).any()
    scan = scan_store(s, full=True)
    assert scan.legacy and scan.ok
    with pytest.raises(StoreError, match="older schlieren without chunk checksums.*new --out") as info:
        ResultStore.create(legacy, _layout(), attrs=_attrs(), markers=stage_markers(), producers=PRODUCERS)
    assert "\n" not in str(info.value)
    # a corrupt chunk of an older store still never comes back as data (zstd fails)
    f = _chunk(legacy, "refractivity", 0, 0, 0, 0)
    f.write_bytes(f.read_bytes()[:-9])
    with pytest.raises(ChunkError, match="does not decompress"):
        s.read("refractivity", (0,))


def test_object_store_chunks_are_checked_the_same_way(s3_server):
    """A store in a bucket (zarr's FsspecStore, through CheckedStore): a flipped object and a
    deleted one under set markers are refused by every reader and found by the scans."""
    import fsspec

    url = s3_server.bucket("integrity") + "/run.zarr"
    s = _make(url)
    s.flush()
    fs = fsspec.filesystem("s3", endpoint_url=s3_server.endpoint)
    key = url.removeprefix("s3://")
    blob = bytearray(fs.cat_file(f"{key}/refractivity/c/1/0/0/0"))
    blob[len(blob) // 2] ^= 0x20
    fs.pipe_file(f"{key}/refractivity/c/1/0/0/0", bytes(blob))
    fs.rm_file(f"{key}/flow/c/0/2/0/0/0")
    s = ResultStore.open(url, mode="r")
    with pytest.raises(ChunkError, match=r"field refractivity: chunk \(1, 0, 0, 0\) fails its CRC-32C"):
        s.read("refractivity", (1,))
    with pytest.raises(ChunkError, match=r"field flow: chunk \(0, 2, 0, 0, 0\) is missing although stage resample"):
        s.read("flow", (0, 2))
    with pytest.raises(ChunkError, match=r"field refractivity"):
        open_dataset(url)["refractivity"].values
    np.testing.assert_array_equal(s.read("refractivity", (0,)), _vol(0))
    # the scans list the whole bucket prefix once: the same chunks as a listing per array
    per_array = {n: s.list_chunks(n)[0] for n in s.all_array_names()}
    assert s.list_all_chunks() == {n: k for n, k in per_array.items() if k}
    assert (0, 2, 0, 0, 0) not in per_array["flow"] and (1, 0, 0, 0) in per_array["refractivity"]
    quick, full = scan_store(s), scan_store(s, full=True)
    assert [(p.array, p.kind) for p in quick.problems] == [("flow", "missing")]
    assert sorted((p.array, p.kind, p.stage) for p in full.problems) == \
        [("flow", "missing", "resample"), ("refractivity", "corrupt", "integrate")]


class _CountingStore(zarr.storage.WrapperStore):
    """Counts the ``get`` requests per key that reach the wrapped store; each waits a
    moment first, as a request to an object store does (concurrent callers overlap)."""

    def __init__(self, store, counts=None):
        super().__init__(store)
        self.counts = counts if counts is not None else {}

    def _with_store(self, store):
        return type(self)(store, self.counts)

    async def get(self, key, prototype, byte_range=None):
        self.counts[key] = self.counts.get(key, 0) + 1
        await asyncio.sleep(0.001)
        return await super().get(key, prototype, byte_range)


def test_a_multi_chunk_read_fetches_the_array_metadata_once():
    """zarr requests a read's chunks together; the check of each needs the array's metadata,
    which must be fetched once, not once per chunk in flight (an object store pays a request
    for each). Metadata handed over with ``seed`` (what ResultStore.open already fetched)
    needs no request at all."""
    from schlieren.storage.integrity import CheckedStore

    mem = zarr.storage.MemoryStore()
    a = zarr.create_array(mem, name="a", shape=(16, 8), chunks=(1, 8), dtype="f4",
                          dimension_names=("frame", "x"))
    values = np.arange(128, dtype=np.float32).reshape(16, 8)
    a[...] = values

    counting = _CountingStore(mem)
    arr = zarr.open_array(CheckedStore(counting), path="a", mode="r")
    opened = counting.counts.get("a/zarr.json", 0)
    np.testing.assert_array_equal(arr[...], values)
    assert sum(k.startswith("a/c/") for k in counting.counts) == 16
    assert counting.counts["a/zarr.json"] - opened == 1  # the check's own fetch, once for 16 chunks

    seeded_counts = _CountingStore(mem)
    arr = zarr.open_array(CheckedStore(seeded_counts), path="a", mode="r")
    arr.store.seed({"a": arr.metadata.to_dict()})  # the array's own (read-only) CheckedStore
    opened = seeded_counts.counts.get("a/zarr.json", 0)
    np.testing.assert_array_equal(arr[...], values)
    assert seeded_counts.counts.get("a/zarr.json", 0) == opened  # no request for the checks


def test_a_metadata_fetch_whose_callers_were_cancelled_is_not_reused():
    """A shared metadata fetch that finishes after its only caller was cancelled must not
    answer a later call: that later call (e.g. after the array was created) fetches again."""
    from zarr.core.buffer import default_buffer_prototype

    from schlieren.storage.integrity import CheckedStore

    counting = _CountingStore(zarr.storage.MemoryStore())
    cs = CheckedStore(counting)
    proto = default_buffer_prototype()

    async def scenario():
        first = asyncio.ensure_future(cs._fetch_once("a/zarr.json", proto))
        await asyncio.sleep(0)  # the fetch is under way
        first.cancel()
        await asyncio.sleep(0.01)  # ... and ends with nobody waiting for it
        assert cs._fetching == {}
        await cs._fetch_once("a/zarr.json", proto)

    asyncio.run(scenario())
    assert counting.counts["a/zarr.json"] == 2
