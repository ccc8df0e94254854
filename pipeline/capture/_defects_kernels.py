"""numba kernel of the defective-pixel statistics (:mod:`.defects`): the median of a
residual's magnitude over every second pixel, by an exact two-pass radix selection on the
float32 bit patterns (two passes of counting instead of a partition).
"""

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def _select(bits: np.ndarray, k: int) -> np.uint32:
    """The ``k``-th smallest (0-based) of the non-negative float32 bit patterns ``bits``
    (ordered as the values are): the high 16 bits by one histogram, the low 16 bits of
    those in its bin by a second."""
    hist = np.zeros(65536, np.int64)
    for b in bits:
        hist[b >> 16] += 1
    below = 0
    hi = 0
    while below + hist[hi] <= k:
        below += hist[hi]
        hi += 1
    hist[:] = 0
    for b in bits:
        if (b >> 16) == hi:
            hist[b & 0xFFFF] += 1
    lo = 0
    while below + hist[lo] <= k:
        below += hist[lo]
        lo += 1
    return np.uint32((hi << 16) | lo)


@nb.njit(cache=True, nogil=True)
def _abs_bits_every_second(r: np.ndarray) -> np.ndarray:
    """Bit patterns of ``|r[::2, ::2]|`` (float32, sign bit cleared), row by row."""
    rows, cols = (r.shape[0] + 1) // 2, (r.shape[1] + 1) // 2
    out = np.empty(rows * cols, np.uint32)
    n = 0
    for i in range(0, r.shape[0], 2):
        u = r[i].view(np.uint32)
        for j in range(0, r.shape[1], 2):
            out[n] = u[j] & np.uint32(0x7FFFFFFF)
            n += 1
    return out


def abs_median_every_second(r: np.ndarray) -> float:
    """``np.median(np.abs(r[::2, ::2]))`` of a finite float32 image, bit for bit (the mean
    of the two middle values in float32 for an even count, as NumPy's)."""
    bits = _abs_bits_every_second(np.ascontiguousarray(r, np.float32))
    n = len(bits)
    hi = np.array([_select(bits, n // 2)], np.uint32).view(np.float32)[0]
    if n % 2:
        return float(hi)
    lo = np.array([_select(bits, n // 2 - 1)], np.uint32).view(np.float32)[0]
    return float((lo + hi) / np.float32(2))
