"""The spine: a synthetic capture through every stage, against its ground truth.

* the serial loop and the Dask executor produce identical stores;
* the reconstruction's PSNR against the truth is above a floor for this tiny rig;
* a run killed with SIGKILL midway and rerun computes only the missing chunks and ends
  identical to an uninterrupted run;
* bad data in one frame fails that camera-frame's task with a message naming it, keeps
  every other completed chunk, and the CLI exits non-zero with a summary.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from schlieren.storage.store import decode_attrs

from schlieren.workers.run import run_session

from store_compare import assert_same_store, sigkill_when


def test_every_stage_completed_and_time_is_recorded(serial_store, tiny_session):
    g = zarr.open_group(str(serial_store), mode="r")
    for name, marker in g["status"].arrays():
        assert np.all(np.asarray(marker[...]) == 1), name
    t = np.asarray(g["time"][:])
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)
    # strobe sync recovered the hidden offsets within two line times
    truth = zarr.open_group(str(tiny_session.truth), mode="r")
    off_true = np.asarray(truth["time_offset"][:])
    assert np.abs(np.asarray(g["time_offset"][:]) - off_true).max() < 2 * 1.54e-5
    assert set(decode_attrs(g.attrs)["stage_times"]) >= {"deflection", "tomography", "integrate"}


def test_reconstruction_matches_truth(serial_store, tiny_session):
    from schlieren.workers.evaluate import evaluate

    res = evaluate(serial_store, tiny_session.truth)
    # 4 cameras, 192x144 images, 5 mm voxels: far from the paper's rig, but well above noise
    assert res["overall"]["psnr"] > 30.0, res["overall"]
    temp = np.asarray(zarr.open_group(str(serial_store), mode="r")["temperature"][0])
    assert 250 < np.nanmin(temp) and np.nanmax(temp) < 800


def test_threshold_pools_the_summaries_the_potential_tasks_wrote(serial_store, tmp_path):
    from schlieren.pipeline import masks
    from schlieren.workers.tasks import TaskFailed, run_task

    g = zarr.open_group(str(serial_store), mode="r")
    pots = np.asarray(g["potential"][...])
    sums = np.asarray(g["potential_summary"][...])
    n_q = sums.shape[-1] - 1
    C, F = pots.shape[:2]
    # the map step: each camera-frame's summary is that of its stored potential
    for c in range(C):
        for k in range(F):
            np.testing.assert_array_equal(sums[c, k], masks.potential_summary(pots[c, k], n_quantiles=n_q))
    # the reduction: the 95th percentile of every smoothed |P| of the sequence, within
    # the quantile spacing of one summary
    pooled = np.concatenate([masks._magnitude(pots[c, k], 1.0).ravel() for c in range(C) for k in range(F)])
    thr = float(g["mask_threshold"][0])
    lo, hi = np.percentile(pooled, [95.0 - 100.0 / n_q, 95.0 + 100.0 / n_q])
    assert lo <= thr <= hi
    # summaries lost under set potential markers: the threshold task refuses to pool
    # fill values, naming the array and chunk (the verified resume recomputes them:
    # tests/e2e/test_lose_nothing.py)
    old = tmp_path / "old.zarr"
    shutil.copytree(serial_store, old)
    shutil.rmtree(old / "potential_summary" / "c")
    (old / "status" / "threshold" / "c").unlink()
    with pytest.raises(TaskFailed, match=r"threshold: ChunkError: .*field potential_summary: chunk \(0, 0, 0\) is missing"):
        run_task(str(old), "threshold", (), run_token="old-store")


@pytest.mark.system
def test_dask_executor_gives_the_identical_store(serial_store, tiny_session, tmp_path):
    from schlieren.workers.cluster import ClusterOptions, open_client

    out = tmp_path / "dask.zarr"
    with open_client(ClusterOptions(workers=2)) as (client, _info):
        # another grouping of frames into tasks than the serial run's default (blocks of
        # 3 leave partial blocks): the store must not depend on it
        summary = run_session(tiny_session.session, out, client=client, frames_per_task=3)
    assert summary.ok, summary.failures
    assert summary.executor == "dask"
    assert_same_store(serial_store, out)
    # one receipt per stage and index, whatever the grouping
    keys = [(r["stage"], tuple(r["index"])) for r in summary.receipts]
    assert len(keys) == len(set(keys))
    assert sum(1 for s, _ in keys if s == "mask") == zarr.open_array(out / "status" / "mask").size


def test_a_new_run_at_the_same_path_gets_fresh_worker_caches(serial_store, tiny_session, tmp_path):
    """Tasks cache the run's context per process, keyed by path and run token: a store
    deleted and made again at the same path by a run with other parameters, in the same
    process, must not be computed with the first run's settings or cached chunks."""
    import dataclasses

    from schlieren.pipeline.poisson import PoissonParams
    from schlieren.pipeline.stages import RunConfig

    other = RunConfig(poisson=PoissonParams(alpha=1.0), masks=dataclasses.replace(RunConfig().masks,
                                                                                 temporal_radius=0))
    same, fresh = tmp_path / "same.zarr", tmp_path / "fresh.zarr"
    assert run_session(tiny_session.session, same, serial=True).ok
    shutil.rmtree(same)
    assert run_session(tiny_session.session, same, serial=True, config=other).ok
    assert run_session(tiny_session.session, fresh, serial=True, config=other).ok
    assert_same_store(fresh, same)
    a = zarr.open_group(str(same), mode="r")
    b = zarr.open_group(str(serial_store), mode="r")
    assert not np.array_equal(np.asarray(a["mask"][...]), np.asarray(b["mask"][...]))


