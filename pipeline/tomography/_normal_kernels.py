"""Numba kernels of :mod:`~schlieren.pipeline.tomography.normal_equations`: the fused vector
work of one CG iteration on three columns (serial loops; the normal product's pass over
``S`` is the parallel part)."""

from __future__ import annotations

import numba as nb
import numpy as np

from schlieren.pipeline.tomography._restriction_kernels import row_dot3


@nb.njit(cache=True)
def _cg_apply(P, d, indptr, indices, data, mu2, x, p, q):
    """``q = P (d + mu2 M x)`` (``M`` in CSR, ``P`` a row scaling); returns ``p . q`` per column."""
    pq = np.zeros(3)
    for i in range(q.shape[0]):
        r0 = d[i, 0]
        r1 = d[i, 1]
        r2 = d[i, 2]
        if mu2 > 0.0:
            a0, a1, a2 = row_dot3(indptr, indices, data, x, i)
            r0 += mu2 * a0
            r1 += mu2 * a1
            r2 += mu2 * a2
        q[i, 0] = P[i] * r0
        q[i, 1] = P[i] * r1
        q[i, 2] = P[i] * r2
        pq[0] += p[i, 0] * q[i, 0]
        pq[1] += p[i, 1] * q[i, 1]
        pq[2] += p[i, 2] * q[i, 2]
    return pq


@nb.njit(cache=True)
def _cg_update3(z, StSx, r, p, q, Sp, alpha):
    """``z += alpha p``, ``StSx += alpha Sp``, ``r -= alpha q`` per column; returns ``r . r``."""
    rr = np.zeros(3)
    for i in range(z.shape[0]):
        for c in range(3):
            a = alpha[c]
            z[i, c] += a * p[i, c]
            StSx[i, c] += a * Sp[i, c]
            v = r[i, c] - a * q[i, c]
            r[i, c] = v
            rr[c] += v * v
    return rr


@nb.njit(cache=True)
def _cg_direction3(p, r, beta, P, x):
    """``p = r + beta p`` per column and ``x = P p``."""
    for i in range(p.shape[0]):
        for c in range(3):
            v = r[i, c] + beta[c] * p[i, c]
            p[i, c] = v
            x[i, c] = P[i] * v
