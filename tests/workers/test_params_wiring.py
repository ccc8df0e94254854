"""Every run parameter reaches the code that uses it, and every value a run derives in place
of a parameter is logged once and stored beside the requested one (tiny session)."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
from params_reads import params_classes, recording_reads
from store_compare import copy_store

from schlieren.pipeline.params import class_schema
from schlieren.storage.store import ResultStore

REPO = Path(__file__).resolve().parents[2]


def _direct_reads(store: Path, tmp_path: Path) -> set:
    """The fields read by one frame's tomography task with ``reconstruction: direct`` (on a copy)."""
    from schlieren.workers.tasks import context
    from schlieren.workers.tasks.tomography import tomography_task

    copy = copy_store(store, tmp_path)
    ctx = context(str(copy), "direct-reads")
    ctx = dataclasses.replace(ctx, config=dataclasses.replace(ctx.config, reconstruction="direct"))
    with recording_reads() as reads:
        tomography_task(ctx, 0)
    return set(reads)


def _read_on_another_branch(cls, name: str) -> bool:
    """A field of a params object passed whole to a stage kernel (``params=``) that its
    package's kernels read as ``params.<name>`` on a branch the tiny run did not take."""
    import importlib

    path = Path(importlib.import_module(cls.__module__).__file__)
    files = [path] if path.parent.name == "pipeline" else sorted(path.parent.glob("*.py"))
    pattern = re.compile(rf"\bparams\.{re.escape(name)}\b")
    return any(pattern.search(p.read_text()) for p in files if p != path or path.parent.name == "pipeline")


def _unread(reads: set) -> tuple[list[str], list[str]]:
    """``(missing, branch_only)``: the fields no code read, and those only a branch the run
    did not take reads from a params object."""
    branch_only, missing = [], []
    for cls in params_classes():
        for fs in class_schema(cls):
            if (cls.__name__, fs.name) not in reads:
                (branch_only if _read_on_another_branch(cls, fs.name) else missing).append(f"{cls.__name__}.{fs.name}")
    return missing, branch_only


def test_every_parameter_is_read_by_the_run(serial_run, tmp_path):
    missing, branch_only = _unread(set(serial_run.reads) | _direct_reads(serial_run.store, tmp_path))
    assert not missing, ("declared but never passed to a kernel nor read by a run (a renamed or forgotten "
                         f"field): {missing}")
    # the tiny run's defaults leave only the diffusion tensor's own parameters (poisson.alpha 1)
    # and those of the stages it has off (spacetime, uncertainty) unread
    from schlieren.pipeline.stages import OPTIONAL_STAGES, RunConfig

    off = {type(getattr(RunConfig(), s.params)).__name__ for s in OPTIONAL_STAGES}
    rest = {b for b in branch_only if b.split(".")[0] not in off}
    assert rest <= {"PoissonParams.sigma", "PoissonParams.k", "PoissonParams.value_scale"}, branch_only


@pytest.mark.parametrize("field", [("FlowParams", "presmooth"), ("MaskParams", "grow_factor"),
                                   ("RunConfig", "warm_start_block"), ("FlashParams", "min_contrast")])
def test_a_field_no_code_reads_fails_the_check(serial_run, field):
    """What the test above catches: a field the glue stopped passing (or a kernel stopped reading)."""
    assert field in serial_run.reads
    missing, _ = _unread(set(serial_run.reads) - {field})
    assert missing == [".".join(field)]


OVERRIDE_LINES = {
    "flow.window": r"flow\.window 17 -> (\d+) px from window_per_voxel 3\.8 x [\d.]+ px per voxel",
    "flow.presmooth": r"flow\.presmooth auto -> ([\d.]+) px from the sharpness of each camera's reference",
    "flow.factor": r"flow\.factor 3 -> (\d) px per flow cell from auto_factor \([\d.]+ flow cells per voxel edge; "
                   r"3 would leave [\d.]+\)",
    "tomography.ray_binning": r"tomography\.ray_binning 0 -> (\d+) flow cells from [\d.]+ flow cells per voxel edge",
    "tomography.n_ambient": r"tomography\.n_ambient 1\.00029 -> ([\d.]+) from the session's medium\.n_ambient",
    "direct.n_ambient": r"direct\.n_ambient 1\.00029 -> ([\d.]+) from the session's medium\.n_ambient",
    "tomography.reg_weight": r"tomography\.reg_weight 0\.1 -> ([\d.e-]+) from the discrepancy principle on frame 1",
    "tomography.flow_window": r"tomography\.flow_window \(not given\) -> ([\d.]+) flow cells from each camera's "
                              r"flow averaging",
}


def test_the_run_logs_each_derived_value_once(serial_run):
    for path, pattern in OVERRIDE_LINES.items():
        found = [ln for ln in serial_run.log if re.match(pattern, ln)]
        assert len(found) == 1, (path, [ln for ln in serial_run.log if ln.startswith(path)])


