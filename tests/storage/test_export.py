"""Exports read back by independent readers: the VTK XML parsed with the standard library,
NRRD with pynrrd, MetaImage by parsing its header; values checked against the analytic blob
at the world coordinates the files declare (so origin, spacing and axis order are tested)."""

from __future__ import annotations

import base64
import importlib.util
import json
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import zarr

from schlieren.storage.errors import StoreError
from schlieren.storage.export import export


def _fixture_module():
    path = Path(__file__).with_name("test_report.py")
    spec = importlib.util.spec_from_file_location("_schlieren_report_store_fixture", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


FX = _fixture_module()


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return FX.make_store(tmp_path_factory.mktemp("export"))


def analytic(points_xyz: np.ndarray, frame: int) -> np.ndarray:
    d = points_xyz - FX.blob_centre(frame)
    return FX.R_AMB - FX.AMP * np.exp(-np.sum(d ** 2, axis=-1) / (2 * FX.SIGMA ** 2))


def world_points(origin, spacing, sizes_xyz) -> np.ndarray:
    """World coordinates of the samples in file order (x fastest), shape (N, 3)."""
    nx, ny, nz = sizes_xyz
    iz, iy, ix = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    idx = np.stack([ix, iy, iz], axis=-1).reshape(-1, 3)
    return np.asarray(origin) + idx * np.asarray(spacing)


def read_vti(path: Path):
    root = ET.parse(path).getroot()
    assert root.get("type") == "ImageData" and root.get("byte_order") == "LittleEndian"
    hdr = {"UInt64": "<Q", "UInt32": "<I"}[root.get("header_type", "UInt32")]
    img = root.find("ImageData")
    ext = [int(v) for v in img.get("WholeExtent").split()]
    sizes = (ext[1] - ext[0] + 1, ext[3] - ext[2] + 1, ext[5] - ext[4] + 1)
    origin = [float(v) for v in img.get("Origin").split()]
    spacing = [float(v) for v in img.get("Spacing").split()]
    da = img.find("Piece/PointData/DataArray")
    assert da.get("format") == "binary"
    raw = base64.b64decode("".join(da.text.split()))
    hsize = struct.calcsize(hdr)
    (nbytes,) = struct.unpack(hdr, raw[:hsize])
    ncomp = int(da.get("NumberOfComponents", "1"))
    fmt = {"Float32": "f", "UInt8": "B"}[da.get("type")]
    count = nbytes // struct.calcsize(fmt)
    assert count == sizes[0] * sizes[1] * sizes[2] * ncomp
    values = np.array(struct.unpack(f"<{count}{fmt}", raw[hsize:hsize + nbytes]))
    return sizes, origin, spacing, ncomp, da.get("Name"), values


def test_vti_values_origin_spacing_and_time_collection(store, tmp_path):
    res = export(store, tmp_path / "vti", format="vti")
    pvd = res.entry_points[0]
    assert pvd.suffix == ".pvd"
    coll = ET.parse(pvd).getroot().find("Collection")
    sets = coll.findall("DataSet")
    assert [float(s.get("timestep")) for s in sets] == pytest.approx((1 + np.arange(FX.N_FRAMES)) / FX.FRAME_RATE)
    g = zarr.open_group(str(store), mode="r")
    for f, ds in enumerate(sets):
        sizes, origin, spacing, ncomp, name, values = read_vti(pvd.parent / ds.get("file"))
        assert name == "refractivity" and ncomp == 1
        assert sizes == (24, 20, 16)
        assert origin == pytest.approx(FX.GRID.origin, abs=1e-15)
        assert spacing == pytest.approx([FX.GRID.voxel_size] * 3, abs=1e-15)
        # the stored float32 values, bit for bit, in VTK's x-fastest order
        np.testing.assert_array_equal(values.astype(np.float32), g["refractivity"][f].ravel())
        # and the physics at the declared world positions
        want = analytic(world_points(origin, spacing, sizes), f)
        assert np.abs(values - want).max() < 1e-9  # float32 rounding of ~3e-4


def test_vti_gradient_is_a_vector_field(store, tmp_path):
    res = export(store, tmp_path / "g", format="vti", quantity="gradient", frames=(2, 3))  # capture 2 = store 1
    files = [p for p in res.files if p.suffix == ".vti"]
    assert [p.name for p in files] == ["gradient_00002.vti"]
    sizes, origin, spacing, ncomp, name, values = read_vti(files[0])
    assert ncomp == 3
    g = zarr.open_group(str(store), mode="r")
    np.testing.assert_array_equal(values.reshape(-1, 3).astype(np.float32), g["gradient"][1].reshape(-1, 3))


def test_nrrd_read_by_pynrrd(store, tmp_path):
    nrrd = pytest.importorskip("nrrd")  # test-only dependency (pynrrd)
    # capture frames 2 and 3 are store frames 1 and 2 (the fixture's first frame is 1)
    res = export(store, tmp_path / "n", format="nrrd", quantity="refractivity", frames=(2, 4))
    assert [p.name for p in res.entry_points] == ["refractivity_00002.nrrd", "refractivity_00003.nrrd"]
    for f, path in zip((1, 2), res.entry_points):
        data, header = nrrd.read(str(path))  # Fortran order: data[x, y, z]
        assert data.shape == (24, 20, 16) and data.dtype == np.float32
        origin = np.asarray(header["space origin"], dtype=float)
        dirs = np.asarray(header["space directions"], dtype=float)
        assert origin == pytest.approx(FX.GRID.origin, abs=1e-15)
        np.testing.assert_allclose(dirs, FX.GRID.voxel_size * np.eye(3), atol=1e-15)
        ix, iy, iz = np.meshgrid(*(np.arange(n) for n in data.shape), indexing="ij")
        pts = origin + np.stack([ix, iy, iz], axis=-1) @ dirs  # row i of dirs = step along axis i
        assert np.abs(data - analytic(pts, f)).max() < 1e-9
        assert header["frame"] == str(f + 1)  # the capture index; pynrrd keeps "key:=value" pairs as strings
        assert float(header["time"]) == pytest.approx((1 + f) / FX.FRAME_RATE)
        assert header["space units"] == ["m", "m", "m"]


def test_nrrd_hull_is_uint8(store, tmp_path):
    nrrd = pytest.importorskip("nrrd")
    res = export(store, tmp_path / "h", format="nrrd", quantity="hull", frames=(1, 2))
    data, header = nrrd.read(str(res.entry_points[0]), index_order="C")  # data[z, y, x]
    g = zarr.open_group(str(store), mode="r")
    assert data.dtype == np.uint8
    np.testing.assert_array_equal(data.astype(bool), g["hull"][0])


def test_raw_with_metaimage_header_and_json_sidecar(store, tmp_path):
    res = export(store, tmp_path / "r", format="raw", quantity="temperature")
    mhds = res.entry_points
    assert len(mhds) == FX.N_FRAMES and all(p.suffix == ".mhd" for p in mhds)
    side = json.loads((tmp_path / "r" / "temperature.json").read_text())
    assert side["shape_zyx"] == [16, 20, 24] and side["units"] == "K" and side["byte_order"] == "little"
    for f, mhd in enumerate(mhds):
        kv = dict(line.split(" = ", 1) for line in mhd.read_text().splitlines() if " = " in line)
        sizes = tuple(int(v) for v in kv["DimSize"].split())
        origin = [float(v) for v in kv["Offset"].split()]
        spacing = [float(v) for v in kv["ElementSpacing"].split()]
        assert kv["ElementType"] == "MET_FLOAT" and kv["BinaryDataByteOrderMSB"] == "False"
        assert origin == side["origin_xyz_m"] and spacing == side["spacing_xyz_m"]
        values = np.fromfile(mhd.parent / kv["ElementDataFile"], dtype="<f4")
        assert values.size == np.prod(sizes)
        r = analytic(world_points(origin, spacing, sizes), f)
        T = FX.MEDIUM.T_ambient * FX.R_AMB / r
        np.testing.assert_allclose(values, T, rtol=2e-6)
        assert side["frames"][f]["time"] == pytest.approx((1 + f) / FX.FRAME_RATE)


def test_unfinished_frames_are_skipped(tmp_path):
    store = FX.make_store(tmp_path, partial="unfinished")  # frame 2 not integrated
    res = export(store, tmp_path / "u", format="vti")
    assert res.skipped == [3]  # capture frame 3 = store frame 2
    sets = ET.parse(res.entry_points[0]).getroot().find("Collection").findall("DataSet")
    assert [s.get("file") for s in sets] == ["refractivity_00001.vti", "refractivity_00002.vti"]
    with pytest.raises(StoreError, match="no frame of 'temperature' in 3:4 is complete"):
        export(store, tmp_path / "v", format="nrrd", quantity="temperature", frames=(3, 4))


def test_store_opens_in_xarray_with_dims(store, tmp_path):
    """The whole store opens in xarray with its dims and coordinates, and the export carries
    the values xarray sees."""
    import xarray as xr

    ds = xr.open_zarr(str(store), consolidated=False, chunks=None)  # numpy-backed, no dask
    assert ds["refractivity"].dims == ("frame", "z", "y", "x")
    assert ds["gradient"].dims == ("frame", "z", "y", "x", "axis")
    assert ds["flow"].dims == ("camera", "frame", "v", "u", "component")
    np.testing.assert_allclose(ds["x"].values, FX.GRID.axes()[0])
    res = export(store, tmp_path / "x", format="nrrd", frames=(1, 2))
    data = np.fromfile(res.entry_points[0], dtype=np.uint8)
    payload = data[-ds["refractivity"][0].size * 4:].view("<f4")
    np.testing.assert_array_equal(payload, ds["refractivity"][0].values.ravel())
    # and the voxel at world (x, y, z) in xarray's labelled coordinates is that of the file
    pt = ds["refractivity"][0].sel(x=ds["x"][5], y=ds["y"][7], z=ds["z"][3]).item()
    nx, ny = ds.sizes["x"], ds.sizes["y"]
    assert payload[(3 * ny + 7) * nx + 5] == np.float32(pt)


def test_bad_requests_are_one_line_errors(tmp_path):
    partial = FX.make_store(tmp_path, partial="missing")
    with pytest.raises(StoreError, match="no 'temperature' array"):
        export(partial, tmp_path / "o", format="vti", quantity="temperature")
    with pytest.raises(StoreError, match="unknown export format"):
        export(partial, tmp_path / "o", format="vtk")
    with pytest.raises(StoreError, match="cannot export"):
        export(partial, tmp_path / "o", format="vti", quantity="flow")
    with pytest.raises(StoreError, match="frame range"):
        export(partial, tmp_path / "o", format="raw", frames=(4, 5))


def test_export_command_prints_the_files_to_open(store, tmp_path, capsys):
    from schlieren.workers.cli import main

    assert main(["export", str(store), "--format", "vti", "--out", str(tmp_path / "v")]) == 0
    out = capsys.readouterr().out.split()
    assert out == [str(tmp_path / "v" / "refractivity.pvd")]
    assert main(["export", str(store), "--format", "nrrd", "--quantity", "density", "--frames", "2:3",
                 "--out", str(tmp_path / "d")]) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / "d" / "density_00002.nrrd")]


