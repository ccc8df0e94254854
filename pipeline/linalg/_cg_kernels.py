"""Serial numba vector kernels of :class:`~schlieren.pipeline.linalg.cg.SerialVectors`
(one column: the Poisson integration's preconditioned CG; why serial loops and not BLAS:
:func:`~schlieren.pipeline.linalg.cg.pcg`)."""

from __future__ import annotations

import numba as nb

__all__ = ["dot", "cg_update", "cg_direction"]


@nb.njit(cache=True, fastmath=True)
def dot(a, b):
    """``a . b`` of two vectors."""
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@nb.njit(cache=True, fastmath=True)
def cg_update(x, r, p, q, alpha):
    """``x += alpha p``, ``r -= alpha q``; returns ``r . r``."""
    s = 0.0
    for i in range(x.shape[0]):
        x[i] += alpha * p[i]
        ri = r[i] - alpha * q[i]
        r[i] = ri
        s += ri * ri
    return s


@nb.njit(cache=True, fastmath=True)
def cg_direction(p, z, beta):
    """``p = z + beta p``."""
    for i in range(p.shape[0]):
        p[i] = z[i] + beta * p[i]
