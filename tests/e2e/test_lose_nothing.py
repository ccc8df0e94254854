"""Results you can't silently lose, end to end on the tiny session.

* readers (``evaluate``, ``export``, ``report``) refuse a damaged chunk with one line
  naming the array and the chunk, exit code 2;
* ``schlieren verify`` finds damage, ``--repair`` plus a rerun (or ``run --verify``)
  recomputes exactly the damaged tasks and everything downstream, and the store equals
  the undisturbed one bit for bit; a plain rerun notices lost chunks by listing;
* one writer per store (lease), and a store of the older version is refused for resume;
* a full disk ends with the failure summary, and the rerun completes the store;
* chaos: random SIGKILLs, byte flips, truncations, deleted chunks and markers and a
  damaged geometry cache, then ``run --verify`` gives the undisturbed store.
"""

from __future__ import annotations

import errno
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from schlieren.workers.run import run_session
from store_compare import assert_same_store

CLI = [sys.executable, "-m", "schlieren.workers.cli"]


def _cli(*args, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True, timeout=timeout)


def _one_line_error(proc, *needles):
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for n in needles:
        assert n in err, (n, err)


def _flip(f: Path, at: float = 0.5) -> None:
    b = bytearray(f.read_bytes())
    if not b:  # emptied by an earlier round of the chaos test: no byte to flip, still damaged
        return
    b[min(int(len(b) * at), len(b) - 1)] ^= 0x10
    f.write_bytes(bytes(b))


@pytest.fixture
def copy_of(serial_store, tmp_path):
    def make(name="s.zarr") -> Path:
        out = tmp_path / name
        shutil.copytree(serial_store, out)
        return out
    return make


def test_readers_refuse_a_corrupt_chunk_and_verify_repair_recomputes_it(copy_of, serial_store, tiny_session,
                                                                        tmp_path):
    out = copy_of()
    _flip(out / "refractivity" / "c" / "1" / "0" / "0" / "0")
    for cmd in (["evaluate", out, "--truth", tiny_session.truth],
                ["export", out, "--format", "raw", "--out", tmp_path / "exp"],
                ["report", out, "--out", tmp_path / "rep"]):
        _one_line_error(_cli(*cmd), f"file {out}", "field refractivity", "chunk (1, 0, 0, 0)", "checksum",
                        "verify")
    # a plain rerun lists files only: the flip is found by reading, not listing
    quick = run_session(tiny_session.session, out, serial=True)
    assert quick.ok and quick.tasks == 0 and quick.integrity.ok
    found = _cli("verify", out, "--json", tmp_path / "v.json")
    assert found.returncode == 1, found.stderr
    assert "refractivity chunk (1, 0, 0, 0): corrupt" in found.stdout and "task integrate (1,)" in found.stdout
    problems = json.loads((tmp_path / "v.json").read_text())["problems"]
    assert [(p["array"], p["kind"], p["stage"], p["index"]) for p in problems] == \
        [("refractivity", "corrupt", "integrate", [1])]
    fixed = _cli("verify", out, "--repair")
    assert fixed.returncode == 1 and "1 task(s) to recompute (integrate 1)" in fixed.stdout, fixed.stdout
    again = run_session(tiny_session.session, out, serial=True)
    assert again.ok and again.tasks == 1 and {r["stage"] for r in again.receipts} == {"integrate"}
    assert_same_store(serial_store, out)
    assert _cli("verify", out).returncode == 0
    assert not Path(f"{out}.lease").exists()


