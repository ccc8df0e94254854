"""The optional ``uncertainty`` stage end to end on the tiny session: its arrays, their CF
attributes in xarray, export, the report, and resume / verify like every other stage."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from schlieren.pipeline.stages import RunConfig
from schlieren.workers.run import run_session
from store_compare import assert_same_store

SIGMAS = {"refractivity_sigma": ("refractivity", "1"), "density_sigma": ("density", "kg m-3"),
          "temperature_sigma": ("temperature", "K")}


def _config() -> RunConfig:
    return RunConfig(uncertainty=dataclasses.replace(RunConfig().uncertainty, enabled=True, samples=2))


@pytest.fixture(scope="module")
def unc_store(tiny_session, tmp_path_factory):
    out = tmp_path_factory.mktemp("unc") / "store.zarr"
    summary = run_session(tiny_session.session, out, serial=True, config=_config())
    assert summary.ok, summary.failures
    return out


def test_sigma_arrays_beside_the_values(unc_store, serial_store):
    g = zarr.open_group(str(unc_store), mode="r")
    ref = zarr.open_group(str(serial_store), mode="r")
    hull = np.asarray(g["hull"][...])
    for sigma, (value, units) in SIGMAS.items():
        a, v = g[sigma], g[value]
        assert a.shape == v.shape and a.chunks == v.chunks and a.metadata.dimension_names == v.metadata.dimension_names
        assert v.attrs["ancillary_variables"] == sigma
        assert a.attrs["units"] == units and a.attrs["standard_name"].endswith(" standard_error")
        assert a.attrs["origin"] == v.attrs["origin"] and a.attrs["voxel_size"] == v.attrs["voxel_size"]
        s = np.asarray(a[...])
        assert np.all(s[~hull] == 0)
        if sigma != "temperature_sigma":  # T's sigma is NaN where T is (r <= 0)
            assert np.all(np.isfinite(s)) and np.all(s >= 0) and s[hull].min() > 0
    # the values are the default run's, bit for bit (the stage only adds)
    for name in ("gradient", "refractivity", "density", "temperature"):
        np.testing.assert_array_equal(np.asarray(g[name][...]), np.asarray(ref[name][...]))
    assert "uncertainty" in g["status"] and np.all(np.asarray(g["status/uncertainty"][...]) == 1)
    assert "refractivity_sigma" not in ref and "uncertainty" not in ref["status"]
    assert "ancillary_variables" not in ref["refractivity"].attrs


def test_xarray_sees_the_standard_error_as_the_values_ancillary_variable(unc_store):
    from schlieren.storage.integrity import open_dataset

    ds = open_dataset(unc_store)
    for sigma, (value, units) in SIGMAS.items():
        assert ds[value].attrs["ancillary_variables"] == sigma
        assert ds[sigma].dims == ds[value].dims and ds[sigma].attrs["units"] == units
    assert ds["refractivity_sigma"].attrs["standard_name"] == "refractivity standard_error"
    assert ds["temperature_sigma"].attrs["standard_name"] == "air_temperature standard_error"
    assert "time" in ds["refractivity_sigma"].coords


@pytest.mark.parametrize("fmt", ["vti", "raw", "nrrd", "ome-zarr"])
def test_export_writes_the_sigma_with_the_values(unc_store, tmp_path, fmt):
    from schlieren.workers.report import generate_export

    res = generate_export(unc_store, tmp_path / fmt, format=fmt, quantity="temperature")
    names = {p.name for p in res.files}
    assert any(n.startswith("temperature_sigma") for n in names), names
    assert any(n.startswith("temperature") and "sigma" not in n for n in names), names
    if fmt == "nrrd":
        import nrrd

        f = sorted((tmp_path / fmt).glob("temperature_sigma_*.nrrd"))[0]
        data, header = nrrd.read(str(f))
        frame = int(header["frame"]) - int(zarr.open_group(str(unc_store), mode="r")["frame"][0])
        expect = np.asarray(zarr.open_group(str(unc_store), mode="r")["temperature_sigma"][frame])
        np.testing.assert_array_equal(data.transpose(2, 1, 0), expect)
    only = generate_export(unc_store, tmp_path / f"{fmt}-only", format=fmt, quantity="refractivity_sigma")
    assert only.files and all("refractivity_sigma" in p.name for p in only.files)


def test_report_shows_the_sigma_slices_and_the_axis_profile(unc_store, tmp_path):
    from schlieren.workers.report import build_report

    page = build_report(unc_store, tmp_path / "rep")
    text = page.read_text()
    assert 'id="uncertainty"' in text or "Uncertainty" in text
    for f in ("uncertainty_refractivity.png", "uncertainty_temperature.png", "uncertainty_density.png",
              "uncertainty_axis.png"):
        assert (tmp_path / "rep" / "figures" / f).exists(), f


def test_a_lost_sigma_chunk_is_recomputed_and_a_repaired_gradient_redoes_the_uncertainty(unc_store, tiny_session,
                                                                                        tmp_path):
    from schlieren.storage.store import ResultStore
    from schlieren.workers.verify import verify_store

    out = tmp_path / "s.zarr"
    shutil.copytree(unc_store, out)
    (out / "refractivity_sigma" / "c" / "1" / "0" / "0" / "0").unlink()
    # without its geometry cache (beside the store) the stage needs the geometry built again
    again = run_session(tiny_session.session, out, serial=True, config=_config())
    assert again.ok and [(p.array, p.stage, p.index) for p in again.integrity.problems] == \
        [("refractivity_sigma", "uncertainty", (1,))]
    assert {(r["stage"], tuple(r["index"])) for r in again.receipts} == {("uncertainty", (1,)), ("geometry", ())}
    assert_same_store(unc_store, out)  # the seeded samples give the same sigma again
    # damage upstream: the repair clears the frame's uncertainty with its integration
    b = bytearray((out / "gradient" / "c" / "2" / "0" / "0" / "0" / "0").read_bytes())
    b[len(b) // 2] ^= 0x10
    (out / "gradient" / "c" / "2" / "0" / "0" / "0" / "0").write_bytes(bytes(b))
    report = verify_store(ResultStore.open(out, mode="r+"), full=True, repair=True)
    assert report.invalidated.get("uncertainty") == 1 and report.invalidated.get("integrate") == 1
    redo = run_session(tiny_session.session, out, serial=True, config=_config())
    assert redo.ok and ("uncertainty", (2,)) in {(r["stage"], tuple(r["index"])) for r in redo.receipts}
    assert_same_store(unc_store, out)


def test_a_default_store_resumes_with_uncertainty_refused_as_another_configuration(serial_store, tiny_session,
                                                                                    tmp_path):
    """Switching the stage on changes the run's parameters: the store of the default run is not
    silently extended (its fingerprint differs), as for any other parameter."""
    from schlieren.storage.errors import StoreError

    out = tmp_path / "d.zarr"
    shutil.copytree(serial_store, out)
    with pytest.raises(StoreError):
        run_session(tiny_session.session, out, serial=True, config=_config())
    assert Path(out / "refractivity").exists()
