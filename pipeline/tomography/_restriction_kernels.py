"""Numba kernels of :mod:`~schlieren.pipeline.tomography.restriction`: the restriction's
count and fill passes, the fused setup pass, and three-column CSR products (``S x``,
``S^T y``, ``S^T S x``) over fixed row blocks (see the module notes there on determinism).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def _count_kept(indptr, indices, rows, keep, counts):
    """Entries of each of ``rows`` in the columns ``keep`` (uint8 0/1) marks; four
    independent partial counts per row (shorter dependency chains; docs/tuning.md, "Speed")."""
    for k in nb.prange(rows.shape[0]):
        r = rows[k]
        p = indptr[r]
        end = indptr[r + 1]
        c0 = 0
        c1 = 0
        c2 = 0
        c3 = 0
        while p + 4 <= end:
            c0 += keep[indices[p]]
            c1 += keep[indices[p + 1]]
            c2 += keep[indices[p + 2]]
            c3 += keep[indices[p + 3]]
            p += 4
        while p < end:
            c0 += keep[indices[p]]
            p += 1
        counts[k] = c0 + c1 + c2 + c3


@nb.njit(cache=True, inline="always")
def _restrict_row(indptr, indices, data, r, colmap, new_indices, new_data, q):
    """Copy row ``r`` from position ``q`` on, keeping the columns ``colmap`` maps (>= 0)."""
    for p in range(indptr[r], indptr[r + 1]):
        j = colmap[indices[p]]
        if j >= 0:
            new_indices[q] = j
            new_data[q] = data[p]
            q += 1


@nb.njit(cache=True, fastmath=True, inline="always")
def _row_setup(indptr, indices, data, r, b, x, with_x, acc):
    """One row's share of ``diag(S^T S)``, ``S^T b`` and (if ``with_x``) ``S^T S x``.

    ``acc[j]`` holds the three products of column ``j`` side by side (float32: one cache
    line per entry instead of three arrays' worth): ``acc[j, 0]`` the squared sum, ``1:4``
    ``S^T b``, ``4:7`` ``S^T S x`` (``x`` float32 as in :func:`_normal3`).
    """
    b0 = np.float32(b[r, 0])
    b1 = np.float32(b[r, 1])
    b2 = np.float32(b[r, 2])
    t0 = t1 = t2 = np.float32(0.0)
    if with_x:
        t0, t1, t2 = row_dot3_f32(indptr, indices, data, x, r)
    for p in range(indptr[r], indptr[r + 1]):
        j = indices[p]
        v = data[p]
        acc[j, 0] += v * v
        acc[j, 1] += v * b0
        acc[j, 2] += v * b1
        acc[j, 3] += v * b2
        if with_x:  # loop-invariant: the compiler unswitches it
            acc[j, 4] += v * t0
            acc[j, 5] += v * t1
            acc[j, 6] += v * t2


@nb.njit(parallel=True, cache=True)
def _restrict_fill(indptr, indices, data, rows, colmap, new_indptr, new_indices, new_data):
    for k in nb.prange(rows.shape[0]):
        _restrict_row(indptr, indices, data, rows[k], colmap, new_indices, new_data, new_indptr[k])


@nb.njit(inline="always", cache=True)
def _setup_accumulators(m, n, nchunks):
    """Per-block partial sums of the setup products (see :func:`_row_setup`), and the row
    bounds of ``nchunks`` blocks."""
    acc = np.zeros((nchunks, n, 8), np.float32)
    bounds = np.linspace(0, m, nchunks + 1).astype(np.int64)
    return acc, bounds


@nb.njit(parallel=True, cache=True, fastmath=True)
def _sum_chunks(acc, n, nchunks):
    """Sum the per-block partial products in block order (fixed: thread-count independent),
    in float64: ``(diag(S^T S) (n,), S^T b (n, 3), S^T S x (n, 3))``."""
    out_s = np.zeros(n)
    out_b = np.zeros((n, 3))
    out_x = np.zeros((n, 3))
    for j in nb.prange(n):
        for c in range(nchunks):
            a = acc[c, j]
            out_s[j] += a[0]
            out_b[j, 0] += a[1]
            out_b[j, 1] += a[2]
            out_b[j, 2] += a[3]
            out_x[j, 0] += a[4]
            out_x[j, 1] += a[5]
            out_x[j, 2] += a[6]
    return out_s, out_b, out_x


@nb.njit(parallel=True, cache=True, fastmath=True)
def _restrict_setup3(indptr, indices, data, rows, colmap, new_indptr, new_indices, new_data, b, x, n,
                     nchunks, with_x, valid):
    """:func:`_restrict_fill` fused with :func:`_setup3` (each restricted row is used while hot);
    rows whose ray ``valid`` (uint8 over all rays; empty: every ray) marks 0 are written but
    left out of the products."""
    acc, bounds = _setup_accumulators(rows.shape[0], n, nchunks)
    masked = valid.shape[0] > 0
    for c in nb.prange(nchunks):
        a = acc[c]
        for k in range(bounds[c], bounds[c + 1]):
            _restrict_row(indptr, indices, data, rows[k], colmap, new_indices, new_data, new_indptr[k])
            if masked and valid[rows[k]] == 0:
                continue
            _row_setup(new_indptr, new_indices, new_data, k, b, x, with_x, a)
    return _sum_chunks(acc, n, nchunks)


@nb.njit(cache=True, fastmath=True, inline="always")
def row_dot3(indptr, indices, data, x, r):
    """Row ``r`` of a CSR matrix times the three columns of ``x`` (a tuple of three sums)."""
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    for p in range(indptr[r], indptr[r + 1]):
        j = indices[p]
        v = data[p]
        a0 += v * x[j, 0]
        a1 += v * x[j, 1]
        a2 += v * x[j, 2]
    return a0, a1, a2


@nb.njit(cache=True, fastmath=True, inline="always")
def row_scatter3(indptr, indices, data, r, t0, t1, t2, a):
    """``a[j] += S[r, j] * (t0, t1, t2)`` over the entries of CSR row ``r``."""
    for p in range(indptr[r], indptr[r + 1]):
        j = indices[p]
        v = data[p]
        a[j, 0] += v * t0
        a[j, 1] += v * t1
        a[j, 2] += v * t2


@nb.njit(parallel=True, cache=True, fastmath=True)
def _move3(src, dst, idx, scatter):
    """``dst[idx[i]] = src[i]`` (``scatter``) or ``dst[i] = src[idx[i]]``, three components
    (cast to ``dst``'s type)."""
    for i in nb.prange(idx.shape[0]):
        j = idx[i]
        for c in range(3):
            if scatter:
                dst[j, c] = src[i, c]
            else:
                dst[i, c] = src[j, c]


@nb.njit(parallel=True, cache=True, fastmath=True)
def _reduce_chunks3(acc):
    """Sum per-block partial products (nchunks, n, 3) in block order (thread-count independent)."""
    nchunks, n = acc.shape[0], acc.shape[1]
    out = np.zeros((n, 3))
    for j in nb.prange(n):
        for c in range(nchunks):
            out[j, 0] += acc[c, j, 0]
            out[j, 1] += acc[c, j, 1]
            out[j, 2] += acc[c, j, 2]
    return out


@nb.njit(parallel=True, cache=True, fastmath=True)
def matvec3(indptr, indices, data, x, y):
    """``y = M x`` for a CSR matrix ``M`` and three columns ``x`` (n, 3)."""
    m = indptr.shape[0] - 1
    for r in nb.prange(m):
        a0, a1, a2 = row_dot3(indptr, indices, data, x, r)
        y[r, 0] = a0
        y[r, 1] = a1
        y[r, 2] = a2


@nb.njit(parallel=True, cache=True, fastmath=True)
def _rmatvec3(indptr, indices, data, y, n, nchunks):
    m = indptr.shape[0] - 1
    acc = np.zeros((nchunks, n, 3))
    bounds = np.linspace(0, m, nchunks + 1).astype(np.int64)
    for c in nb.prange(nchunks):
        a = acc[c]
        for r in range(bounds[c], bounds[c + 1]):
            row_scatter3(indptr, indices, data, r, y[r, 0], y[r, 1], y[r, 2], a)
    return _reduce_chunks3(acc)


@nb.njit(cache=True, fastmath=True, inline="always")
def row_dot3_f32(indptr, indices, data, x, r):
    """:func:`row_dot3` in float32 with two interleaved partial sums per column.

    The single-accumulator loop is bound by the latency of its chain of fused
    multiply-adds (about 4 cycles per entry); two independent chains halve that. The
    summation order is fixed (even and odd entries, then their sum), so results stay
    deterministic.
    """
    a0 = np.float32(0.0)
    a1 = np.float32(0.0)
    a2 = np.float32(0.0)
    b0 = np.float32(0.0)
    b1 = np.float32(0.0)
    b2 = np.float32(0.0)
    p = indptr[r]
    end = indptr[r + 1]
    while p + 1 < end:
        j = indices[p]
        v = data[p]
        k = indices[p + 1]
        w = data[p + 1]
        a0 += v * x[j, 0]
        a1 += v * x[j, 1]
        a2 += v * x[j, 2]
        b0 += w * x[k, 0]
        b1 += w * x[k, 1]
        b2 += w * x[k, 2]
        p += 2
    if p < end:
        j = indices[p]
        v = data[p]
        a0 += v * x[j, 0]
        a1 += v * x[j, 1]
        a2 += v * x[j, 2]
    return a0 + b0, a1 + b1, a2 + b2


@nb.njit(cache=True, fastmath=True, inline="always")
def _scatter_block(indptr, indices, data, x, y, lo, hi, fused, live, a):
    """Rows ``lo <= r < hi`` of :func:`_scatter_blocks_f32` into the float32 sums ``a``."""
    masked = live.shape[0] > 0
    for r in range(lo, hi):
        if masked and live[r] == 0:
            continue
        if fused:
            t0, t1, t2 = row_dot3_f32(indptr, indices, data, x, r)
        else:
            t0, t1, t2 = y[r, 0], y[r, 1], y[r, 2]
        row_scatter3(indptr, indices, data, r, t0, t1, t2, a)


@nb.njit(parallel=True, cache=True, fastmath=True)
def _scatter_blocks_f32_parallel(indptr, indices, data, x, y, n, nchunks, fused, live):
    m = indptr.shape[0] - 1
    acc = np.zeros((nchunks, n, 3), np.float32)
    bounds = np.linspace(0, m, nchunks + 1).astype(np.int64)
    for c in nb.prange(nchunks):
        _scatter_block(indptr, indices, data, x, y, bounds[c], bounds[c + 1], fused, live, acc[c])
    return _reduce_chunks3(acc)


@nb.njit(cache=True, fastmath=True)
def _scatter_blocks_f32_serial(indptr, indices, data, x, y, n, nchunks, fused, live):
    m = indptr.shape[0] - 1
    out = np.zeros((n, 3))
    a = np.empty((n, 3), np.float32)
    bounds = np.linspace(0, m, nchunks + 1).astype(np.int64)
    for c in range(nchunks):
        a[:] = 0.0
        _scatter_block(indptr, indices, data, x, y, bounds[c], bounds[c + 1], fused, live, a)
        for j in range(n):
            out[j, 0] += a[j, 0]
            out[j, 1] += a[j, 1]
            out[j, 2] += a[j, 2]
    return out


@nb.njit(parallel=True, cache=True, fastmath=True)
def _matvec3_f32(indptr, indices, data, x, y):
    """``y = S x`` in float32 (the first half of :func:`_normal3`)."""
    for r in nb.prange(indptr.shape[0] - 1):
        t0, t1, t2 = row_dot3_f32(indptr, indices, data, x, r)
        y[r, 0] = t0
        y[r, 1] = t1
        y[r, 2] = t2


@nb.njit(parallel=True, cache=True)
def _colsumsq(indices, data, n, nchunks):
    nnz = indices.shape[0]
    acc = np.zeros((nchunks, n))
    bounds = np.linspace(0, nnz, nchunks + 1).astype(np.int64)
    for c in nb.prange(nchunks):
        for p in range(bounds[c], bounds[c + 1]):
            v = np.float64(data[p])
            acc[c, indices[p]] += v * v
    out = np.zeros(n)
    for c in range(nchunks):
        out += acc[c]
    return out


@nb.njit(cache=True, fastmath=True, inline="always")
def _setup_block(indptr, indices, data, b, x, lo, hi, with_x, live, a):
    """Rows ``lo <= r < hi`` of :func:`_setup3` into the float32 sums ``a``."""
    masked = live.shape[0] > 0
    for r in range(lo, hi):
        if masked and live[r] == 0:
            continue
        _row_setup(indptr, indices, data, r, b, x, with_x, a)


@nb.njit(parallel=True, cache=True, fastmath=True)
def _setup3_parallel(indptr, indices, data, b, x, n, nchunks, with_x, live):
    acc, bounds = _setup_accumulators(indptr.shape[0] - 1, n, nchunks)
    for c in nb.prange(nchunks):
        _setup_block(indptr, indices, data, b, x, bounds[c], bounds[c + 1], with_x, live, acc[c])
    return _sum_chunks(acc, n, nchunks)


@nb.njit(cache=True, fastmath=True)
def _setup3_serial(indptr, indices, data, b, x, n, nchunks, with_x, live):
    bounds = np.linspace(0, indptr.shape[0] - 1, nchunks + 1).astype(np.int64)
    a = np.empty((n, 8), np.float32)
    out_s = np.zeros(n)
    out_b = np.zeros((n, 3))
    out_x = np.zeros((n, 3))
    for c in range(nchunks):
        a[:] = 0.0
        _setup_block(indptr, indices, data, b, x, bounds[c], bounds[c + 1], with_x, live, a)
        for j in range(n):  # as _sum_chunks: block c added after blocks 0 .. c-1
            out_s[j] += a[j, 0]
            out_b[j, 0] += a[j, 1]
            out_b[j, 1] += a[j, 2]
            out_b[j, 2] += a[j, 3]
            out_x[j, 0] += a[j, 4]
            out_x[j, 1] += a[j, 5]
            out_x[j, 2] += a[j, 6]
    return out_s, out_b, out_x


@nb.njit(parallel=True, cache=True)
def _live_rows(indptr, indices, keep, valid, out):
    """``out[r]`` = 1 if row ``r`` is ``valid`` and has an entry in a column ``keep`` marks."""
    for r in nb.prange(indptr.shape[0] - 1):
        hit = 0
        if valid[r]:
            for p in range(indptr[r], indptr[r + 1]):
                if keep[indices[p]]:
                    hit = 1
                    break
        out[r] = hit
