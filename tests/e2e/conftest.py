"""A tiny synthetic capture shared by the end-to-end tests (rendered once per session)."""

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