def test_report_and_export_modules_do_not_import_dask():
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import schlieren.storage.report, schlieren.storage.export\n"
        "print(','.join(sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed'})))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _ome_world(ds: dict, index) -> np.ndarray:
    """World coordinates (per axis) of array index ``index`` from an NGFF dataset's transformations."""
    (scale,), (shift,) = ([t["scale"]] for t in ds["coordinateTransformations"][:1]), \
        ([t["translation"]] for t in ds["coordinateTransformations"][1:])
    return np.asarray(index, dtype=float) * np.asarray(scale) + np.asarray(shift)


def _check_ngff(meta: dict, ndim: int) -> None:
    """The NGFF 0.5 rules the export must follow (specification, "multiscales")."""
    assert meta["version"] == "0.5"
    (ms,) = meta["multiscales"]
    axes = ms["axes"]
    kinds = [a.get("type") for a in axes]
    assert len(axes) == ndim and kinds[0] == "time" and kinds[-3:] == ["space"] * 3
    assert kinds == sorted(kinds, key=["time", "channel", "space"].index)  # time, channel, then space
    assert all(a["unit"] == "meter" for a in axes if a["type"] == "space") and axes[0]["unit"] == "second"
    scales = []
    for ds in ms["datasets"]:
        kinds_t = [t["type"] for t in ds["coordinateTransformations"]]
        assert kinds_t in (["scale"], ["scale", "translation"])  # exactly one scale, first
        for t in ds["coordinateTransformations"]:
            assert len(t.get("scale", t.get("translation"))) == ndim
        scales.append(ds["coordinateTransformations"][0]["scale"])
    spatial = np.asarray(scales)[:, -3:]
    assert np.all(np.diff(spatial, axis=0) > 0)  # ordered from the highest resolution down


