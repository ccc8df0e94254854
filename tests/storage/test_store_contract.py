"""The result-store contract, run on a local folder and on an in-memory zarr store.

Template creation (dims, shapes, chunks, explicit fill values, attrs), round trips,
chunk-aligned writes, completion markers, resume refusal/acceptance, xarray view.
"""

from __future__ import annotations

import pickle
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr

from schlieren.pipeline.geometry import Grid
from schlieren.storage.errors import StoreError
from schlieren.storage.layout import (
    STORE_FORMAT,
    AlignmentError,
    ArraySpec,
    result_layout,
    stage_markers,
)
from schlieren.storage.store import ResultStore, fingerprint, to_json

CAMS = ["cam00", "cam01", "cam02"]
NF = 4
FLOW = (5, 6)
GRID = Grid((-0.05, -0.04, 0.0), (0.05, 0.04, 0.06), 0.02)  # (nz, ny, nx) = (3, 4, 5)


def layout(n_frames=NF, first_frame=10):
    return result_layout(camera_names=CAMS, n_frames=n_frames, flow_shape=FLOW, grid=GRID,
                         first_frame=first_frame)


def attrs(fp="run-1"):
    return {"fingerprint": fingerprint({"session": "tiny", "config": fp}),
            "session": {"name": "tiny", "frames": (10, 14)}, "version": "0.1.0"}


@pytest.fixture(params=["local", "memory", pytest.param("s3", marks=pytest.mark.system)])
def location(request, tmp_path):
    """A fresh place for a store: a folder path, a MemoryStore or a URL on a local S3 server."""
    if request.param == "local":
        return tmp_path / "run.zarr"
    if request.param == "s3":
        return request.getfixturevalue("s3_server").bucket() + "/run.zarr"
    return zarr.storage.MemoryStore()


@pytest.fixture
def store(location):
    return ResultStore.create(location, layout(), attrs=attrs(), markers=stage_markers())


# ---------------------------------------------------------------------------------------
# layout
# ---------------------------------------------------------------------------------------
def test_layout_matches_the_design_table():
    specs = {s.name: s for s in layout()}
    C, F, (h, w), (nz, ny, nx) = len(CAMS), NF, FLOW, GRID.shape
    expected = {
        "time": (("frame",), (F,), "float64"),
        "frame_quality": (("camera", "raw_frame", "quality"), (C, F, 7), "float32"),
        "time_offset": (("camera",), (C,), "float64"),
        "flash_frames": (("camera", "bound"), (C, 2), "int64"),
        "flow_raw": (("camera", "raw_frame", "v", "u", "component"), (C, F, h, w, 2), "float32"),
        "flow": (("camera", "frame", "v", "u", "component"), (C, F, h, w, 2), "float32"),
        "potential": (("camera", "frame", "v", "u"), (C, F, h, w), "float32"),
        "potential_summary": (("camera", "frame", "summary"), (C, F, 2001), "float64"),
        "mask_threshold": (("scalar",), (1,), "float64"),
        "mask": (("camera", "frame", "v", "u"), (C, F, h, w), "bool"),
        "hull": (("frame", "z", "y", "x"), (F, nz, ny, nx), "bool"),
        "gradient": (("frame", "z", "y", "x", "axis"), (F, nz, ny, nx, 3), "float32"),
        "refractivity": (("frame", "z", "y", "x"), (F, nz, ny, nx), "float32"),
        "density": (("frame", "z", "y", "x"), (F, nz, ny, nx), "float32"),
        "temperature": (("frame", "z", "y", "x"), (F, nz, ny, nx), "float32"),
    }
    for name, (dims, shape, dtype) in expected.items():
        s = specs[name]
        assert (s.dims, s.shape, s.dtype) == (dims, shape, dtype), name
        # one chunk per camera-frame (image arrays) or per frame (volumes)
        per_index = [1 if d in ("camera", "frame", "raw_frame") else n for d, n in zip(s.dims, s.shape)]
        if name == "time":
            per_index = [F]  # written at once by the sync step
        assert list(s.chunks) == per_index, name
        if "z" in s.dims:
            assert s.attrs["origin"] == pytest.approx(list(GRID.origin))
            assert s.attrs["voxel_size"] == [GRID.voxel_size] * 3
        if "frame" in s.dims and name != "time":
            assert s.attrs["coordinates"] == "time"
        assert "units" in s.attrs or s.dtype == "str"
    # each dimension name has one size (so xarray can put every array in one dataset)
    sizes = {}
    for s in specs.values():
        for d, n in zip(s.dims, s.shape):
            assert sizes.setdefault(d, n) == n, (d, s.name)
    assert sizes["component"] == 2 and sizes["axis"] == 3


