"""Preflight (workers/preflight.py): memory per task from the measured model times the tasks
each worker runs at once times the workers, and the store's disk space, checked before
anything is written; and the model's inputs against brute force."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from schlieren.pipeline import resources
from schlieren.pipeline.geometry import FlowGrid
from schlieren.pipeline.stages import RunConfig
from schlieren.storage.errors import ResourceError
from schlieren.storage.session import load_session
from schlieren.workers import preflight as pf
from schlieren.workers.run import run_layout, run_session

MiB = 2.0 ** 20
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def session(tiny_session):
    return load_session(tiny_session.session)


@pytest.fixture
def model(monkeypatch):
    """A known model: 3-D tasks 1 kB per voxel, 2-D tasks 10 B per pixel, 100 MiB per process."""
    monkeypatch.setattr(resources, "TASK_MODEL", {"tomography": (0.0, 1000.0, 0.0, 0.0),
                                                  "geometry": (5 * MiB, 0.0, 0.0, 0.0)})
    monkeypatch.setattr(resources, "PIXEL_MODEL", {"deflection": (0.0, 10.0)})
    monkeypatch.setattr(resources, "PROCESS_BYTES", 100 * MiB)
    monkeypatch.setattr(resources, "MODEL_MARGIN", 1.0)
    monkeypatch.setattr(resources, "HELD_BYTES_PER_CROSSING", 0.0)  # see the test below


def test_memory_is_per_task_times_slots_times_workers(session, model, monkeypatch, tmp_path):
    cfg = RunConfig()
    layout = run_layout(session, cfg)[0]
    nvox = math.prod(session.grid.shape)
    w, h = session.cameras[0].image_size
    one = 100 * MiB + 1000.0 * nvox  # a worker's 3-D task dominates its 2-D ones here
    assert 1000.0 * nvox > 10.0 * w * h
    monkeypatch.setattr(pf, "_machine_memory", lambda: 3.5 * one)
    res = pf.preflight(session, cfg, layout, tmp_path / "a.zarr", workers=[pf.WorkerSlots()] * 3)
    assert res.worker_peak == [pytest.approx(one)] * 3 and res.memory.stage_3d == "tomography"
    with pytest.raises(ResourceError) as info:
        pf.preflight(session, cfg, layout, tmp_path / "a.zarr", workers=[pf.WorkerSlots()] * 4)
    msg = str(info.value)
    assert "4 worker(s) on this machine" in msg and "--workers 3" in msg and "benchmarks/memory.py" in msg
    assert "\n" not in msg
    # two task slots per worker, one TOMO: a 3-D and a 2-D task at once
    two = pf.preflight(session, cfg, layout, tmp_path / "a.zarr", workers=[pf.WorkerSlots(threads=2)])
    assert two.worker_peak[0] == pytest.approx(one + 10.0 * w * h)
    # remote workers count against their own limit, not this machine's memory
    remote = [pf.WorkerSlots(memory_limit=2 * one, local=False)] * 8
    pf.preflight(session, cfg, layout, tmp_path / "a.zarr", workers=remote)
    with pytest.raises(ResourceError, match="more than its memory limit"):
        pf.preflight(session, cfg, layout, tmp_path / "a.zarr",
                     workers=[pf.WorkerSlots(threads=2, tomo=2, memory_limit=1.2 * one, local=False)])


def test_memory_counts_the_block_restriction_a_tomography_thread_keeps(session, model, monkeypatch, tmp_path):
    """Each 3-D slot of a worker keeps one more block restriction between its solves:
    HELD_BYTES_PER_CROSSING per ray-voxel crossing, once per TOMO slot, not per 2-D slot."""
    cfg = RunConfig()
    layout = run_layout(session, cfg)[0]

    def peak(tomo):
        return pf.preflight(session, cfg, layout, tmp_path / "a.zarr",
                            workers=[pf.WorkerSlots(threads=2, tomo=tomo)]).worker_peak[0]

    before = {t: peak(t) for t in (1, 2)}
    monkeypatch.setattr(resources, "HELD_BYTES_PER_CROSSING", 7.0)
    crossings = resources.estimate_memory(session.cameras, session.grid, FlowGrid(session.cameras[0].image_size,
                                          cfg.flow_factor), session.cameras[0].image_size).crossings
    assert crossings > 0
    for t in (1, 2):
        assert peak(t) == pytest.approx(before[t] + t * 7.0 * crossings)
    with pytest.raises(ResourceError, match="kept between solves"):
        pf.preflight(session, cfg, layout, tmp_path / "a.zarr", workers=[pf.WorkerSlots(memory_limit=1.0, local=False)])


class _FakeClient:
    """What preflight asks a Dask client: its workers (never reached: refused first)."""

    def __init__(self, n, limit):
        self.n, self.limit = n, limit

    def scheduler_info(self, n_workers=-1):
        return {"workers": {f"tcp://127.0.0.1:{4000 + i}": {"host": "127.0.0.1", "nthreads": 1,
                                                            "memory_limit": self.limit,
                                                            "resources": {"TOMO": 1}} for i in range(self.n)}}


def test_a_run_that_does_not_fit_is_refused_before_the_store_exists(tiny_session, model, monkeypatch, tmp_path):
    out = tmp_path / "never.zarr"
    monkeypatch.setattr(pf, "_machine_memory", lambda: 150 * MiB)
    with pytest.raises(ResourceError, match="1 worker"):
        run_session(tiny_session.session, out, serial=True)
    monkeypatch.setattr(pf, "_machine_memory", lambda: 64 * 2.0 ** 30)
    with pytest.raises(ResourceError, match="memory limit"):
        run_session(tiny_session.session, out, client=_FakeClient(2, 120 * MiB))
    assert not out.exists() and not Path(f"{out}.lease").exists()


def test_disk_space_is_estimated_and_checked(session, monkeypatch, tmp_path):
    cfg = RunConfig()
    layout = run_layout(session, cfg)[0]
    arrays = sum(math.prod(s.shape) * (16 if s.dtype == "str" else np.dtype(s.dtype).itemsize) for s in layout)
    res = pf.preflight(session, cfg, layout, tmp_path / "s.zarr", workers=[pf.WorkerSlots()])
    assert res.disk_needed >= arrays
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(pf.shutil, "disk_usage", lambda p: usage._replace(free=int(res.disk_needed * 0.5)))
    with pytest.raises(ResourceError) as info:
        pf.preflight(session, cfg, layout, tmp_path / "s.zarr", workers=[pf.WorkerSlots()])
    assert f"file {tmp_path / 's.zarr'}" in str(info.value) and "free" in str(info.value)
    # a resumed store already holds part of it: only the rest must fit
    (tmp_path / "s.zarr").mkdir()
    (tmp_path / "s.zarr" / "blob").write_bytes(b"\0" * int(res.disk_needed * 0.6))
    pf.preflight(session, cfg, layout, tmp_path / "s.zarr", workers=[pf.WorkerSlots()])


def test_ray_crossings_match_brute_force_sampling(session):
    fg = FlowGrid(session.cameras[0].image_size, 3)
    grid = session.grid
    crossings, rays = resources.ray_crossings(session.cameras, grid, fg, max_rays=10 ** 9)
    assert rays == len(session.cameras) * fg.shape[0] * fg.shape[1]
    lo, hi = np.asarray(grid.vmin), np.asarray(grid.vmax)
    total = 0.0
    step = grid.voxel_size / 20
    for cam in session.cameras:
        origin, d = cam.rays(fg.pixel_centres()[::4, ::4].reshape(-1, 2))
        t = np.arange(0.0, 6.0, step)
        inside = 0
        for chunk in np.array_split(d, 8):
            pts = origin + t[None, :, None] * chunk[:, None, :]
            inside += int(np.all((pts >= lo) & (pts <= hi), axis=-1).sum())
        total += inside * step * 16  # every 4th ray in both directions
    assert crossings == pytest.approx(total / grid.voxel_size, rel=0.05)
    # the sub-sampled estimate the preflight uses agrees
    assert resources.ray_crossings(session.cameras, grid, fg)[0] == pytest.approx(crossings, rel=0.02)


def test_the_model_is_the_one_benchmarks_memory_measured():
    recorded = json.loads((REPO / "benchmarks" / "results" / "memory.json").read_text())["model"]
    assert resources.PIXEL_MODEL == {k: tuple(v) for k, v in recorded["pixel_model"].items()}
    assert resources.TASK_MODEL == {k: tuple(v) for k, v in recorded["task_model"].items()}
    assert resources.CACHE_MODEL == tuple(recorded["cache_model"])
    assert resources.PROCESS_BYTES == recorded["process_bytes"]
    assert resources.MODEL_MARGIN == recorded["margin"] >= 1.0
    assert resources.BYTES_PER_VOXEL > 0 and resources.BYTES_PER_PIXEL > 0


def test_the_model_predicts_every_measurement_it_was_fitted_to_within_its_margin():
    """The preflight never under-estimates a measured task (the margin covers the fit)."""
    rows = json.loads((REPO / "benchmarks" / "results" / "memory.json").read_text())["rows"]
    for r in rows:
        for stage, (c, a, b, q) in resources.TASK_MODEL.items():
            got = resources.MODEL_MARGIN * (c + a * r["voxels"] + b * r["crossings"] + q * r["rays"])
            assert got >= r["tasks"][stage]["bytes"] * 0.999, (stage, r["image"], r["voxel_size"])
        for stage, (c, p) in resources.PIXEL_MODEL.items():
            assert resources.MODEL_MARGIN * (c + p * r["pixels"]) >= r["tasks"][stage]["bytes"] * 0.999
