"""Direct chunk-file I/O (storage/chunkio.py) against zarr itself.

Two stores with the same layout: one written through :class:`ResultStore` (which takes
the direct path for whole single chunks), one written chunk by chunk through zarr's own
``Array.__setitem__``. Every chunk file must be byte-identical, and each side must read
the other's files back to the same arrays.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import zarr

from schlieren.pipeline.geometry import Grid
from schlieren.storage.chunkio import ChunkLayout, chunk_layout
from schlieren.storage.layout import ArraySpec, result_layout, stage_markers
from schlieren.storage.store import ResultStore, fingerprint

CAMS = ["cam00", "cam01", "cam02"]
NF = 3
FLOW = (5, 7)
GRID = Grid((-0.05, -0.04, 0.0), (0.05, 0.04, 0.06), 0.02)


def _layout():
    return result_layout(camera_names=CAMS, n_frames=NF, flow_shape=FLOW, grid=GRID, first_frame=4)


def _attrs():
    return {"fingerprint": fingerprint({"session": "tiny"}), "session": {"name": "tiny"}, "version": "0"}


def _files(root: Path, name: str) -> dict[str, bytes]:
    base = root / name / "c"
    if not base.exists():
        return {}
    return {str(p.relative_to(base)): p.read_bytes() for p in base.rglob("*") if p.is_file()}


def _random_chunk(rng, dtype, shape):
    if np.dtype(dtype) == bool:
        return rng.random(shape) < 0.3
    if np.dtype(dtype).kind in "iu":
        return rng.integers(0, 100, shape).astype(dtype)
    a = rng.standard_normal(shape).astype(dtype)
    a.flat[::7] = np.nan  # NaN inside a chunk that is not all fill
    return a


@pytest.fixture
def two_stores(tmp_path):
    fast = ResultStore.create(tmp_path / "fast.zarr", _layout(), attrs=_attrs(), markers=stage_markers())
    ref = ResultStore.create(tmp_path / "ref.zarr", _layout(), attrs=_attrs(), markers=stage_markers())
    return fast, ref, tmp_path


def _per_chunk_arrays(store):
    """(name, zarr array) of the numeric arrays chunked one camera/frame per chunk."""
    out = []
    for name in ("flow", "flow_raw", "potential", "mask", "frame_quality", "gradient", "hull",
                 "refractivity", "density", "temperature", "time_offset", "flash_frames"):
        if name in store:
            out.append((name, store.array(name)))
    return out


def test_every_per_task_array_takes_the_direct_path(two_stores):
    fast, _, _ = two_stores
    for name, arr in _per_chunk_arrays(fast):
        assert fast._chunk_files(name) is not None, name
    assert fast._chunk_files("status/mask") is not None
    # string coordinates go through zarr
    assert fast._chunk_files("camera") is None


def test_direct_writes_are_byte_identical_to_zarr_and_read_back_both_ways(two_stores):
    fast, ref, root = two_stores
    rng = np.random.default_rng(3)
    for name, arr in _per_chunk_arrays(fast):
        lead = next(i for i, c in enumerate(arr.chunks) if c != 1) if any(c != 1 for c in arr.chunks) else len(arr.chunks)
        index_ranges = [range(n) for n in arr.shape[:lead]]
        chunk = tuple(arr.chunks[lead:])
        for idx in np.ndindex(*[len(r) for r in index_ranges]):
            data = _random_chunk(rng, arr.dtype, chunk)
            fast.write(name, idx, data)
            ref.array(name)[idx] = data  # zarr's own path
            back = fast.read(name, idx)
            np.testing.assert_array_equal(back, data)
            assert back.dtype == np.dtype(arr.dtype) and back.flags.writeable
        assert _files(root / "fast.zarr", name) == _files(root / "ref.zarr", name), name
        # zarr reads the direct files, the direct path reads zarr's
        np.testing.assert_array_equal(np.asarray(ref.array(name)[...]), np.asarray(fast.array(name)[...]))
        for idx in np.ndindex(*[len(r) for r in index_ranges]):
            np.testing.assert_array_equal(fast.read(name, idx), np.asarray(ref.array(name)[idx]))
    assert not list(root.rglob("*.partial"))


def test_fill_value_chunks_of_data_arrays_are_stored_as_zarr_does_with_write_empty_chunks(two_stores):
    """Data arrays store even fill-valued chunks (a set marker then means every chunk has a
    file); zarr, opened through the store, does the same, with the same bytes."""
    fast, ref, root = two_stores
    f = np.ones((*FLOW, 2), np.float32)
    fast.write("flow", (1, 2), f)
    path = root / "fast.zarr" / "flow" / "c" / "1" / "2" / "0" / "0" / "0"
    assert path.exists()
    fast.write("flow", (1, 2), np.full((*FLOW, 2), np.nan, np.float32))
    ref.array("flow")[1, 2] = np.full((*FLOW, 2), np.nan, np.float32)
    assert path.exists()
    assert _files(root / "fast.zarr", "flow") == _files(root / "ref.zarr", "flow")
    assert len(_files(root / "fast.zarr", "flow")) == 1
    np.testing.assert_array_equal(fast.read("flow", (1, 2)), np.full((*FLOW, 2), np.nan, np.float32))
    # a never-written chunk (no marker set: no producers here) reads as the fill value
    np.testing.assert_array_equal(fast.read("flow", (0, 0)), np.full((*FLOW, 2), np.nan, np.float32))
    m = fast.read("mask", (2, 1))
    assert m.dtype == bool and not m.any() and m.shape == FLOW
    # an all-False mask (the fill value) is stored too, as zarr stores it
    fast.write("mask", (0, 0), np.zeros(FLOW, bool))
    ref.array("mask")[0, 0] = np.zeros(FLOW, bool)
    assert _files(root / "fast.zarr", "mask") == _files(root / "ref.zarr", "mask") != {}


def test_fill_value_chunks_are_dropped_where_zarr_drops_them(tmp_path):
    """Markers (and arrays opened with zarr's default write_empty_chunks=False) keep zarr's
    default: a fill-valued chunk has no file."""
    g = zarr.open_group(tmp_path / "x.zarr", mode="w", zarr_format=3)
    a = g.create_array("a", shape=(4, 3), chunks=(1, 3), dtype="float32", fill_value=np.nan,
                       compressors=(zarr.codecs.ZstdCodec(level=3), zarr.codecs.Crc32cCodec()))
    lay = chunk_layout(a, tmp_path / "x.zarr", "a")
    assert lay is not None and lay.checksum and not lay.write_empty
    lay.write((1, 0), np.arange(3, dtype=np.float32))
    assert (tmp_path / "x.zarr" / "a" / "c" / "1" / "0").exists()
    lay.write((1, 0), np.full(3, np.nan, np.float32))
    assert not (tmp_path / "x.zarr" / "a" / "c" / "1" / "0").exists()
    np.testing.assert_array_equal(lay.read((1, 0), (1, 3)), np.full((1, 3), np.nan, np.float32))


def test_markers_written_directly_are_zarr_markers(two_stores):
    fast, ref, root = two_stores
    for ck in [(0, 1), (2, 2)]:
        fast.mark_done("mask", ck)
        ref.mark_done("mask", ck)
    assert _files(root / "fast.zarr", "status/mask") == _files(root / "ref.zarr", "status/mask")
    z = zarr.open_array(root / "fast.zarr" / "status" / "mask", mode="r")
    np.testing.assert_array_equal(np.asarray(z[...]) == 1, fast.done("mask"))
    assert fast.is_done("mask", (0, 1)) and not fast.is_done("mask", (1, 1))


def test_edge_chunks_are_padded_with_the_fill_value_like_zarr(tmp_path):
    spec = ArraySpec("edge", ("a", "b"), (5, 7), (2, 3), "float32", float("nan"), {})
    s1 = ResultStore.create(tmp_path / "a.zarr", [spec], attrs=_attrs(), markers={})
    s2 = ResultStore.create(tmp_path / "b.zarr", [spec], attrs=_attrs(), markers={})
    lay = s1._chunk_files("edge")
    assert isinstance(lay, ChunkLayout)
    rng = np.random.default_rng(1)
    full = rng.standard_normal((5, 7)).astype(np.float32)
    for i in range(0, 5, 2):
        for j in range(0, 7, 3):
            region = (slice(i, min(i + 2, 5)), slice(j, min(j + 3, 7)))
            s1.write("edge", region, full[region])
            s2.array("edge")[region] = full[region]
    assert _files(tmp_path / "a.zarr", "edge") == _files(tmp_path / "b.zarr", "edge")
    np.testing.assert_array_equal(np.asarray(s1.array("edge")[...]), full)
    # the last chunk (1 x 1 of data) read directly
    coords = lay.chunk_of((slice(4, 5), slice(6, 7)))
    assert coords == (2, 2)
    np.testing.assert_array_equal(lay.read(coords, (1, 1)), full[4:5, 6:7])
    # regions that are not one whole chunk are not handled here
    assert lay.chunk_of((slice(0, 4), slice(0, 3))) is None
    assert lay.chunk_of((slice(1, 3), slice(0, 3))) is None


def test_arrays_outside_the_pattern_use_zarr(tmp_path):
    root = tmp_path / "x.zarr"
    g = zarr.open_group(root, mode="w", zarr_format=3)
    plain = g.create_array("plain", shape=(4,), chunks=(2,), dtype="float32", compressors=None)
    blosc = g.create_array("blosc", shape=(4,), chunks=(2,), dtype="float32",
                           compressors=(zarr.codecs.BloscCodec(),))
    z = g.create_array("z", shape=(4,), chunks=(2,), dtype="float32",
                       compressors=(zarr.codecs.ZstdCodec(level=3),))
    summed = g.create_array("checked", shape=(4,), chunks=(2,), dtype="float32",
                            compressors=(zarr.codecs.ZstdCodec(level=3, checksum=True),))
    crc = g.create_array("crc", shape=(4,), chunks=(2,), dtype="float32",
                         compressors=(zarr.codecs.ZstdCodec(level=3), zarr.codecs.Crc32cCodec()))
    crc_first = g.create_array("crc_first", shape=(4,), chunks=(2,), dtype="float32",
                               compressors=(zarr.codecs.Crc32cCodec(), zarr.codecs.ZstdCodec(level=3)))
    strings = g.create_array("s", shape=(2,), chunks=(2,), dtype=str)
    assert chunk_layout(z, root, "z") is not None and not chunk_layout(z, root, "z").checksum
    assert chunk_layout(crc, root, "crc").checksum
    assert chunk_layout(crc_first, root, "crc_first") is None
    assert chunk_layout(plain, root, "plain") is None
    assert chunk_layout(blosc, root, "blosc") is None
    assert chunk_layout(summed, root, "checked") is None
    assert chunk_layout(strings, root, "s") is None
    assert chunk_layout(z, None, "z") is None  # not a folder store
    mem = zarr.open_group(zarr.storage.MemoryStore(), mode="w", zarr_format=3)
    assert chunk_layout(mem.create_array("m", shape=(2,), chunks=(2,), dtype="f4"), None, "m") is None


def test_a_killed_write_never_leaves_half_a_chunk(two_stores, monkeypatch):
    fast, _, root = two_stores
    good = np.arange(np.prod(FLOW) * 2, dtype=np.float32).reshape(*FLOW, 2)
    fast.write("flow", (0, 0), good)

    def broken_replace(src, dst):
        raise KeyboardInterrupt("killed between write and rename")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(KeyboardInterrupt):
        fast.write("flow", (0, 0), good + 1)
    monkeypatch.undo()
    np.testing.assert_array_equal(fast.read("flow", (0, 0)), good)
    assert not list(root.rglob("*.partial"))


# ---------------------------------------------------------------------------------------
# checksums: zarr's crc32c codec, byte for byte, and damage refused both ways
# ---------------------------------------------------------------------------------------
def test_store_arrays_end_with_zarrs_crc32c_codec(two_stores):
    fast, _, root = two_stores
    for name in fast.all_array_names():
        codecs = fast.array(name).metadata.codecs
        assert type(codecs[-1]).__name__ == "Crc32cCodec", name
    # the trailer is the CRC-32C of the compressed bytes, little endian (zarr v3 spec)
    import google_crc32c

    fast.write("flow", (0, 1), np.ones((*FLOW, 2), np.float32))
    blob = (root / "fast.zarr" / "flow" / "c" / "0" / "1" / "0" / "0" / "0").read_bytes()
    assert blob[-4:] == google_crc32c.value(blob[:-4]).to_bytes(4, "little")


def test_float_fields_are_stored_at_zstds_fastest_level_and_the_rest_at_level_3(two_stores):
    """flow_raw, flow and potential (noisy float32 that level 3 shrinks by a few per cent) are
    framed and checksummed by zstd at FAST_ZSTD, which stores noise at its own size; every
    other array keeps level 3 (a hull, a mask, a volume with ambient outside the hull
    compress many times)."""
    from schlieren.storage.layout import FAST_ZSTD

    fast, _, root = two_stores
    fast_arrays = {"flow_raw", "flow", "potential"}
    for name in fast.all_array_names():
        zstd = [c for c in fast.array(name).metadata.codecs if type(c).__name__ == "ZstdCodec"]
        assert [c.level for c in zstd] == [FAST_ZSTD if name in fast_arrays else 3], name
    noise = np.random.default_rng(1).normal(0, 0.1, (*FLOW, 2)).astype(np.float32)
    fast.write("flow", (1, 0), noise)
    blob = (root / "fast.zarr" / "flow" / "c" / "1" / "0" / "0" / "0" / "0").read_bytes()
    assert noise.nbytes <= len(blob) <= noise.nbytes + 64  # raw bytes, the frame and the CRC
    np.testing.assert_array_equal(fast.read("flow", (1, 0)), noise)


def _damage(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "flip":
        data[len(data) // 2] ^= 0x40
    elif how == "truncate":
        data = data[: len(data) - 7]
    elif how == "empty":
        data = bytearray()
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("how", ["flip", "truncate", "empty"])
def test_a_damaged_chunk_is_an_error_naming_array_and_chunk_on_both_paths(two_stores, how):
    from schlieren.storage.errors import ChunkError

    fast, _, root = two_stores
    fast.write("flow", (2, 1), np.arange(np.prod(FLOW) * 2, dtype=np.float32).reshape(*FLOW, 2))
    _damage(root / "fast.zarr" / "flow" / "c" / "2" / "1" / "0" / "0" / "0", how)
    with pytest.raises(ChunkError) as direct:
        fast.read("flow", (2, 1))
    msg = str(direct.value)
    assert "field flow" in msg and "chunk (2, 1, 0, 0, 0)" in msg and str(root / "fast.zarr") in msg
    assert "\n" not in msg and "verify" in msg
    # zarr's own path (through the store's checking wrapper): the same error
    with pytest.raises(ChunkError) as via_zarr:
        fast.array("flow")[2]
    assert via_zarr.value.chunk == (2, 1, 0, 0, 0) and via_zarr.value.array == "flow"
    # and a plain zarr reader never gets data from it either (zarr checks the CRC itself)
    with pytest.raises(ValueError):
        zarr.open_array(root / "fast.zarr" / "flow", mode="r")[2, 1]


def test_chunks_of_older_stores_without_checksum_read_the_same_both_ways(tmp_path):
    """An array written by the older version (zstd, no crc32c, fill chunks dropped): the
    direct path reads zarr's files, and writes the bytes zarr writes."""
    g = zarr.open_group(tmp_path / "old.zarr", mode="w", zarr_format=3)
    kw = dict(shape=(3, 4, 5), chunks=(1, 4, 5), dtype="float32", fill_value=np.nan,
              compressors=(zarr.codecs.ZstdCodec(level=3),))
    a, b = g.create_array("a", **kw), g.create_array("b", **kw)
    lay = chunk_layout(b, tmp_path / "old.zarr", "b")
    assert lay is not None and not lay.checksum and not lay.write_empty
    rng = np.random.default_rng(2)
    for k in range(3):
        v = rng.standard_normal((4, 5)).astype(np.float32) if k != 1 else np.full((4, 5), np.nan, np.float32)
        a[k] = v
        lay.write((k, 0, 0), v)
        np.testing.assert_array_equal(lay.read((k, 0, 0), (1, 4, 5))[0], np.asarray(a[k]))
    assert _files(tmp_path / "old.zarr", "a") == _files(tmp_path / "old.zarr", "b")
    assert len(_files(tmp_path / "old.zarr", "a")) == 2
