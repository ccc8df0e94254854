"""Store comparison helpers for the end-to-end tests, and a store copy with its geometry cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import zarr


def copy_store(store: Path, dest: Path) -> Path:
    """A copy of ``store`` in folder ``dest`` with its geometry cache (``<store>.cache``)."""
    out = dest / store.name
    shutil.copytree(store, out)
    cache = store.parent / (store.name + ".cache")
    if cache.exists():
        shutil.copytree(cache, dest / cache.name)
    return out


def read_all(store_path) -> dict[str, np.ndarray]:
    """Every array of a store (markers included) as numpy arrays."""
    g = zarr.open_group(str(store_path), mode="r")
    out = {}

    def walk(grp, prefix=""):
        for name, arr in grp.arrays():
            out[prefix + name] = np.asarray(arr[...])
        for name, sub in grp.groups():
            walk(sub, prefix + name + "/")

    walk(g)
    return out


def assert_same_store(a, b) -> None:
    A, B = read_all(a), read_all(b)
    assert sorted(A) == sorted(B)
    for k in A:
        x, y = A[k], B[k]
        assert x.shape == y.shape, k
        if x.dtype.kind == "f":
            assert np.array_equal(x, y, equal_nan=True), f"{k} differs (max {np.nanmax(np.abs(x - y))})"
        else:
            assert np.array_equal(x, y), f"{k} differs"


def sigkill_when(cmd: list[str], progress, at_least: int, timeout: float = 240) -> int:
    """Start ``cmd``, SIGKILL it once ``progress()`` reaches ``at_least``; return ``progress()`` then.

    Fails if the command finishes (or ``timeout`` passes) first.
    """
    import os
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + timeout
    try:
        while progress() < at_least and proc.poll() is None and time.time() < deadline:
            time.sleep(0.2)
        assert proc.poll() is None, "the run finished before it could be killed: " + proc.stderr.read().decode()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    done = progress()
    assert done >= at_least
    return done