def test_layout_with_a_raw_frame_margin():
    specs = {s.name: s for s in result_layout(camera_names=CAMS, n_frames=4, flow_shape=FLOW, grid=GRID,
                                              first_frame=10, n_raw=8, raw_first=8)}
    assert specs["flow_raw"].shape == (3, 8) + FLOW + (2,)
    assert specs["flow"].shape == (3, 4) + FLOW + (2,)
    np.testing.assert_array_equal(specs["raw_frame"].data, np.arange(8, 16))
    np.testing.assert_array_equal(specs["frame"].data, np.arange(10, 14))
    no_coord = {s.name for s in result_layout(camera_names=CAMS, n_frames=4, flow_shape=FLOW, grid=GRID,
                                              n_raw=8)}
    assert "raw_frame" not in no_coord and "flow_raw" in no_coord


def test_array_spec_validates_lengths():
    with pytest.raises(ValueError):
        ArraySpec("a", ("x",), (3, 4), (1, 1), "float32", np.nan)
    with pytest.raises(ValueError):
        ArraySpec("a", ("x",), (3,), (0,), "float32", np.nan)


def test_layout_needs_cameras_and_frames():
    with pytest.raises(ValueError):
        result_layout(camera_names=[], n_frames=3, flow_shape=FLOW, grid=GRID)


# ---------------------------------------------------------------------------------------
# template
# ---------------------------------------------------------------------------------------
def test_template_creates_every_array_with_dims_fill_and_attrs(store):
    a = store.attrs
    assert a["format"] == STORE_FORMAT and a["version"] == "0.1.0"
    assert a["session"] == {"name": "tiny", "frames": [10, 14]}
    assert a["fingerprint"] == attrs()["fingerprint"] and a["template_complete"] is True
    for spec in layout():
        arr = store.array(spec.name)
        assert tuple(arr.shape) == spec.shape and tuple(arr.chunks) == spec.chunks, spec.name
        assert store.dims(spec.name) == spec.dims
        if spec.data is None:
            data = store.read(spec.name)
            if spec.dtype.startswith("float"):
                assert np.all(np.isnan(data)), spec.name  # unwritten floats read NaN, never 0
            elif spec.dtype == "bool":
                assert not data.any()
        for k, v in spec.attrs.items():
            assert arr.attrs[k] == to_json(v), (spec.name, k)
    np.testing.assert_array_equal(store.read("frame"), np.arange(10, 14))
    assert list(store.read("camera")) == CAMS
    x, y, z = GRID.axes()
    np.testing.assert_allclose(store.read("x"), x)
    np.testing.assert_allclose(store.read("z"), z)
    assert store.stages() == sorted(stage_markers())
    for stage, dims in stage_markers().items():
        m = store.array(f"status/{stage}")
        assert m.dtype == np.uint8 and tuple(m.chunks) == (1,) * len(dims)
        assert store.dims(f"status/{stage}") == dims
        assert not store.done(stage).any()
    assert store.done("deflection").shape == (3, NF)
    assert store.done("tomography").shape == (NF,)