def test_a_rerun_notices_a_lost_chunk_and_recomputes_everything_downstream(copy_of, serial_store, tiny_session):
    out = copy_of()
    (out / "flow" / "c" / "2" / "0" / "0" / "0" / "0").unlink()
    summary = run_session(tiny_session.session, out, serial=True)
    assert summary.ok, summary.failures
    assert [(p.array, p.kind, p.stage, p.index) for p in summary.integrity.problems] == \
        [("flow", "missing", "resample", (2, 0))]
    redo = {(r["stage"], tuple(r["index"])) for r in summary.receipts}
    n_frames = zarr.open_array(out / "status" / "integrate").shape[0]
    # the lost flow's task, what reads it, and (through the sequence-wide threshold) the 3-D stages
    assert ("resample", (2, 0)) in redo and ("potential", (2, 0)) in redo and ("threshold", ()) in redo
    assert {("integrate", (k,)) for k in range(n_frames)} <= redo
    assert ("deflection", (2, 2)) not in redo and not any(s == "frames" for s, _ in redo)
    assert_same_store(serial_store, out)


def test_a_deleted_array_is_named_by_every_reader_and_recomputed_by_a_rerun(copy_of, serial_store, tiny_session,
                                                                            tmp_path):
    """`rm -rf STORE/temperature` while its markers are set: open and export stop with one
    line naming the array (never NaN with exit 0); verify sees it; a rerun recomputes it."""
    import schlieren
    from schlieren.storage.errors import StoreError

    out = copy_of()
    shutil.rmtree(out / "temperature")
    with pytest.raises(StoreError) as info:
        ds = schlieren.open(out)
        ds.temperature.values
    assert info.value.field == "temperature" and "\n" not in str(info.value), str(info.value)
    _one_line_error(_cli("export", out, "--format", "raw", "--quantity", "temperature", "--out", tmp_path / "exp"),
                    f"file {out}", "field temperature")
    assert not list((tmp_path / "exp").glob("*.raw")) if (tmp_path / "exp").exists() else True
    ds = schlieren.open(out)  # the other arrays read as before
    np.testing.assert_array_equal(ds.refractivity.values, zarr.open_group(str(serial_store))["refractivity"][...])
    assert _cli("verify", out).returncode == 1
    summary = run_session(tiny_session.session, out, serial=True)
    assert summary.ok and {r["stage"] for r in summary.receipts} == {"integrate"}, summary.receipts
    assert_same_store(serial_store, out)


