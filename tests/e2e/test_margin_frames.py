"""Raw frames of the rolling-shutter margins that no output instant reads are not processed
(`workers/tasks/deflection.py:raw_frame_needed`): the result is bit for bit the run that processes
them all, and a flagged frame at the end of a range makes its outer neighbour needed."""

from __future__ import annotations

import logging
import shutil
import warnings

import cv2
import numpy as np
import yaml

from schlieren.pipeline import frame_quality as fq
from schlieren.storage.store import ResultStore
from schlieren.workers.tasks import deflection
from schlieren.workers.run import run_session


def _read(store: ResultStore, name: str) -> np.ndarray:
    return np.asarray(store.array(name)[...])


def _used(summary) -> dict[int, set[int]]:
    """Capture frames each camera's resample tasks read (their receipts' ``raw_frames``)."""
    out: dict[int, set[int]] = {}
    for r in summary.receipts:
        if r.get("stage") == "resample":
            lo, hi = r["raw_frames"]
            out.setdefault(int(r["index"][0]), set()).update(range(lo, hi + 1))
    return out


def _unused(store: ResultStore) -> dict[int, set[int]]:
    flags = np.nan_to_num(_read(store, "frame_quality")[..., 3]).astype(int)
    first = int(store.attrs["run"]["raw_first"])
    return {c: {first + int(j) for j in np.flatnonzero(flags[c] & fq.UNUSED)} for c in range(flags.shape[0])}


def test_unused_margin_frames_are_skipped_without_changing_the_result(tiny_session, tmp_path, monkeypatch):
    sess = tiny_session.session
    skipped = run_session(sess, tmp_path / "skip.zarr", serial=True)
    assert skipped.ok and skipped.bad_frames == []  # unused frames are not "excluded" frames
    with monkeypatch.context() as m:
        m.setattr(deflection, "raw_frame_needed", lambda *a: True)
        every = run_session(sess, tmp_path / "all.zarr", serial=True)
    assert every.ok
    a, b = ResultStore.open(tmp_path / "skip.zarr"), ResultStore.open(tmp_path / "all.zarr")
    unused = _unused(a)
    assert sum(map(len, unused.values())) > 0, "the tiny session's margins should hold unused frames"
    assert _unused(b) == {c: set() for c in unused}
    # exactly the raw frames no resample task read were left out
    used = _used(every)
    first, n_raw = int(a.attrs["run"]["raw_first"]), int(a.attrs["run"]["n_raw"])
    for c in unused:
        assert unused[c] == set(range(first, first + n_raw)) - used[c], c
    assert sum(1 for r in skipped.receipts if r.get("unused")) == sum(map(len, unused.values()))
    for name in ("flow", "mask", "hull", "gradient", "refractivity"):
        np.testing.assert_array_equal(_read(a, name), _read(b, name), err_msg=name)


def test_a_dark_frame_at_a_ranges_end_makes_the_margin_frame_needed(tiny_session, tmp_path, caplog):
    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess)
    clean = run_session(sess, tmp_path / "clean.zarr", serial=True)
    store = ResultStore.open(tmp_path / "clean.zarr")
    unused = _unused(store)
    used = _used(clean)
    c = next(c for c in sorted(unused) if unused[c] and min(unused[c]) < min(used[c]))
    below = max(f for f in unused[c] if f < min(used[c]))  # the unused frame just below the first read
    end = min(used[c])
    assert end == below + 1
    name = yaml.safe_load((sess / "session.yaml").read_text())["cameras"][c]["name"]
    cv2.imwrite(str(sess / name / "frames" / f"{end:05d}.png"), np.zeros((144, 192), np.uint8))  # lens cap
    with warnings.catch_warnings(), caplog.at_level(logging.WARNING):
        warnings.simplefilter("error", RuntimeWarning)  # its zero gain is not divided by
        dark = run_session(sess, tmp_path / "dark.zarr", serial=True)
    assert dark.ok
    assert f"camera {name}, frame {end}: its gain against the reference cannot be estimated" in caplog.text
    assert (store.attrs["session"]["cameras"][c]["name"], end, ["dark"]) in dark.bad_frames
    assert below not in _unused(ResultStore.open(tmp_path / "dark.zarr"))[c]
    assert below in _used(dark)[c]  # the resampling reached past the dark frame to it