def test_markers_given_as_shapes(location):
    s = ResultStore.create(location, layout(), attrs=attrs(), markers={"custom": (2, 3)})
    assert s.done("custom").shape == (2, 3)
    s.mark_done("custom", (1, 2))
    assert s.is_done("custom", (1, 2)) and not s.is_done("custom", (0, 2))


def test_markers_as_shapes_with_single_markers_for_run_once_stages(location):
    # what the workers' stage table gives: shapes, () for stages that run once
    markers = {"frames": (3, NF), "sync": (3,), "clock": (), "threshold": (), "deflection": (3, NF + 2)}
    s = ResultStore.create(location, layout(), attrs=attrs(), markers=markers)
    assert s.done("clock").shape == () and not s.is_done("clock", ())
    s.mark_done("clock", ())
    assert s.is_done("clock", ()) and bool(s.done("clock"))
    s.mark_done("deflection", (2, NF + 1))
    assert s.done("deflection").sum() == 1
    with pytest.raises(ValueError, match="dimension names or a shape"):
        ResultStore.create(zarr.storage.MemoryStore(), layout(), attrs=attrs(), markers={"x": (2, "frame")})


def test_unknown_marker_dimension_is_refused(location):
    with pytest.raises(ValueError, match="unknown dimension"):
        ResultStore.create(location, layout(), attrs=attrs(), markers={"bad": ("camera", "time")})


# ---------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------
def test_round_trip_of_every_kind_of_array(store):
    rng = np.random.default_rng(0)
    flow = rng.normal(size=FLOW + (2,)).astype(np.float32)
    store.write("flow", (1, 2), flow)  # data without the indexed dims
    np.testing.assert_array_equal(store.read("flow", (1, 2)), flow)
    assert np.all(np.isnan(store.read("flow", (1, 1))))  # neighbours untouched
    mask = rng.random(FLOW) > 0.5
    store.write("mask", (0, 3), mask[None, None])  # data with the indexed dims
    np.testing.assert_array_equal(store.read("mask", (0, 3)), mask)
    vol = rng.normal(size=(2,) + GRID.shape).astype(np.float32)
    store.write("refractivity", slice(1, 3), vol)  # two whole frames
    np.testing.assert_array_equal(store.read("refractivity", slice(1, 3)), vol)
    grad = rng.normal(size=GRID.shape + (3,))
    store.write("gradient", 0, grad)  # float64 in, float32 stored
    np.testing.assert_allclose(store.read("gradient", 0), grad.astype(np.float32))
    store.write("time", (), np.array([0.1, 0.2, 0.3, 0.4]))
    np.testing.assert_array_equal(store.read("time"), [0.1, 0.2, 0.3, 0.4])
    store.write("time_offset", 2, np.array(0.25))
    assert store.read("time_offset", 2) == 0.25
    store.write("mask_threshold", 0, np.array(1.5))
    store.write("flash_frames", (1,), np.array([[3, 5]]))
    np.testing.assert_array_equal(store.read("flash_frames", 1), [3, 5])
    np.testing.assert_array_equal(store.read("flash_frames", 0), [-1, -1])  # fill: no flash
    q = np.array([1.0, 0.0, 0.5, 0.0, 2.0, 0.0, 3.0])
    store.write("frame_quality", (2, 0), q)
    np.testing.assert_array_equal(store.read("frame_quality", (2, 0)), q)


def test_partial_chunk_writes_are_refused(store):
    with pytest.raises(AlignmentError, match="whole chunks"):
        store.write("flow", (0, 0, slice(0, 2)), np.zeros((2, FLOW[1], 2)))
    with pytest.raises(AlignmentError):
        store.write("time", slice(0, 2), np.zeros(2))  # time is one chunk of 4
    with pytest.raises(AlignmentError):
        store.write("refractivity", (0, slice(1, 3)), np.zeros((2,) + GRID.shape[1:]))
    assert np.all(np.isnan(store.read("flow", (0, 0))))
    assert np.all(np.isnan(store.read("time")))