def _markers_set(store: Path) -> int:
    try:
        g = zarr.open_group(str(store), mode="r")
        return int(sum(np.asarray(m[...]).sum() for _, m in g["status"].arrays()))
    except Exception:
        return 0


def test_sigkill_then_rerun_resumes_and_matches(serial_store, tiny_session, tmp_path):
    out = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "schlieren.workers.cli", "run", str(tiny_session.session),
           "--out", str(out), "--serial", "--no-progress"]
    before = sigkill_when(cmd, lambda: _markers_set(out), 30)
    summary = run_session(tiny_session.session, out, serial=True)
    assert summary.ok, summary.failures
    assert summary.skipped >= before
    assert_same_store(serial_store, out)


def test_a_corrupt_frame_fails_only_its_tasks(tiny_session, tmp_path):
    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess, ignore=shutil.ignore_patterns("truth.zarr"))
    import yaml

    manifest = yaml.safe_load((sess / "session.yaml").read_text())
    first = manifest["frames"][0]
    bad = sess / "cam01" / "frames" / f"{first + 1:05d}.png"
    data = bytearray(bad.read_bytes())
    good = bytes(data)
    # a truncated file is refused before any work (one line, no store)...
    bad.write_bytes(good[: len(good) // 2])
    out = tmp_path / "bad.zarr"
    proc = subprocess.run([sys.executable, "-m", "schlieren.workers.cli", "run", str(sess), "--out",
                           str(out), "--serial", "--no-progress"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert f"camera cam01, field cameras[1].frames[{first + 1}]: frame {first + 1} is truncated" in proc.stderr
    assert not out.exists()
    # ...while a frame corrupt inside its pixel data (complete file, intact header) fails its tasks
    for k in range(len(data) // 2, len(data) // 2 + 16):
        data[k] ^= 0x5A
    bad.write_bytes(bytes(data))
    proc = subprocess.run([sys.executable, "-m", "schlieren.workers.cli", "run", str(sess), "--out",
                           str(out), "--serial", "--no-progress", "--log", str(tmp_path / "run.jsonl")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1, proc.stderr
    assert "cam01" in proc.stderr and f"frame {first + 1}" in proc.stderr
    assert "Traceback" not in proc.stderr
    # --log: the task that reads the frame (deflection) fails naming camera and frame; tasks
    # downstream of it are logged as not run
    lines = [json.loads(x) for x in (tmp_path / "run.jsonl").read_text().splitlines()]
    failed = [x for x in lines if x["message"] == "task failed"]
    roots = [x for x in failed if not x["error"].startswith("not run")]
    assert [x["stage"] for x in roots] == ["deflection"]
    assert all(f"camera cam01, frame {first + 1}:" in x["error"] for x in roots)
    assert {x["stage"] for x in failed} >= {"threshold", "integrate"}
    assert lines[-1]["message"] == "run finished" and lines[-1]["failed"] == 1
    g = zarr.open_group(str(out), mode="r")
    defl = np.asarray(g["status/deflection"][...])
    assert defl[0].all() and defl[2].all()  # other cameras complete and kept
    # in cam01 only the bad frame is missing: the rest of its task's frames were computed
    raw_bad = first + 1 - int(decode_attrs(g.attrs)["run"]["raw_first"])
    assert not defl[1, raw_bad] and defl[1].sum() == defl.shape[1] - 1
    assert not np.asarray(g["status/integrate"][...]).any()


def test_forced_ray_binning_runs_on_the_ray_grid_and_keeps_the_flow_grid(serial_store, tiny_session, tmp_path):
    """``tomography.ray_binning: 2``: the geometry is built on the ray grid (one ray per 2x2
    flow cells, its receipt says so), the flows, masks and hulls stay on the flow grid, and
    the reconstruction still meets the truth's floor of the default run. (This rig has 0.73
    cells per voxel edge, so the automatic choice keeps one ray per cell; forced, the block
    means halve the flow noise of its smooth blob: 42.7 dB against the default's 40.8.)"""
    import dataclasses

    from schlieren.pipeline.stages import RunConfig
    from schlieren.pipeline.tomography import load_geometry
    from schlieren.storage import arrays_cache
    from schlieren.workers.evaluate import evaluate

    base = RunConfig()
    cfg = dataclasses.replace(base, tomography=dataclasses.replace(base.tomography, ray_binning=2))
    out = tmp_path / "binned.zarr"
    summary = run_session(tiny_session.session, out, serial=True, config=cfg)
    assert summary.ok, summary.failures
    geo = [r for r in summary.receipts if r.get("stage") == "geometry"]
    assert len(geo) == 1 and geo[0]["ray_binning"] == 2
    g = zarr.open_group(str(out), mode="r")
    C, F, h, w, _ = g["flow"].shape
    assert geo[0]["ray_grid"] == [h // 2, w // 2]
    assert g["mask"].shape[-2:] == (h, w)
    geom = load_geometry(arrays_cache.load_arrays(arrays_cache.cache_dir(out, "geometry", geo[0]["key"])))
    assert geom.flow_shape == (C, h // 2, w // 2)
    assert evaluate(out, tiny_session.truth)["overall"]["psnr"] > 30.0


def test_deflection_tasks_in_frame_order_decode_each_frame_once(serial_store, tmp_path):
    """A deflection task compares its frame with the previous one (frozen frames); in frame
    order the previous frame is the one the task before decoded, and is not decoded again.
    The recomputed flows and frame statistics equal the stored ones."""
    from schlieren.pipeline import frame_quality as fq
    from schlieren.workers import tasks

    store = tmp_path / "again.zarr"
    shutil.copytree(serial_store, store)
    ctx = tasks.context(str(store), "decode-once")
    src = ctx.frames(0)
    reads: list[int] = []
    real = src.read

    def counted(f, *a, **k):
        reads.append(f)
        return real(f, *a, **k)

    src.read = counted
    g = zarr.open_group(str(serial_store), mode="r")
    n_raw = g["flow_raw"].shape[1]
    for j in range(n_raw):
        tasks.STAGE_TASKS["deflection"](ctx, 0, j)
    ctx.store.flush()
    first = ctx.raw_first
    assert sorted(reads) == sorted(set(reads)), reads
    # every processed frame and the one before it (an unused margin frame is not read; its
    # task reads the frame at the end of the range it lies outside, processed anyway)
    flags = np.nan_to_num(np.asarray(g["frame_quality"][0, :, 3])).astype(int)
    processed = [first + j for j in range(n_raw) if not flags[j] & fq.UNUSED]
    assert len(processed) < n_raw
    assert set(reads) == {h for f in processed for h in (f - 1, f) if h >= 0}, reads
    again = zarr.open_group(str(store), mode="r")
    np.testing.assert_array_equal(np.asarray(again["flow_raw"][0]), np.asarray(g["flow_raw"][0]))
    np.testing.assert_array_equal(np.asarray(again["frame_quality"][0]), np.asarray(g["frame_quality"][0]))


def test_the_serial_loop_reuses_the_session_the_run_loaded(tiny_session, tmp_path, monkeypatch):
    """The task contexts of a serial run take the session run_session validated (from a
    bucket each load is several requests) instead of loading the manifest again."""
    def refuse(*a, **k):
        raise AssertionError("the manifest was loaded again")

    from schlieren.workers import tasks
    from schlieren.workers.run import run_session
    from schlieren.workers.tasks import run_context

    tasks.context.cache_clear()
    monkeypatch.setattr(run_context, "load_session", refuse)
    summary = run_session(tiny_session.session, tmp_path / "once.zarr", serial=True)
    assert summary.ok, summary.root_failures()
