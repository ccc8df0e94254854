"""Numba kernel of :mod:`~schlieren.pipeline.tomography.binning`: the mean of each block of flow cells."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def _bin_kernel(a, b, need, out):
    # out[c, i, j] = mean of the cells of block (i, j) whose components are all finite;
    # NaN when fewer than ``need`` cells are
    C, hb, wb, k = out.shape
    acc = np.empty(k, np.float64)
    for c in range(C):
        for i in range(hb):
            for j in range(wb):
                acc[:] = 0.0
                n = 0
                for di in range(b):
                    for dj in range(b):
                        ok = True
                        for q in range(k):
                            if not np.isfinite(a[c, i * b + di, j * b + dj, q]):
                                ok = False
                        if ok:
                            n += 1
                            for q in range(k):
                                acc[q] += a[c, i * b + di, j * b + dj, q]
                for q in range(k):
                    out[c, i, j, q] = acc[q] / n if n >= need and n > 0 else np.nan