def test_wrong_data_shape_is_refused(store):
    with pytest.raises(ValueError, match="does not fit"):
        store.write("flow", (0, 0), np.zeros(FLOW))
    with pytest.raises(IndexError):
        store.write("flow", (3, 0), np.zeros(FLOW + (2,)))  # no camera 3


def test_unknown_array(store):
    with pytest.raises(StoreError, match="no such array"):
        store.read("velocity")
    assert "flow" in store and "velocity" not in store


# ---------------------------------------------------------------------------------------
# markers
# ---------------------------------------------------------------------------------------
def test_markers_not_chunk_presence_mean_done(store):
    # a legitimately all-False mask equals the fill value: zarr may drop the chunk...
    store.write("mask", (1, 1), np.zeros(FLOW, dtype=bool))
    assert not store.is_done("mask", (1, 1))
    store.mark_done("mask", (1, 1))
    # ...but the marker says the work is done
    assert store.is_done("mask", (1, 1))
    done = store.done("mask")
    assert done.dtype == bool and done.sum() == 1 and done[1, 1]
    store.mark_done("tomography", 2)
    store.mark_done("threshold", ())
    np.testing.assert_array_equal(store.done("tomography"), [False, False, True, False])
    assert store.is_done("threshold", ())
    with pytest.raises(StoreError, match="no completion marker"):
        store.mark_done("nonsense", 0)


def test_is_done_answers_from_the_files_in_a_folder_store(tmp_path, monkeypatch):
    """In a folder store a single marker position is answered from its chunk file
    without a zarr read; every answer agrees with the marker array, including scalar
    and multi-chunk regions (those go through zarr)."""
    s = ResultStore.create(tmp_path / "run.zarr", layout(), attrs=attrs(), markers=stage_markers())
    rng = np.random.default_rng(0)
    marks = {(int(c), int(k)) for c, k in zip(rng.integers(0, 3, 5), rng.integers(0, NF, 5))}
    for ck in marks:
        s.mark_done("mask", ck)
    s.mark_done("threshold", ())
    expected = s.done("mask")
    reads = []
    real_getitem = zarr.Array.__getitem__
    monkeypatch.setattr(zarr.Array, "__getitem__", lambda self, sel: reads.append(sel) or real_getitem(self, sel))
    for c in range(3):
        for k in range(NF):
            assert s.is_done("mask", (c, k)) == bool(expected[c, k])
    assert reads == []  # single positions never go through zarr
    assert s.is_done("threshold", ()) and not s.is_done("clock", ())
    assert s.is_done("mask", (slice(None), 0)) == bool(expected[:, 0].all())


def test_stage_completion_attrs_and_updates(store):
    store.set_stage_completed("deflection", "2026-11-21T08:00:00+00:00")
    store.set_stage_completed("tomography")
    sc = store.attrs["stages_completed"]
    assert sc["deflection"] == "2026-11-21T08:00:00+00:00" and "T" in sc["tomography"]
    store.update_attrs({"timings": {"flow_s": np.float64(1.5)}})
    assert store.attrs["timings"] == {"flow_s": 1.5}
    with pytest.raises(ValueError):
        store.update_attrs({"format": "other"})


# ---------------------------------------------------------------------------------------
# reopen, resume, refusal
# ---------------------------------------------------------------------------------------
def test_open_sees_what_was_written(location, store):
    store.write("flow", (2, 3), np.ones(FLOW + (2,)))
    store.mark_done("deflection", (2, 3))
    again = ResultStore.open(location)
    np.testing.assert_array_equal(again.read("flow", (2, 3)), 1.0)
    assert again.is_done("deflection", (2, 3))
    ro = ResultStore.open(location, mode="r")
    with pytest.raises(StoreError, match="read-only"):
        ro.write("flow", (0, 0), np.ones(FLOW + (2,)))
    with pytest.raises(StoreError, match="read-only"):
        ro.mark_done("deflection", (0, 0))


