"""Retention (issue 36, build item 5): the user chooses which intermediates a store keeps.

``--keep all`` (default) keeps everything; ``--keep results`` drops ``flow_raw``, ``flow``
and ``potential`` once every task reading them is done; ``--keep flow`` keeps ``flow`` and
drops the other two. Whatever is kept, resume after a kill, ``verify`` and a rerun that
needs a dropped intermediate (damage downstream, or a wider ``--keep``) end with the
kept arrays bit-identical to an undisturbed run's.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
import zarr

from schlieren.workers.run import run_session
from store_compare import read_all, sigkill_when

DROPPABLE = ("flow_raw", "flow", "potential")
POLICIES = {"all": (), "results": DROPPABLE, "flow": ("flow_raw", "potential")}


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "schlieren.workers.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


def assert_kept_like(full, store, dropped) -> None:
    """``store`` holds exactly ``full``'s arrays but ``dropped``, bit for bit."""
    A, B = read_all(full), read_all(store)
    assert sorted(B) == sorted(k for k in A if k not in dropped), (sorted(A), sorted(B))
    for k, b in B.items():
        assert np.array_equal(A[k], b, equal_nan=A[k].dtype.kind == "f"), k


def _markers_set(store) -> int:
    try:
        g = zarr.open_group(str(store), mode="r")
        return int(sum(np.asarray(m[...]).sum() for _, m in g["status"].arrays()))
    except Exception:  # noqa: BLE001 - not created yet
        return 0


def test_keep_parses_a_policy_or_a_list_of_intermediates():
    from schlieren.workers.retention import DROPPABLE as names, arrays_to_drop

    assert set(names) == set(DROPPABLE)
    assert arrays_to_drop("all") == frozenset() and arrays_to_drop(None) == frozenset()
    assert arrays_to_drop("results") == frozenset(DROPPABLE)
    assert arrays_to_drop("flow") == frozenset({"flow_raw", "potential"})
    assert arrays_to_drop("flow,potential") == frozenset({"flow_raw"})
    assert arrays_to_drop(["flow_raw", "flow", "potential"]) == frozenset()
    with pytest.raises(ValueError, match="flow_raw, flow, potential"):
        arrays_to_drop("volumes,flows")


@pytest.mark.parametrize("keep", ["results", "flow"])
def test_a_run_keeps_what_it_is_told_and_the_rest_is_bit_identical(keep, serial_store, tiny_session, tmp_path):
    import schlieren

    out = tmp_path / "s.zarr"
    summary = run_session(tiny_session.session, out, serial=True, keep=keep)
    assert summary.ok, summary.failures
    assert_kept_like(serial_store, out, POLICIES[keep])
    ds = schlieren.open(out)
    assert "refractivity" in ds and not any(k in ds for k in POLICIES[keep])
    assert _cli("verify", out).returncode == 0
    again = run_session(tiny_session.session, out, serial=True, keep=keep)
    assert again.ok and again.steps_computed == 0
    assert_kept_like(serial_store, out, POLICIES[keep])
    if keep == "results":  # the report says why its deflection figures are missing
        assert _cli("report", out, "--out", tmp_path / "rep").returncode == 0
        assert "<code>flow</code> was not kept" in (tmp_path / "rep" / "index.html").read_text()


@pytest.mark.parametrize("keep", list(POLICIES))
def test_a_killed_run_resumes_and_verifies_with_each_policy(keep, serial_store, tiny_session, tmp_path):
    out = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "schlieren.workers.cli", "run", str(tiny_session.session), "--out", str(out),
           "--serial", "--no-progress", "--keep", keep]
    sigkill_when(cmd, lambda: _markers_set(out), 60)
    assert _cli("verify", out).returncode == 0  # chunks dropped under set markers are not "missing"
    p = _cli("run", tiny_session.session, "--out", out, "--serial", "--no-progress", "--keep", keep)
    assert p.returncode == 0, p.stderr
    assert_kept_like(serial_store, out, POLICIES[keep])
    v = _cli("verify", out)
    assert v.returncode == 0, v.stdout


def test_damage_downstream_recomputes_the_dropped_inputs_it_needs(serial_store, tiny_session, tmp_path):
    out = tmp_path / "s.zarr"
    assert run_session(tiny_session.session, out, serial=True, keep="results").ok
    chunk = out / "gradient" / "c" / "1" / "0" / "0" / "0" / "0"
    b = bytearray(chunk.read_bytes())
    b[len(b) // 2] ^= 0x10
    chunk.write_bytes(bytes(b))
    found = _cli("verify", out)
    assert found.returncode == 1 and "gradient chunk (1, 0, 0, 0, 0): corrupt" in found.stdout, found.stdout
    summary = run_session(tiny_session.session, out, serial=True, keep="results", verify=True)
    assert summary.ok, summary.failures
    redo = {(r["stage"], tuple(r["index"])) for r in summary.receipts}
    # frame 1's solve (and what follows it) needs its flows again: resampled from raw flows
    assert ("tomography", (1,)) in redo and ("resample", (0, 1)) in redo and ("deflection", (0, 3)) in redo
    assert ("potential", (0, 1)) not in redo and ("mask", (0, 1)) not in redo  # still valid: not recomputed
    assert_kept_like(serial_store, out, DROPPABLE)
    assert _cli("verify", out).returncode == 0


def test_a_wider_keep_brings_the_dropped_intermediates_back(serial_store, tiny_session, tmp_path):
    out = tmp_path / "s.zarr"
    assert run_session(tiny_session.session, out, serial=True, keep="results").ok
    p = _cli("run", tiny_session.session, "--out", out, "--serial", "--no-progress", "--keep", "flow")
    assert p.returncode == 0, p.stderr
    assert_kept_like(serial_store, out, POLICIES["flow"])
    assert run_session(tiny_session.session, out, serial=True).ok  # keep all
    assert_kept_like(serial_store, out, ())


def test_readers_say_an_intermediate_was_not_kept(tiny_session, tmp_path):
    """Mid-run (a killed run) a dropped chunk is reported as not kept, never as lost."""
    from schlieren.storage.errors import ChunkError
    from schlieren.storage.store import ResultStore

    out = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "schlieren.workers.cli", "run", str(tiny_session.session), "--out", str(out),
           "--serial", "--no-progress", "--keep", "results"]
    sigkill_when(cmd, lambda: int(np.asarray(zarr.open_group(str(out), mode="r")["status/tomography"][...]).sum())
                 if _markers_set(out) else 0, 1)
    st = ResultStore.open(out, mode="r")
    with pytest.raises(ChunkError, match="not kept") as info:
        st.read("flow", (0, 0))
    assert info.value.array == "flow" and "--keep" in str(info.value)


@pytest.mark.system
def test_retention_on_a_local_cluster(serial_store, tiny_session, tmp_path):
    p = _cli("run", tiny_session.session, "--out", tmp_path / "d.zarr", "--workers", "2", "--no-progress",
             "--keep", "results")
    assert p.returncode == 0, p.stderr
    assert_kept_like(serial_store, tmp_path / "d.zarr", DROPPABLE)
