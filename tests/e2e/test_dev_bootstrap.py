"""dev.py, the README's bootstrap: a full disk is named, not retried four times."""

from __future__ import annotations

import importlib.util
from collections import namedtuple
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
Usage = namedtuple("Usage", "total used free")


@pytest.fixture()
def dev():
    spec = importlib.util.spec_from_file_location("schlieren_dev_bootstrap", ROOT / "dev.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_short_of_space_names_the_folder(dev, monkeypatch, tmp_path):
    gib = 2 ** 30
    monkeypatch.setattr(dev, "ROOT", tmp_path)
    monkeypatch.setattr(dev.shutil, "disk_usage", lambda p: Usage(100 * gib, 0, 50 * gib))
    assert dev._short_of_space() is None
    monkeypatch.setattr(dev.shutil, "disk_usage",
                        lambda p: Usage(100 * gib, 0, gib // 2 if Path(p) == tmp_path else 50 * gib))
    msg = dev._short_of_space()
    assert msg is not None and str(tmp_path) in msg and "0.5 GiB free" in msg


def test_pip_failure_on_a_full_disk_exits_at_once(dev, monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(dev.subprocess, "call", lambda cmd: calls.append(cmd) or 1)
    monkeypatch.setattr(dev.time, "sleep", lambda s: pytest.fail("retried on a full disk"))
    monkeypatch.setattr(dev, "_short_of_space", lambda: f"{tmp_path} has 0.1 GiB free")
    with pytest.raises(SystemExit, match="0.1 GiB free"):
        dev._pip(["python", "-m", "pip", "install", "x"])
    assert len(calls) == 1
    # with space, a failure is retried (the network), and the last one names the command
    calls.clear()
    monkeypatch.setattr(dev, "_short_of_space", lambda: None)
    monkeypatch.setattr(dev.time, "sleep", lambda s: None)
    with pytest.raises(SystemExit, match="failed 3 times"):
        dev._pip(["python", "-m", "pip", "install", "x"], attempts=3)
    assert len(calls) == 3