def _damage_metadata(out: Path) -> None:
    """A truncated array zarr.json, a flipped byte in another, a marker's deleted."""
    meta = out / "flow" / "zarr.json"
    meta.write_bytes(meta.read_bytes()[: len(meta.read_bytes()) // 2])
    _flip(out / "refractivity" / "zarr.json", at=0.3)
    (out / "status" / "tomography" / "zarr.json").unlink()


def _files(root: Path) -> dict[str, bytes]:
    return {str(f.relative_to(root)): f.read_bytes() for f in sorted(root.rglob("*")) if f.is_file()}


def test_corrupt_array_metadata_is_rewritten_from_the_consolidated_copy(copy_of, serial_store, tiny_session):
    out = copy_of()
    _damage_metadata(out)
    found = _cli("verify", out)
    assert found.returncode == 1, found.stderr
    for line in ("flow: corrupt-metadata: its zarr.json does not parse",
                 "refractivity: corrupt-metadata: its zarr.json",
                 "status/tomography: corrupt-metadata: its zarr.json is missing"):
        assert line in found.stdout, found.stdout
    fixed = _cli("verify", out, "--repair")
    assert fixed.returncode == 1 and "3 metadata file(s) rewritten" in fixed.stdout, fixed.stdout
    assert _files(out) == _files(serial_store)  # every file, bit for bit: nothing to recompute
    assert _cli("verify", out).returncode == 0
    # a plain rerun repairs it too (zarr would re-read it to consolidate: a raw JSON traceback before)
    again = copy_of("again.zarr")
    _damage_metadata(again)
    summary = run_session(tiny_session.session, again, serial=True)
    assert summary.ok and summary.tasks == 0, summary.failures
    assert_same_store(serial_store, again)
    assert _cli("verify", again).returncode == 0


def test_run_refuses_a_store_of_the_older_version_and_a_store_held_by_another_run(copy_of, tiny_session):
    from schlieren.storage.lease import StoreLease

    out = copy_of()
    g = zarr.open_group(out, mode="r+")
    attrs = dict(g.attrs)
    attrs.pop("integrity")
    g.attrs.clear()
    g.attrs.update(attrs)
    _one_line_error(_cli("run", tiny_session.session, "--out", out, "--serial", "--no-progress"),
                    f"file {out}", "older schlieren without chunk checksums", "new --out")
    # readers still open it
    assert _cli("export", out, "--format", "raw", "--out", out.parent / "exp").returncode == 0
    fresh = out.parent / "held.zarr"
    with StoreLease(fresh):  # a live run (this process) holds it
        _one_line_error(_cli("run", tiny_session.session, "--out", fresh, "--serial", "--no-progress"),
                        f"file {fresh}", "another run is writing this store", f"pid {os.getpid()}")
        assert not fresh.exists()  # refused before the store was created


# ---------------------------------------------------------------------------------------
# a full disk
# ---------------------------------------------------------------------------------------
_ENOSPC_SHIM = r"""
import errno, sys
from schlieren.storage import chunkio, arrays_cache
left = [int(sys.argv[1])]
real_write = chunkio.ChunkLayout.write
def write(self, coords, data):
    left[0] -= 1
    if left[0] < 0:
        raise OSError(errno.ENOSPC, "No space left on device", self.path(coords))
    return real_write(self, coords, data)
chunkio.ChunkLayout.write = write
def save_arrays(path, arrays):
    raise OSError(errno.ENOSPC, "No space left on device", str(path))
arrays_cache.save_arrays = save_arrays
from schlieren.workers.cli import main
sys.exit(main(sys.argv[2:]))
"""


def _fill_the_disk(session, out: Path, tmp_path: Path) -> tuple[subprocess.CompletedProcess, str]:
    """Run into a full disk: a real tmpfs in a private mount namespace where the platform
    allows it (root, or unprivileged user namespaces), filled by another file once the run
    is under way (the preflight refuses a disk that is too small from the start: checked
    first, with a 1 MiB tmpfs); else a writer that raises ENOSPC after 40 chunks
    (monkeypatched in the subprocess)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    unshare = shutil.which("unshare")
    if unshare and sys.platform.startswith("linux"):
        user = [] if os.geteuid() == 0 else ["--user", "--map-root-user"]
        run = f"{' '.join(CLI)} run {session} --out {mnt}/store.zarr --serial --no-progress"
        script = f"""
            mount -t tmpfs -o size=1m tmpfs {mnt} || exit 97
            {run} 2> {tmp_path}/tiny.err; echo $? > {tmp_path}/tiny.rc
            umount {mnt}; mount -t tmpfs -o size=64m tmpfs {mnt} || exit 97
            {run} & pid=$!
            while [ ! -d {mnt}/store.zarr/status/deflection/c ] && kill -0 $pid 2>/dev/null; do sleep 0.02; done
            dd if=/dev/zero of={mnt}/filler bs=64k 2>/dev/null
            wait $pid; rc=$?
            rm -f {mnt}/filler; cp -a {mnt}/store.zarr {out}; exit $rc
        """
        proc = subprocess.run([unshare, *user, "--mount", "sh", "-c", script], capture_output=True, text=True,
                              timeout=600)
        if proc.returncode != 97 and "unshare" not in proc.stderr.split(":")[0]:
            tiny = (tmp_path / "tiny.err").read_text()
            assert (tmp_path / "tiny.rc").read_text().strip() == "2", tiny
            assert "free" in tiny and "Traceback" not in tiny and len(tiny.strip().splitlines()) == 1, tiny
            return proc, "tmpfs"
        shutil.rmtree(out, ignore_errors=True)
    proc = subprocess.run([sys.executable, "-c", _ENOSPC_SHIM, "40", "run", str(session), "--out", str(out),
                           "--serial", "--no-progress"], capture_output=True, text=True, timeout=600)
    return proc, "simulated"


def test_a_full_disk_ends_with_the_failure_summary_and_the_rerun_completes(serial_store, tiny_session, tmp_path):
    out = tmp_path / "full.zarr"
    proc, how = _fill_the_disk(tiny_session.session, out, tmp_path)
    print(f"full disk: {how}")
    assert proc.returncode == 1, (how, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    assert "FAILED:" in proc.stderr and "No space left on device" in proc.stderr
    assert "the disk is full: free space and rerun; completed chunks are kept" in proc.stderr
    summary = run_session(tiny_session.session, out, serial=True)
    assert summary.ok and summary.skipped > 0, summary.failures
    assert_same_store(serial_store, out)


# ---------------------------------------------------------------------------------------
# chaos
# ---------------------------------------------------------------------------------------
def _chunk_files(store: Path) -> list[Path]:
    return sorted(p for p in store.rglob("*") if p.is_file() and p.name != "zarr.json"
                  and (p.name.isdigit() or p.name == "c"))


def _damage(store: Path, rng: random.Random, log: list[str]) -> None:
    files = _chunk_files(store)
    if not files:
        return
    for f in rng.sample(files, min(len(files), rng.randint(1, 4))):
        how = rng.choice(["flip", "truncate", "delete", "empty"])
        rel = f.relative_to(store)
        if how == "flip":
            _flip(f, rng.random())
        elif how == "truncate":
            f.write_bytes(f.read_bytes()[: rng.randrange(len(f.read_bytes()))])
        elif how == "empty":
            f.write_bytes(b"")
        else:
            f.unlink()
        log.append(f"{how} {rel}")
    markers = [p for p in files if p.parts[len(store.parts)] == "status" and p.exists()]
    if markers and rng.random() < 0.7:
        m = rng.choice(markers)
        m.unlink()
        log.append(f"delete marker {m.relative_to(store)}")
    cache = Path(f"{store}.cache")
    geo = sorted(cache.rglob("*.npy")) if cache.exists() else []
    if geo and rng.random() < 0.3:
        _flip(geo[0], rng.random())
        log.append(f"flip {geo[0].relative_to(cache)}")


def _markers(store: Path) -> int:
    return sum(1 for p in (store / "status").rglob("*") if p.is_file()) if (store / "status").exists() else 0


def test_chaos_kills_and_damage_end_in_the_undisturbed_store(serial_store, tiny_session, tmp_path):
    rng = random.Random(int(os.environ.get("SCHLIEREN_CHAOS_SEED", "1606")))  # other seeds: stress runs
    out = tmp_path / "chaos.zarr"
    log: list[str] = []
    cmd = CLI + ["run", str(tiny_session.session), "--out", str(out), "--serial", "--no-progress"]
    round_ = 0
    # rounds until the run was killed at least three times and chunks or markers deleted twice
    # (a run may also end by itself, failing on a damaged upstream chunk or completing)
    while round_ < 30 and (sum("SIGKILL" in x for x in log) < 3 or sum("delete" in x for x in log) < 2
                           or round_ < 6):
        round_ += 1
        # kill once the run has made some random progress (machine load does not matter); after
        # a run that ended by itself (little work left) sooner
        ended = any(x.startswith(f"round {round_ - 1}: exit") for x in log)
        start, more = _markers(out), rng.randint(1, 4 if ended else 25)
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.time() + 300
            while proc.poll() is None and time.time() < deadline and _markers(out) < start + more:
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 0.3))
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                log.append(f"round {round_}: SIGKILL")
            else:
                log.append(f"round {round_}: exit {proc.returncode}")
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert "Traceback" not in err, (log, err)
        if out.exists():
            _damage(out, rng, log)
    final = _cli("run", tiny_session.session, "--out", out, "--serial", "--no-progress", "--verify")
    assert final.returncode == 0, (log, final.stderr)
    assert_same_store(serial_store, out)
    assert _cli("verify", out).returncode == 0, log
    assert not Path(f"{out}.lease").exists()
    assert not list(out.rglob("*.partial"))
    assert sum("SIGKILL" in x for x in log) >= 3 and sum("delete" in x for x in log) >= 2, log
    print("\n".join(log))  # the damage done, shown with -s
