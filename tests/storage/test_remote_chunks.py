"""storage/remote.py: the written-chunk cache and background writes of object stores.

The guarantees the tasks rely on, with stand-in ``send`` functions: a marker (sent with
``after_pending``) goes out only after every earlier write is stored and never after a
failed one; ``barrier`` waits for everything and raises the first failure naming the
chunk; a chunk read back is the data written, even while its write is in flight.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from schlieren.storage.remote import RemoteChunks


def test_background_writes_return_at_once_and_the_barrier_waits():
    rc = RemoteChunks(write_behind=True)
    gate = threading.Event()
    stored = []

    def slow_send():
        gate.wait(10)
        stored.append("flow")

    t0 = time.perf_counter()
    rc.put(("flow", (0, 0)), np.ones((2, 2), np.float32), slow_send, "flow at (0, 0)")
    assert time.perf_counter() - t0 < 1.0 and stored == []
    # read back while the write is in flight: the data written, as a copy
    a = rc.get(("flow", (0, 0)))
    np.testing.assert_array_equal(a, np.ones((2, 2)))
    a[...] = 5
    np.testing.assert_array_equal(rc.get(("flow", (0, 0))), np.ones((2, 2)))
    threading.Timer(0.2, gate.set).start()
    rc.barrier()
    assert stored == ["flow"]


def test_a_marker_waits_for_the_data_it_vouches_for():
    rc = RemoteChunks(write_behind=True)
    order = []
    gate = threading.Event()

    def data():
        gate.wait(10)
        order.append("data")

    rc.put(("gradient", (0,)), np.zeros(3), data, "gradient at 0")
    rc.put(None, None, lambda: order.append("marker"), "marker", after_pending=True)
    time.sleep(0.3)
    assert order == []  # the marker did not overtake its data
    gate.set()
    rc.barrier()
    assert order == ["data", "marker"]


def test_a_failed_write_is_raised_by_the_barrier_and_its_marker_is_never_sent():
    rc = RemoteChunks(write_behind=True)
    sent = []

    def broken():
        raise ConnectionError("connection reset by peer")

    rc.put(("flow", (1, 2)), np.zeros(2), broken, "flow at (1, 2)")
    rc.put(None, None, lambda: sent.append("marker"), "the resample marker at (1, 2)", after_pending=True)
    with pytest.raises(OSError, match=r"writing flow at \(1, 2\) to the object store failed: "
                                      r"ConnectionError: connection reset by peer"):
        rc.barrier()
    assert sent == []
    assert rc.get(("flow", (1, 2))) is None  # a chunk that was not stored is not served from memory
    rc.barrier()  # the failure was reported once; later work goes on
    rc.put(None, None, lambda: sent.append("later"), "later", after_pending=True)
    rc.barrier()
    assert sent == ["later"]


def test_without_write_behind_writes_happen_in_the_call():
    rc = RemoteChunks(write_behind=False)
    sent = []
    rc.put(("a", (0,)), np.arange(3), lambda: sent.append(1), "a")
    assert sent == [1]
    np.testing.assert_array_equal(rc.get(("a", (0,))), np.arange(3))


def test_the_cache_is_bounded_and_an_evicted_chunk_in_flight_is_waited_for():
    rc = RemoteChunks(write_behind=True)
    rc.max_bytes = 3 * 800
    gate = threading.Event()
    done = []
    rc.put(("v", (0,)), np.zeros(100), lambda: (gate.wait(10), done.append(0)), "v at 0")
    for i in range(1, 5):
        rc.put(("v", (i,)), np.full(100, i, np.float64), lambda: None, f"v at {i}")
    assert rc.get(("v", (4,))) is not None and rc.get(("v", (1,))) is None
    threading.Timer(0.2, gate.set).start()
    assert rc.get(("v", (0,))) is None and done == [0]  # evicted: returned only once it was stored
    rc.barrier()
