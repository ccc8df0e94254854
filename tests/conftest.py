"""Shared fixtures: a tiny synthetic capture (rendered once per test session) and its serial reconstruction."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

TINY = dict(cameras=4, ring="half", phantom="blob", frames=3, size=(192, 144), seed=3,
            recon_voxel=0.005, supersample=2)


@pytest.fixture(scope="session")
def tiny_session(tmp_path_factory):
    from schlieren.workers.synth import synthesize

    out = tmp_path_factory.mktemp("tiny") / "session"
    res = synthesize(out, **TINY)
    return res


@pytest.fixture(scope="session")
def serial_store(tiny_session, tmp_path_factory):
    """The tiny session reconstructed by the serial reference executor."""
    from schlieren.workers.run import run_session

    out = tmp_path_factory.mktemp("serial") / "store.zarr"
    summary = run_session(tiny_session.session, out, serial=True)
    assert summary.ok, summary.failures
    return out


def pytest_configure(config):
    # tests/ holds shared helpers (store_compare.py) importable from every test folder
    import sys
    from pathlib import Path

    here = str(Path(__file__).parent)
    if here not in sys.path:
        sys.path.insert(0, here)