def test_ome_zarr_multiscale_image_in_world_coordinates(store, tmp_path):
    res = export(store, tmp_path / "o", format="ome-zarr", quantity="refractivity")
    (path,) = res.entry_points
    assert path.name == "refractivity.ome.zarr"
    root = zarr.open_group(str(path), mode="r")
    meta = root.attrs["ome"]
    _check_ngff(meta, 4)
    datasets = meta["multiscales"][0]["datasets"]
    assert [tuple(root[d["path"]].shape) for d in datasets] == [(FX.N_FRAMES, 16, 20, 24), (FX.N_FRAMES, 8, 10, 12)]
    g = zarr.open_group(str(store), mode="r")
    lvl0, lvl1 = (np.asarray(root[d["path"]][:]) for d in datasets)
    np.testing.assert_array_equal(lvl0, g["refractivity"][:])
    # every level-0 sample is the analytic blob at the world point and time the metadata declare
    t_idx, iz, iy, ix = np.meshgrid(*(np.arange(n) for n in lvl0.shape), indexing="ij")
    w = _ome_world(datasets[0], np.stack([t_idx, iz, iy, ix], axis=-1))
    assert w[:, 0, 0, 0, 0] == pytest.approx((1 + np.arange(FX.N_FRAMES)) / FX.FRAME_RATE)
    for f in range(FX.N_FRAMES):
        want = analytic(w[f][..., [3, 2, 1]], f)  # (x, y, z) world points
        assert np.abs(lvl0[f] - want).max() < 1e-9
    # level 1: 2x2x2 means, each placed at the centre of the eight voxels it averages
    np.testing.assert_allclose(lvl1, lvl0.reshape(FX.N_FRAMES, 8, 2, 10, 2, 12, 2).mean(axis=(2, 4, 6)), rtol=1e-6)
    c1 = _ome_world(datasets[1], [0, 3, 4, 5])[1:]
    c0 = np.mean([_ome_world(datasets[0], [0, 6 + a, 8 + b, 10 + c])[1:]
                  for a in (0, 1) for b in (0, 1) for c in (0, 1)], axis=0)
    np.testing.assert_allclose(c1, c0, atol=1e-15)