def test_resume_with_the_same_fingerprint_keeps_everything(location, store):
    store.write("refractivity", 1, np.full(GRID.shape, 7.0))
    store.mark_done("integrate", 1)
    resumed = ResultStore.create(location, layout(), attrs=attrs(), markers=stage_markers())
    assert resumed.is_done("integrate", 1)
    np.testing.assert_array_equal(resumed.read("refractivity", 1), 7.0)
    assert not resumed.done("integrate")[[0, 2, 3]].any()


def test_different_run_is_refused_and_nothing_is_touched(location, store):
    store.write("refractivity", 1, np.full(GRID.shape, 7.0))
    store.mark_done("integrate", 1)
    with pytest.raises(StoreError) as info:
        ResultStore.create(location, layout(), attrs=attrs("run-2"), markers=stage_markers())
    err = info.value
    assert "different session or configuration" in err.message and err.field == "fingerprint"
    assert err.file and err.file in str(err) and "\n" not in str(err)
    with pytest.raises(StoreError, match="no fingerprint"):
        ResultStore.create(location, layout(), attrs={}, markers=stage_markers())
    again = ResultStore.open(location)
    assert again.attrs["fingerprint"] == attrs()["fingerprint"]
    np.testing.assert_array_equal(again.read("refractivity", 1), 7.0)
    assert again.is_done("integrate", 1)


def test_same_fingerprint_but_different_layout_is_refused(location, store):
    with pytest.raises(StoreError, match="does not match the layout"):
        ResultStore.create(location, layout(n_frames=NF + 1), attrs=attrs(), markers=stage_markers())


def test_interrupted_template_is_completed_on_resume(location):
    specs = layout()
    first = [s for s in specs if s.name in ("frame", "time", "flow")]
    partial = ResultStore.create(location, first, attrs=attrs(), markers={})
    partial.group.attrs.update({"template_complete": False})
    full = ResultStore.create(location, specs, attrs=attrs(), markers=stage_markers())
    assert full.attrs["template_complete"] is True
    assert "temperature" in full and full.done("hull").shape == (NF,)


def test_in_memory_store_is_not_picklable_but_a_path_store_is(tmp_path):
    mem = ResultStore.create(zarr.storage.MemoryStore(), layout(), attrs=attrs(), markers=stage_markers())
    with pytest.raises(TypeError):
        pickle.dumps(mem)
    local = ResultStore.create(tmp_path / "p.zarr", layout(), attrs=attrs(), markers=stage_markers())
    local.write("flow", (0, 0), np.ones(FLOW + (2,)))
    clone = pickle.loads(pickle.dumps(local))
    np.testing.assert_array_equal(clone.read("flow", (0, 0)), 1.0)


