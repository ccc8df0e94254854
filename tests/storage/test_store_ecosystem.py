"""The result store in the xarray / Zarr / netCDF ecosystem (issue 15, item 5)."""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest
import zarr


def test_open_zarr_with_default_arguments_is_warning_free(serial_store):
    import xarray as xr

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = xr.open_zarr(serial_store)
        zarr.open_group(str(serial_store), mode="r").members(max_depth=None)  # every node is a Zarr node
    assert ds["temperature"].dims == ("frame", "z", "y", "x")
    assert not (serial_store / "_cache").exists()  # the geometry cache lives outside the hierarchy


def test_to_netcdf_round_trips_values_and_attributes(serial_store, tmp_path):
    import xarray as xr

    ds = xr.open_zarr(serial_store)
    path = tmp_path / "run.nc"
    ds.to_netcdf(path)
    back = xr.open_dataset(path)
    np.testing.assert_array_equal(back["temperature"].values, ds["temperature"].values)
    np.testing.assert_array_equal(back["frame"].values, ds["frame"].values)
    assert list(back["camera"].values) == list(ds["camera"].values)
    # nested root attributes are JSON text that parses back to the manifest and parameters
    assert json.loads(back.attrs["params"])["tomography"]["max_iter"] > 0
    assert json.loads(back.attrs["session"])["format"] == "schlieren-session/1"
    assert set(back.attrs["json_attrs"].split()) >= {"session", "params", "run", "stage_times"}


def test_cf_attributes_and_pixel_coordinates(serial_store):
    import xarray as xr

    from schlieren.storage.store import ResultStore

    ds = xr.open_zarr(serial_store)
    assert ds["temperature"].attrs["standard_name"] == "air_temperature"
    assert ds["temperature"].attrs["units"] == "K"
    assert ds["density"].attrs["standard_name"] == "air_density" and ds["density"].attrs["units"] == "kg m-3"
    assert ds["gradient"].attrs["units"] == "m-1" and ds["refractivity"].attrs["units"] == "1"
    assert [ds[a].attrs["axis"] for a in "xyz"] == ["X", "Y", "Z"] and ds["z"].attrs["positive"] == "up"
    assert all(ds[a].attrs["units"] == "m" for a in "xyz")
    for name in ds.data_vars:
        assert "long_name" in ds[name].attrs and "units" in ds[name].attrs, name
    # u/v: the image position of every flow cell's centre (cell j averages pixels f j .. f j + f - 1)
    f = ResultStore.open(serial_store, mode="r").attrs["run"]["flow_factor"]
    assert ds["flow"].dims[2:4] == ("v", "u")
    np.testing.assert_array_equal(ds["u"].values, f * np.arange(ds.sizes["u"]) + (f - 1) / 2)
    np.testing.assert_array_equal(ds["v"].values, f * np.arange(ds.sizes["v"]) + (f - 1) / 2)
    assert ds["u"].attrs["units"] == "pixel"


def test_one_frame_numbering_everywhere(serial_store, tiny_session, tmp_path):
    """evaluate, export and the store all use the capture frame index."""
    import xarray as xr

    from schlieren.workers.evaluate import evaluate
    from schlieren.storage.export import export

    frames = [int(v) for v in xr.open_zarr(serial_store)["frame"].values]
    assert frames[0] > 0  # the tiny session starts after its strobe frames
    assert [r["frame"] for r in evaluate(serial_store, tiny_session.truth)["frames"]] == frames
    res = export(serial_store, tmp_path / "e", format="nrrd", frames=(frames[1], frames[2]))
    assert [p.name for p in res.entry_points] == [f"refractivity_{frames[1]:05d}.nrrd"]


def test_clean_removes_the_cache_and_a_rerun_only_rebuilds_it_when_needed(serial_store, tmp_path, capsys):
    from schlieren.storage.arrays_cache import cache_root
    from schlieren.storage.store import ResultStore
    from schlieren.workers.cli import main
    from schlieren.workers.run import run_session

    store = tmp_path / "run.zarr"
    shutil.copytree(serial_store, store)
    shutil.copytree(cache_root(serial_store), cache_root(store))
    before = np.asarray(zarr.open_group(str(store), mode="r")["refractivity"][...])
    assert main(["clean", str(store)]) == 0
    assert "MiB" in capsys.readouterr().out
    assert not cache_root(store).exists()
    st = ResultStore.open(store, mode="r")
    assert not st.is_done("geometry", ()) and st.done("tomography").all()
    # everything is complete: a rerun has nothing to do, and does not rebuild the geometry
    summary = run_session(st.attrs["session_path"], store, serial=True)
    assert summary.ok and summary.tasks == 0
    assert not cache_root(store).exists()
    np.testing.assert_array_equal(np.asarray(zarr.open_group(str(store), mode="r")["refractivity"][...]), before)


def test_clean_refuses_what_is_not_a_store(tmp_path, capsys):
    from schlieren.workers.cli import main

    assert main(["clean", str(tmp_path / "nothing.zarr")]) == 2
    assert "no result store" in capsys.readouterr().err
