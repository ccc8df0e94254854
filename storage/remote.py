"""Whole-chunk traffic of a result store on object storage: a chunk cache and writes in the background.

In a folder store a task's chunk read or write is a local file access
(storage/chunkio.py). In an object store each is a request, far slower even against a
server on the same machine (docs/tuning.md, "Chunk I/O and object storage"), and a task
makes several.
:class:`RemoteChunks` hides most of them, without changing what is stored (zarr still
encodes and sends every chunk, the same bytes as in a folder store):

* **written chunks are kept** (LRU, :attr:`RemoteChunks.max_bytes`): a later read of a
  chunk this process wrote is answered from memory. In a run a chunk is final once its
  task has written it (tasks are idempotent), so the copy equals what the store holds;
* **writes go out in the background** when the store is opened with ``write_behind``
  (the tasks' per-process store): :meth:`RemoteChunks.put` returns at once, several
  requests travel together while the task computes its next frame, and
  :meth:`RemoteChunks.barrier` waits for all of them. The store calls the barrier before
  sending a completion marker (a marker never arrives before the data it vouches for) and
  the task glue calls it before a task returns (its dependents, perhaps on other
  machines, read the store). A process killed meanwhile loses writes whose markers were
  not sent either: the rerun computes those again.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Hashable

import numpy as np

__all__ = ["RemoteChunks"]


class RemoteChunks:
    """Chunk cache and background writes for one opened object store (see the module doc)."""

    #: Bytes of written chunks kept per opened store.
    max_bytes = 64 * 2 ** 20
    #: Requests in flight at once.
    max_in_flight = 8

    def __init__(self, *, write_behind: bool):
        self.write_behind = write_behind
        self._lock = threading.Lock()
        self._cache: OrderedDict[Hashable, np.ndarray] = OrderedDict()
        self._cache_bytes = 0
        self._pending: dict[Hashable, Future] = {}
        self._pool: ThreadPoolExecutor | None = None
        self._readers: ThreadPoolExecutor | None = None

    # -- cache ----------------------------------------------------------------------
    def get(self, key: Hashable) -> np.ndarray | None:
        """A copy of the chunk written under ``key`` by this process, or None."""
        with self._lock:
            a = self._cache.get(key)
            if a is not None:
                self._cache.move_to_end(key)
                return a.copy()
            fut = self._pending.get(key)
        if fut is not None:  # evicted while its write is in flight: let it land first
            fut.result()
        return None

    def forget(self, which: Callable[[Hashable], bool]) -> None:
        """Drop the cached chunks whose key satisfies ``which``."""
        with self._lock:
            for key in [k for k in self._cache if which(k)]:
                self._cache_bytes -= self._cache.pop(key).nbytes

    def _remember(self, key: Hashable, a: np.ndarray) -> None:
        a = np.array(a, copy=True)
        a.flags.writeable = False
        with self._lock:
            old = self._cache.pop(key, None)
            if old is not None:
                self._cache_bytes -= old.nbytes
            if a.nbytes > self.max_bytes:
                return
            self._cache[key] = a
            self._cache_bytes += a.nbytes
            while self._cache_bytes > self.max_bytes:
                _, gone = self._cache.popitem(last=False)
                self._cache_bytes -= gone.nbytes

    # -- writes ---------------------------------------------------------------------
    def put(self, key: Hashable | None, data: np.ndarray | None, send: Callable[[], None],
            describe: str, *, after_pending: bool = False) -> None:
        """Send one chunk (``send()`` stores it); keep ``data`` under ``key`` for later reads.

        With ``write_behind`` the request goes out in the background and a failure is
        raised by the next :meth:`barrier`, as an ``OSError`` naming ``describe``.
        ``after_pending``: send only once every write sent before is stored, and not at
        all if one of them failed (a completion marker after its data).
        """
        if key is not None and data is not None:
            self._remember(key, data)
        if not self.write_behind:
            if after_pending:
                self.barrier()
            send()
            return
        job = _named(send, describe)
        if after_pending:
            with self._lock:
                before = list(self._pending.values())
            job = _after(before, job)
        # a job waits only for jobs submitted before it, which the FIFO pool has started
        # by then: no deadlock with a bounded pool
        fut = self._executor().submit(job)
        with self._lock:
            self._pending[key if key is not None else object()] = fut

    def barrier(self) -> None:
        """Wait until every write sent so far is stored; raise the first failure."""
        with self._lock:
            pending = list(self._pending.items())
        first: BaseException | None = None
        for key, fut in pending:
            try:
                fut.result()
            except BaseException as exc:  # noqa: BLE001 - re-raised below, after every wait
                if first is None:
                    first = exc
                self.forget(lambda k: k == key)
        with self._lock:
            for key, fut in pending:
                if self._pending.get(key) is fut:
                    del self._pending[key]
        if first is not None:
            raise first

    def read_all(self, read: Callable[[Hashable], np.ndarray], keys: list) -> list[np.ndarray]:
        """``[read(k) for k in keys]`` with the reads in flight together (their own threads,
        so a read never waits behind the writes it may need)."""
        with self._lock:
            if self._readers is None:
                self._readers = ThreadPoolExecutor(self.max_in_flight, thread_name_prefix="schlieren-get")
            pool = self._readers
        return list(pool.map(read, keys))

    def _executor(self) -> ThreadPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.max_in_flight, thread_name_prefix="schlieren-put")
            return self._pool


def _after(before: list[Future], job: Callable[[], None]) -> Callable[[], None]:
    def run() -> None:
        for fut in before:
            if fut.exception() is not None:
                return  # the barrier reports that failure; this write is not sent
        job()
    return run


def _named(send: Callable[[], None], describe: str) -> Callable[[], None]:
    def run() -> None:
        try:
            send()
        except Exception as exc:
            raise OSError(f"writing {describe} to the object store failed: {type(exc).__name__}: {exc}") from exc
    return run