def test_ome_zarr_vectors_hull_and_unfinished_frames(store, tmp_path):
    g = zarr.open_group(str(store), mode="r")
    grad = zarr.open_group(str(export(store, tmp_path / "g", format="ome-zarr", quantity="gradient").entry_points[0]))
    _check_ngff(grad.attrs["ome"], 5)
    assert [a["name"] for a in grad.attrs["ome"]["multiscales"][0]["axes"]] == ["t", "c", "z", "y", "x"]
    np.testing.assert_array_equal(grad["0"][:], np.moveaxis(g["gradient"][:], -1, 1))
    hull = zarr.open_group(str(export(store, tmp_path / "h", format="ome-zarr", quantity="hull").entry_points[0]))
    h0, h1 = hull["0"][:], hull["1"][:]
    assert h0.dtype == np.uint8 and np.array_equal(h0.astype(bool), g["hull"][:])
    np.testing.assert_array_equal(h1, h0.reshape(FX.N_FRAMES, 8, 2, 10, 2, 12, 2).max(axis=(2, 4, 6)))
    partial = FX.make_store(tmp_path / "p", partial="unfinished")  # frame 2 not integrated
    res = export(partial, tmp_path / "u", format="ome-zarr", quantity="temperature")
    assert res.skipped == [3]
    t = zarr.open_group(str(res.entry_points[0]))["0"][:]
    assert np.isfinite(t[:2]).all() and np.isnan(t[2]).all()
