"""Numba kernels of :mod:`~schlieren.pipeline.tomography.projection`: ray clipping, the
normalised basis weights, the projection build's pass over the rays and row pruning."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def _clip_kernel(o, d, lo, hi, s0, s1):
    """One pass per ray (the numpy form made a dozen (M, 3) temporaries; docs/tuning.md,
    "Speed"). An axis-parallel ray inside a slab is unbounded along that axis, outside it
    misses."""
    for r in nb.prange(o.shape[0]):
        t0 = 0.0
        t1 = np.inf
        for k in range(3):
            if d[r, k] == 0.0:
                if not (lo[k] <= o[r, k] <= hi[k]):
                    t0 = np.inf
                    t1 = -np.inf
                continue
            inv = 1.0 / d[r, k]
            ta = (lo[k] - o[r, k]) * inv
            tb = (hi[k] - o[r, k]) * inv
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        s0[r] = t0
        s1[r] = t1


@nb.njit(cache=True)
def _cell_weights(qx, qy, qz, nx, ny, nz, idx, w):
    """Normalised basis weights of the eight voxel centres around index point q."""
    ix = min(max(int(np.floor(qx)), 0), nx - 2)
    iy = min(max(int(np.floor(qy)), 0), ny - 2)
    iz = min(max(int(np.floor(qz)), 0), nz - 2)
    fx = qx - ix
    fy = qy - iy
    fz = qz - iz
    tot = 0.0
    k = 0
    for dz in range(2):
        for dy in range(2):
            for dx in range(2):
                ex = fx - dx
                ey = fy - dy
                ez = fz - dz
                r = np.sqrt(ex * ex + ey * ey + ez * ez)
                v = 1.0 - r
                if v < 0.0:
                    v = 0.0
                w[k] = v
                idx[k] = ((iz + dz) * ny + (iy + dy)) * nx + (ix + dx)
                tot += v
                k += 1
    for k in range(8):
        w[k] /= tot


@nb.njit(cache=True)
def _basis_weights_kernel(q, nx, ny, nz):
    n = q.shape[0]
    idx_out = np.empty((n, 8), np.int64)
    w_out = np.empty((n, 8), np.float64)
    idx = np.empty(8, np.int64)
    w = np.empty(8, np.float64)
    for p in range(n):
        _cell_weights(q[p, 0], q[p, 1], q[p, 2], nx, ny, nz, idx, w)
        for k in range(8):
            idx_out[p, k] = idx[k]
            w_out[p, k] = w[k]
    return idx_out, w_out


@nb.njit(cache=True, inline="always")
def _flush_run(acc, order, nord, base, nx, ny, ray, stamp, pos, cols, vals, cnt):
    """Enter the run totals ``acc`` of the cell ``base`` into the row being built, its
    nodes in the order their weights first became positive (``order[:nord]``, corner ``j``
    = ``dz dy dx`` in binary); clears ``acc``; returns the new entry count."""
    for t in range(nord):
        j = order[t]
        v = acc[j]
        acc[j] = 0.0
        node = base + ((j >> 2) * ny + ((j >> 1) & 1)) * nx + (j & 1)
        if stamp[node] != ray:
            stamp[node] = ray
            pos[node] = cnt
            cols[cnt] = node
            vals[cnt] = v
            cnt += 1
        else:
            vals[pos[node]] += v
    return cnt


# ~110 lines in one kernel: the build's hot loop, its per-chunk scratch (stamp, pos, acc,
# order) and the sample loop's state local to one prange body
@nb.njit(parallel=True, cache=True)
def _project_pass(a, b, s0, s1, nx, ny, nz, ds_target, bounds, counts, starts, limits, indices, data,
                  packed):
    """The projection build's pass over the rays: each row's entries and its length.

    Rays ``bounds[c]:bounds[c + 1]`` form chunk ``c`` (one thread each); ``counts[ray]``
    receives every row's length. Packed (``packed=True``), the rows of chunk ``c`` go one
    after another from ``starts[c]``; a chunk whose rows would pass ``limits[c]`` stops
    writing and sets ``limits[c] = -1`` (its counts stay right). Unpacked, row ``ray`` goes
    to ``starts[ray]`` (an indptr built from those counts).

    ``a`` (M, 3) are ray origins and ``b`` (M, 3) unit directions in *index* space scaled
    so that index point = a + s * b for world arc length s (b = d / h).

    The midpoint samples of a ray fall in the same grid cell about three at a time (step
    0.25 voxel, mean chord of a cube 2/3 voxel): the eight weights ``w_k ds`` of a run of
    samples in one cell are summed first and entered into the row once per run, when the
    ray leaves the cell (the row's node lookups are the build's cache misses). This gives
    the same entries as adding every sample's weights one by one (entries in order of
    first appearance, so the products sum in the same order and the values are
    bit-identical), in a fraction of the time (docs/tuning.md, "Speed").
    """
    nnodes = nx * ny * nz
    nchunks = bounds.shape[0] - 1
    for c in nb.prange(nchunks):
        stamp = np.full(nnodes, -1, np.int32)  # int32: half the cache footprint of int64
        pos = np.empty(nnodes, np.int32)
        acc = np.zeros(8, np.float64)
        w = np.empty(8, np.float64)
        order = np.empty(8, np.int64)
        cols = np.empty(0, np.int64)
        vals = np.empty(0, np.float64)
        at = starts[c] if packed else 0
        for ray in range(bounds[c], bounds[c + 1]):
            L = s1[ray] - s0[ray]
            if L <= 0.0:
                counts[ray] = 0
                continue
            nsamp = int(np.ceil(L / ds_target - 1e-9))
            if nsamp < 1:
                nsamp = 1
            ds = L / nsamp
            cap = 8 * nsamp
            if cols.shape[0] < cap:
                cols = np.empty(2 * cap, np.int64)
                vals = np.empty(2 * cap, np.float64)
            cnt = 0
            cell = -1
            nord = 0
            seen = 0  # corners of the current cell with a positive weight so far (bit j)
            for k in range(nsamp):
                s = s0[ray] + (k + 0.5) * ds
                qx = a[ray, 0] + s * b[ray, 0]
                qy = a[ray, 1] + s * b[ray, 1]
                qz = a[ray, 2] + s * b[ray, 2]
                ix = min(max(int(np.floor(qx)), 0), nx - 2)
                iy = min(max(int(np.floor(qy)), 0), ny - 2)
                iz = min(max(int(np.floor(qz)), 0), nz - 2)
                here = (iz * ny + iy) * nx + ix
                if here != cell:
                    if cell >= 0:
                        cnt = _flush_run(acc, order, nord, cell, nx, ny, ray, stamp, pos, cols, vals, cnt)
                    cell = here
                    nord = 0
                    seen = 0
                fx = qx - ix
                fy = qy - iy
                fz = qz - iz
                tot = 0.0
                pm = 0
                j = 0
                for dz in range(2):
                    ez = fz - dz
                    for dy in range(2):
                        ey = fy - dy
                        for dx in range(2):
                            ex = fx - dx
                            r2 = ex * ex + ey * ey + ez * ez
                            if r2 < 1.0:
                                pm |= 1 << j
                            v = 1.0 - np.sqrt(r2)  # the normalised radial linear basis, eq. 6
                            if v < 0.0:
                                v = 0.0
                            w[j] = v
                            tot += v
                            j += 1
                new = pm & ~seen
                if new:
                    for j in range(8):
                        if new & (1 << j):
                            order[nord] = j
                            nord += 1
                    seen |= pm
                inv = ds / tot
                for j in range(8):
                    acc[j] += w[j] * inv
            cnt = _flush_run(acc, order, nord, cell, nx, ny, ray, stamp, pos, cols, vals, cnt)
            counts[ray] = cnt
            if packed:
                if limits[c] < 0 or at + cnt > limits[c]:
                    limits[c] = -1  # over the bound: the caller builds this matrix in two passes
                    continue
                start = at
                at += cnt
            else:
                start = starts[ray]
            for j in range(cnt):
                indices[start + j] = cols[j]
                data[start + j] = vals[j]


@nb.njit(cache=True)
def _prune_kernel(indptr, indices, data, fraction):
    """Compact every row to its entries >= ``fraction`` x its largest (kept entries move
    left only, so one sequential pass works in place); rescale to the row's sum; returns
    the new number of entries (``indptr`` is rewritten)."""
    q = 0
    start = indptr[0]
    for r in range(indptr.shape[0] - 1):
        end = indptr[r + 1]
        mx = 0.0
        total = 0.0
        for p in range(start, end):
            v = np.float64(data[p])
            total += v
            if v > mx:
                mx = v
        lim = fraction * mx
        kept = 0.0
        row_start = q
        for p in range(start, end):
            v = np.float64(data[p])
            if v >= lim:
                indices[q] = indices[p]
                data[q] = data[p]
                kept += v
                q += 1
        if kept > 0.0 and kept != total:
            scale = total / kept
            for p in range(row_start, q):
                data[p] = np.float32(np.float64(data[p]) * scale)
        indptr[r] = row_start
        start = end
    indptr[indptr.shape[0] - 1] = q
    return q
