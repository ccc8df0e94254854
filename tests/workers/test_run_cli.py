"""`schlieren run` on bad input: one line, non-zero exit, no traceback, nothing touched."""

from __future__ import annotations

import pytest

import shutil
import subprocess
import sys

import yaml
import zarr


def _cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "schlieren.workers.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def _copy_session(tiny_session, tmp_path):
    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess, ignore=shutil.ignore_patterns("truth.zarr"))
    return sess


@pytest.mark.system  # passes --workers N: the fast tier's guard cannot tell a refusal from a start
def test_malformed_manifest_is_refused_before_any_work(tiny_session, tmp_path):
    sess = _copy_session(tiny_session, tmp_path)
    m = yaml.safe_load((sess / "session.yaml").read_text())
    m["cameras"][2]["R"][0][0] = 0.5  # no longer a rotation
    (sess / "session.yaml").write_text(yaml.safe_dump(m))
    out = tmp_path / "out.zarr"
    p = _cli("run", sess, "--out", out, "--workers", "2")  # refused before a cluster starts
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    assert "session.yaml" in lines[0] and m["cameras"][2]["name"] in lines[0] and "R" in lines[0]
    assert "Traceback" not in p.stderr
    assert not out.exists()  # nothing was created


def test_a_misspelled_field_names_the_field(tiny_session, tmp_path):
    sess = _copy_session(tiny_session, tmp_path)
    text = (sess / "session.yaml").read_text().replace("frame_rate:", "frame_rte:")
    (sess / "session.yaml").write_text(text)
    p = _cli("run", sess, "--out", tmp_path / "o.zarr", "--serial")
    assert p.returncode == 2 and "frame_rte" in p.stderr and "frame_rate" in p.stderr
    assert "Traceback" not in p.stderr


def test_an_existing_store_of_another_run_is_never_overwritten(tiny_session, serial_store, tmp_path):
    sess = _copy_session(tiny_session, tmp_path)
    m = yaml.safe_load((sess / "session.yaml").read_text())
    m["name"] = "another run"
    (sess / "session.yaml").write_text(yaml.safe_dump(m))
    out = tmp_path / "existing.zarr"
    shutil.copytree(serial_store, out)
    before = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    r_before = zarr.open_group(str(out), mode="r")["refractivity"][...]
    p = _cli("run", sess, "--out", out, "--serial")
    assert p.returncode == 2 and str(out) in p.stderr and "Traceback" not in p.stderr
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == before
    assert (zarr.open_group(str(out), mode="r")["refractivity"][...] == r_before).all()


def test_bad_frame_range_argument(tiny_session, tmp_path):
    p = _cli("run", tiny_session.session, "--out", tmp_path / "o.zarr", "--frames", "5:2")
    assert p.returncode == 2 and "--frames" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.system  # passes --workers N: the fast tier's guard cannot tell a refusal from a start
def test_an_unwritable_log_path_is_refused_before_any_work(tiny_session, tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    out = tmp_path / "o.zarr"
    p = _cli("run", tiny_session.session, "--out", out, "--workers", "2", "--log", blocker / "run.jsonl")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert f"--log {blocker / 'run.jsonl'}: cannot write it" in p.stderr
    assert "dashboard:" not in p.stderr and not out.exists()  # no cluster, no store


@pytest.mark.system  # passes --workers N: the fast tier's guard cannot tell a refusal from a start
def test_bad_worker_counts_and_demo_sizes_are_refused(tiny_session, tmp_path):
    for n in ("0", "-3"):
        p = _cli("run", tiny_session.session, "--out", tmp_path / "o.zarr", "--workers", n)
        assert p.returncode == 2 and "--workers" in p.stderr and "must be at least 1" in p.stderr
    assert not (tmp_path / "o.zarr").exists()
    for flag, value in (("--cameras", "1"), ("--frames", "0"), ("--workers", "0")):
        p = _cli("demo", "--out", tmp_path / "d", flag, value)
        assert p.returncode == 2 and flag in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert not (tmp_path / "d").exists()


def test_demo_refuses_to_reuse_a_session_of_another_size(tiny_session, tmp_path):
    # a session already in --out (4 cameras x 3 frames at 192x144) is reused only if it
    # is what the flags ask for
    shutil.copytree(tiny_session.session.parent, tmp_path / "d" / "session",
                    ignore=shutil.ignore_patterns("truth.zarr"))
    p = _cli("demo", "--out", tmp_path / "d")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "holds a demo session of 4 cameras x 3 frames at 192x144, not the 8 x 4 at 480x360" in p.stderr
    assert not (tmp_path / "d" / "result.zarr").exists()


def test_demo_runs_every_stage_and_writes_its_report(tmp_path):
    """`schlieren demo` (the README's main command) end to end on a tiny rig."""
    out = tmp_path / "demo"
    proc = _cli("demo", "--out", str(out), "--workers", "1", "--cameras", "4", "--frames", "3",
                "--size", "96x72", "--no-progress", timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    stores = [p for p in out.iterdir() if p.suffix == ".zarr"]
    assert stores, list(out.iterdir())
    g = zarr.open_group(str(stores[0]), mode="r")
    assert bool(g["status/integrate"][...].all())
    assert "demo: PSNR" in proc.stdout
    assert (out / "report").is_dir() and any((out / "report").iterdir())
