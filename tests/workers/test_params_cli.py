"""`schlieren run --params` and `schlieren.run(params=...)`: bad values refused before any store exists."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("text,field", [
    ("tomography:\n  reg_weight: abc\n", "tomography.reg_weight"),
    ("flow:\n  texture_correction: 'no'\n", "flow.texture_correction"),
    ("tomography:\n  max_iter: 1e9\n  tol: 0\n", "tomography.max_iter"),
    ("flow:\n  levels: 2.7\n", "flow.levels"),
    ("poisson:\n  tol: .nan\n", "poisson.tol"),
])
def test_run_refuses_bad_params_before_the_store_exists(tiny_session, tmp_path, capsys, text, field):
    from schlieren.workers.cli import main

    p = tmp_path / "params.yaml"
    p.write_text(text)
    out = tmp_path / "out.zarr"
    assert main(["run", str(tiny_session.session), "--out", str(out), "--serial", "--params", str(p)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and str(p) in err[0] and f"field {field}:" in err[0], err
    assert not out.exists()


def test_python_configurations_are_checked_before_the_store_exists(tiny_session, tmp_path):
    import dataclasses

    from schlieren.pipeline.params import ParamsError
    from schlieren.pipeline.stages import RunConfig
    from schlieren.workers.run import run_session

    cfg = RunConfig()
    with pytest.raises(ParamsError, match="FlowParams.presmooth"):  # refused where it is built
        dataclasses.replace(cfg.flow, presmooth=float("inf"))
    flow = dataclasses.replace(cfg.flow)
    object.__setattr__(flow, "presmooth", float("inf"))  # changed behind the construction's back
    bad = dataclasses.replace(cfg, flow=flow)
    out = tmp_path / "out.zarr"
    with pytest.raises(ParamsError, match="flow.presmooth"):
        run_session(tiny_session.session, out, serial=True, config=bad)
    assert not out.exists()


def test_a_store_of_another_configuration_names_the_differences_and_overwrite_replaces_it(
        tiny_session, serial_store, tmp_path, capsys):
    import shutil

    import numpy as np
    import zarr

    from schlieren.workers.cli import main

    out = tmp_path / "run.zarr"
    shutil.copytree(serial_store, out)
    p = tmp_path / "params.yaml"
    p.write_text("tomography:\n  max_iter: 30\nhull:\n  margin_px: 0.5\n")
    args = ["run", str(tiny_session.session), "--out", str(out), "--serial", "--no-progress", "--params", str(p)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "params.tomography.max_iter: 25 -> 30" in err and "params.hull.margin_px: 0.0 -> 0.5" in err
    assert "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert main(args + ["--overwrite"]) == 0
    g = zarr.open_group(str(out), mode="r")
    assert '"max_iter":30' in g.attrs["params"]
    assert np.isfinite(np.asarray(g["refractivity"][...])).all()
    # --overwrite never deletes what is not a result store
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    assert main(["run", str(tiny_session.session), "--out", str(other), "--serial", "--overwrite"]) == 2
    assert (other / "keep.txt").read_text() == "x"