def test_the_store_records_the_requested_and_the_effective_value(serial_run):
    store = ResultStore.open(serial_run.store, mode="r")
    derived = store.attrs["derived"]
    assert set(derived) == set(OVERRIDE_LINES)
    for path, pattern in OVERRIDE_LINES.items():
        (line,) = [ln for ln in serial_run.log if re.match(pattern, ln)]
        shown = re.match(pattern, line).group(1)
        eff = derived[path]["effective"]
        assert float(shown) == pytest.approx(np.unique(eff)[0] if isinstance(eff, list) else eff, rel=1e-5), path
        assert derived[path]["from"] and "requested" in derived[path], path
    # the effective values are those the run used
    run = store.attrs["run"]
    assert derived["flow.factor"] == {"requested": 3, "effective": run["flow_factor"], "unit": "px per flow cell",
                                      "from": derived["flow.factor"]["from"]}
    assert derived["flow.window"]["requested"] == 17 and len(derived["flow.window"]["effective"]) == 4
    assert derived["tomography.reg_weight"]["effective"] == float(np.asarray(store.read("reg_weight", ()))[0])
    np.testing.assert_array_equal(derived["tomography.flow_window"]["effective"],
                                  np.asarray(store.read("flow_window", ())))
    assert derived["tomography.n_ambient"]["effective"] == store.attrs["params"]["tomography"]["n_ambient"]
    # netCDF-compatible like the other nested attributes: JSON text listed in json_attrs
    import zarr

    raw = zarr.open_group(str(serial_run.store), mode="r").attrs
    assert "derived" in raw["json_attrs"].split() and json.loads(raw["derived"]) == derived


def test_the_windows_logged_are_the_deflection_tasks(serial_run):
    from schlieren.workers.tasks import context, flow_params

    store = ResultStore.open(serial_run.store, mode="r")
    ctx = context(str(serial_run.store), "windows")
    windows = [flow_params(ctx, c).window for c in range(len(ctx.cameras))]
    assert store.attrs["derived"]["flow.window"]["effective"] == windows


def test_a_resumed_run_keeps_or_reads_back_the_chosen_values(serial_run, tmp_path, caplog):
    import zarr

    from schlieren.workers.run import run_session

    copy = copy_store(serial_run.store, tmp_path)
    before = ResultStore.open(copy, mode="r").attrs["derived"]
    g = zarr.open_group(str(copy), mode="r+")
    g.attrs["derived"] = "{}"  # a store written before the attribute existed
    session = ResultStore.open(copy, mode="r").attrs["session_path"]
    with caplog.at_level("INFO", logger="schlieren"):
        summary = run_session(session, copy, serial=True)
    assert summary.ok and summary.tasks == 0
    assert ResultStore.open(copy, mode="r").attrs["derived"] == before
    assert any(m.startswith("flow.window 17 -> ") for m in caplog.messages)
    assert not any(m.startswith("tomography.reg_weight") for m in caplog.messages)  # not chosen again


def test_a_voxel_from_the_cameras_is_a_derived_value(tiny_session):
    from schlieren.pipeline.geometry import Grid, auto_voxel_size
    from schlieren.pipeline.overrides import session_overrides
    from schlieren.storage.session import load_session

    s = load_session(tiny_session.session, check_files=False)
    assert session_overrides(s.cameras, s.grid, voxel_size_given=True) == []
    voxel, info = auto_voxel_size(s.cameras, s.grid.vmin, s.grid.vmax)
    grid = Grid(s.grid.vmin, s.grid.vmax, voxel)
    (o,) = session_overrides(s.cameras, grid, voxel_size_given=False)
    assert o.record() == {"requested": None, "effective": voxel, "unit": "m", "from": o.source}
    assert re.match(rf"volume\.voxel_size \(not given\) -> {voxel:.6g} m from the cameras' pixel footprint "
                    rf"\({info['px_per_voxel']:.2f} px per voxel, limited by {info['limited_by']}\)$", o.line())


def test_the_report_shows_the_requested_and_the_effective_values(serial_run):
    from schlieren.workers.report.build import _parameters_html

    attrs = ResultStore.open(serial_run.store, mode="r").attrs
    page = _parameters_html(attrs["params"], attrs["derived"])
    windows = ", ".join(str(w) for w in attrs["derived"]["flow.window"]["effective"])
    assert f"<tr><td>flow.window</td><td>17</td><td>{windows}</td><td>px</td><td>window_per_voxel " in page
    assert "<td>volume.voxel_size</td>" not in page  # the tiny session's manifest gives its voxel
    assert page.count("<tr><td>") == len(attrs["derived"])
    assert "&quot;flow&quot;: {" in page  # then every parameter, as stored


def test_a_factor_auto_factor_keeps_says_only_what_it_leaves(tiny_session):
    from schlieren.pipeline.overrides import bind_run
    from schlieren.pipeline.stages import RunConfig
    from schlieren.storage.session import load_session

    s = load_session(tiny_session.session, check_files=False)
    cfg = RunConfig(flow=dataclasses.replace(RunConfig().flow, factor=2))  # the tiny run's auto factor
    bound, overrides = bind_run(cfg, s.cameras, s.grid, s.medium.n_ambient)
    (o,) = [o for o in overrides if o.path == "flow.factor"]
    assert bound.flow.factor == 2 and (o.requested, o.effective) == (2, 2)
    assert re.fullmatch(r"flow\.factor 2 -> 2 px per flow cell from auto_factor \([\d.]+ flow cells per voxel edge\)",
                        o.line())
