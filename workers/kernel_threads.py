"""Kernels run single-threaded: OpenCV, numba and BLAS each on one thread
(:func:`single_threaded_kernels`), for the serial executor (bit for bit the Dask workers'
results) and for callers that parallelise over threads themselves (``schlieren check``).
Light on imports, so a command that needs only this does not load the executors."""

from __future__ import annotations

import contextlib

__all__ = ["single_threaded_kernels"]


@contextlib.contextmanager
def single_threaded_kernels():
    """Run OpenCV, numba and BLAS single-threaded, as in the Dask workers, so both executors agree
    bit for bit (threaded BLAS reductions round differently)."""
    import cv2
    import numba
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads(), numba.get_num_threads()
    cv2.setNumThreads(1)
    numba.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(before[0])
        numba.set_num_threads(before[1])
