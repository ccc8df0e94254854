"""A failed multi-chunk zarr call leaves no chunk operation running (storage/inflight.py).

zarr gathers one task per chunk; when one chunk fails the call raises at once and the
other chunks' tasks go on running on zarr's event loop. Under load they outlived the
failed task and the process: at exit they failed on the closed thread pool ("cannot
schedule new futures after shutdown") and printed tracebacks into a clean run's stderr
(the chaos test of tests/e2e/test_lose_nothing.py).
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import zarr
from zarr.core import sync as zsync
from zarr.storage import LocalStore, WrapperStore

from schlieren.storage.inflight import settle

DAMAGED = textwrap.dedent('''
    import asyncio
    from zarr.storage import WrapperStore

    class Damaged(WrapperStore):
        """Chunk (3, 0) is damaged; every other chunk is slow to read (a loaded machine)."""
        async def get(self, key, prototype, byte_range=None):
            if key.endswith("c/3/0"):
                raise OSError("damaged chunk " + key)
            await asyncio.sleep(0.05)
            return await self._store.get(key, prototype, byte_range)
''')
exec(DAMAGED)


@pytest.fixture
def array_path(tmp_path):
    path = tmp_path / "a.zarr"
    a = zarr.create_array(LocalStore(path), shape=(40, 8), chunks=(1, 8), dtype="f4")
    a[:] = np.arange(320, dtype="f4").reshape(40, 8)
    return path


def _running() -> int:
    async def count():
        return sum(1 for t in asyncio.all_tasks() if t is not asyncio.current_task() and not t.done())
    return asyncio.run_coroutine_threadsafe(count(), zsync.loop[0]).result()


def test_a_failed_read_leaves_its_other_chunks_running_until_settled(array_path):
    a = zarr.open_array(Damaged(LocalStore(array_path)), mode="r")  # noqa: F821 - defined by exec above
    t0 = time.perf_counter()
    with pytest.raises(OSError, match="damaged chunk"):
        a[:]
    assert _running() > 0  # the cause: the call has raised, its siblings still read
    assert settle(timeout=30) is True
    assert _running() == 0
    assert time.perf_counter() - t0 < 30
    assert settle() is True  # nothing in flight: returns at once


def test_settle_without_zarr_loop_or_work_returns_at_once():
    t0 = time.perf_counter()
    assert settle() is True
    assert time.perf_counter() - t0 < 1.0


SCRIPT = DAMAGED + textwrap.dedent('''
    import sys, zarr
    from zarr.storage import LocalStore
    a = zarr.open_array(Damaged(LocalStore(sys.argv[1])), mode="r")
    try:
        a[:]
    except OSError:
        pass
    if sys.argv[2] == "settle":
        from schlieren.storage.inflight import settle
        settle()
''')


def test_a_process_ending_after_a_failed_read_prints_nothing_once_settled(array_path):
    """Without :func:`settle` the process ends with the siblings in flight: zarr's pool and
    loop are shut down under them (tracebacks, "Task was destroyed but it is pending")."""
    def run(mode):
        return subprocess.run([sys.executable, "-c", SCRIPT, str(array_path), mode], capture_output=True,
                              text=True, timeout=120)
    before = run("exit")
    assert "Task was destroyed but it is pending" in before.stderr or "Traceback" in before.stderr, before.stderr
    after = run("settle")
    assert after.returncode == 0 and after.stderr == "", after.stderr
