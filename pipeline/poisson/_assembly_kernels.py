"""Numba kernel of :mod:`~schlieren.pipeline.poisson.assembly`: the rows of ``A`` and ``f``."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def _assemble_rows(hidx, real, rows_z, rows_y, rows_x, D, g, inv_h, indptr, indices, data, f, count_only):
    """Rows of ``A = 1/2 sum_s grad_s^T D grad_s`` and ``f = 1/2 sum_s grad_s^T D g`` (gathered per row).

    For row voxel ``p`` the forward/backward difference at voxel ``i`` contributes
    ``D_ab(i) / h^2 (delta_{i + s e_a} - delta_i)(delta_{i + s e_b} - delta_i)^T`` with
    ``i = p`` or ``i = p - s e_a``; the 3x3x3 neighbourhood of ``p`` holds every column.
    ``hidx`` maps voxels to unknowns (-1 = Dirichlet zero); a term is kept only if
    ``i``, ``i + s e_a`` and ``i + s e_b`` are all ``real`` (differences that would cross
    a face with a natural boundary are dropped). The arrays are padded so that every
    neighbour index is in bounds.
    """
    n = rows_z.shape[0]
    for r in nb.prange(n):
        k = rows_z[r]
        j = rows_y[r]
        i = rows_x[r]
        acc = np.zeros(27)
        fp = 0.0
        for si in range(2):
            s = 2 * si - 1
            for a in range(3):
                # offset of e_a in (z, y, x) order; component a = 0 is x
                az = 1 if a == 2 else 0
                ay = 1 if a == 1 else 0
                ax = 1 if a == 0 else 0
                k1 = k - s * az
                j1 = j - s * ay
                i1 = i - s * ax
                ok1 = real[k1, j1, i1] and real[k, j, i]  # i1 and i1 + s e_a (= p)
                okp = real[k, j, i] and real[k + s * az, j + s * ay, i + s * ax]
                for b in range(3):
                    bz = 1 if b == 2 else 0
                    by = 1 if b == 1 else 0
                    bx = 1 if b == 0 else 0
                    if ok1 and real[k1 + s * bz, j1 + s * by, i1 + s * bx]:
                        d1 = D[k1, j1, i1, a, b]
                        # i1 terms: +d1 at (i1 + s e_b), -d1 at i1 (offsets relative to p)
                        acc[((-s * az + s * bz) + 1) * 9 + ((-s * ay + s * by) + 1) * 3 + (-s * ax + s * bx) + 1] += d1
                        acc[(-s * az + 1) * 9 + (-s * ay + 1) * 3 + (-s * ax + 1)] -= d1
                        fp += s * d1 * g[k1, j1, i1, b]
                    if okp and real[k + s * bz, j + s * by, i + s * bx]:
                        dp = D[k, j, i, a, b]
                        # p terms: -dp at (p + s e_b), +dp at p
                        acc[(s * bz + 1) * 9 + (s * by + 1) * 3 + (s * bx + 1)] -= dp
                        acc[13] += dp
                        fp -= s * dp * g[k, j, i, b]
        row = hidx[k, j, i]
        if count_only:
            c = 0
            for q in range(27):
                if acc[q] != 0.0 and hidx[k + q // 9 - 1, j + (q // 3) % 3 - 1, i + q % 3 - 1] >= 0:
                    c += 1
            indptr[row + 1] = c
        else:
            pos = indptr[row]
            for q in range(27):
                col = hidx[k + q // 9 - 1, j + (q // 3) % 3 - 1, i + q % 3 - 1]
                if acc[q] != 0.0 and col >= 0:
                    indices[pos] = col
                    data[pos] = 0.5 * acc[q] * inv_h * inv_h
                    pos += 1
            f[row] = 0.5 * fp * inv_h