# local-only refusals --------------------------------------------------------------------
def test_refuses_a_non_empty_folder_that_is_not_a_store(tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    with pytest.raises(StoreError, match="not empty") as info:
        ResultStore.create(out, layout(), attrs=attrs(), markers=stage_markers())
    assert info.value.file == str(out)
    assert (out / "notes.txt").read_text() == "precious" and sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_refuses_a_file_and_accepts_an_empty_folder(tmp_path):
    f = tmp_path / "file.zarr"
    f.write_text("x")
    with pytest.raises(StoreError, match="is a file"):
        ResultStore.create(f, layout(), attrs=attrs(), markers=stage_markers())
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    s = ResultStore.create(empty, layout(), attrs=attrs(), markers=stage_markers())
    assert (Path(empty) / "zarr.json").is_file() and "flow" in s


def test_refuses_a_foreign_zarr_group(tmp_path):
    p = tmp_path / "other.zarr"
    zarr.open_group(p, mode="w", attributes={"fingerprint": attrs()["fingerprint"]})
    with pytest.raises(StoreError, match="not a schlieren-store/1 store"):
        ResultStore.create(p, layout(), attrs=attrs(), markers=stage_markers())
    with pytest.raises(StoreError, match="not a schlieren-store/1 store"):
        ResultStore.open(p)


def test_open_missing_store(tmp_path):
    with pytest.raises(StoreError, match="no result store") as info:
        ResultStore.open(tmp_path / "nothing.zarr")
    assert info.value.file == str(tmp_path / "nothing.zarr")


def test_concurrent_whole_chunk_writers_lose_nothing(tmp_path):
    path = tmp_path / "c.zarr"
    ResultStore.create(path, layout(), attrs=attrs(), markers=stage_markers())
    jobs = [(c, f) for c in range(len(CAMS)) for f in range(NF)]

    def task(cf):
        s = ResultStore.open(path)  # tasks open by path
        c, f = cf
        s.write("flow", (c, f), np.full(FLOW + (2,), 10 * c + f, dtype=np.float32))
        s.mark_done("deflection", (c, f))
        return cf

    with ThreadPoolExecutor(4) as ex:
        assert sorted(ex.map(task, jobs)) == sorted(jobs)
    s = ResultStore.open(path, mode="r")
    flow = s.read("flow")
    for c, f in jobs:
        assert np.all(flow[c, f] == 10 * c + f)
    assert s.done("deflection").all()


# ---------------------------------------------------------------------------------------
# xarray view
# ---------------------------------------------------------------------------------------
def test_xarray_shows_named_dims_and_the_time_coordinate(location, store):
    times = np.array([0.0, 1 / 60, 2 / 60, 3 / 60])
    store.write("time", (), times)
    store.write("refractivity", 2, np.full(GRID.shape, 3e-4))
    store.write("flow", (1, 0), np.full(FLOW + (2,), 0.5))
    ds = xr.open_zarr(location, consolidated=False)
    assert "time" in ds.coords and ds["time"].dims == ("frame",)
    np.testing.assert_allclose(ds["time"].values, times)
    np.testing.assert_array_equal(ds["frame"].values, np.arange(10, 14))
    assert ds["refractivity"].dims == ("frame", "z", "y", "x")
    assert ds["flow"].dims == ("camera", "frame", "v", "u", "component")
    assert ds["gradient"].dims == ("frame", "z", "y", "x", "axis")
    assert ds["mask"].dims == ("camera", "frame", "v", "u") and ds["mask"].dtype == bool
    assert ds["refractivity"].attrs["units"] == "1"
    assert ds["refractivity"].attrs["voxel_size"] == [GRID.voxel_size] * 3
    assert "time" in ds["refractivity"].coords
    sel = ds["refractivity"].sel(frame=12).values
    np.testing.assert_allclose(sel, 3e-4, rtol=1e-6)
    np.testing.assert_allclose(ds["flow"].sel(camera="cam01", frame=10, component="u").values, 0.5)
    assert np.isnan(ds["refractivity"].sel(frame=13).values).all()
    np.testing.assert_allclose(ds["z"].values, GRID.axes()[2])
    assert ds.attrs["format"] == STORE_FORMAT


# ---------------------------------------------------------------------------------------
# attrs helpers
# ---------------------------------------------------------------------------------------
def test_fingerprint_is_canonical():
    a = fingerprint({"a": 1, "b": [1.0, 2.0]}, {"x": (1, 2)})
    assert a == fingerprint({"b": [1.0, 2.0], "a": 1}, {"x": [1, 2]})
    assert a != fingerprint({"a": 1, "b": [1.0, 2.5]}, {"x": (1, 2)})
    assert len(a) == 64


def test_to_json_converts_numpy_and_paths():
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class P:
        factor: int = 3
        sigma: float = float("nan")

    out = to_json({"a": np.float32(1.5), "b": np.arange(3), "p": Path("/x"), "d": P(), "t": (1, 2)})
    assert out == {"a": 1.5, "b": [0, 1, 2], "p": "/x", "d": {"factor": 3, "sigma": "NaN"}, "t": [1, 2]}
    with pytest.raises(TypeError):
        to_json({"f": object()})
