"""Numba kernels of :mod:`~schlieren.pipeline.tomography.regularisers`: the set's 7-point
Laplacian, the curl's plaquettes and the matrix-free ``C^T C``."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _difference_normal_kernel(inset, indptr, indices, data):
    nz, ny, nx = inset.shape
    idx = np.full(inset.shape, -1, np.int64)
    n = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if inset[k, j, i]:
                    idx[k, j, i] = n
                    n += 1
    pos = 0
    row = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if not inset[k, j, i]:
                    continue
                # neighbours in increasing C order: -z, -y, -x, self, +x, +y, +z
                deg = (k > 0) + (k < nz - 1) + (j > 0) + (j < ny - 1) + (i > 0) + (i < nx - 1)
                for dk, dj, di in ((-1, 0, 0), (0, -1, 0), (0, 0, -1), (0, 0, 0), (0, 0, 1), (0, 1, 0),
                                   (1, 0, 0)):
                    kk, jj, ii = k + dk, j + dj, i + di
                    if dk == 0 and dj == 0 and di == 0:
                        indices[pos] = row
                        data[pos] = deg
                        pos += 1
                    elif 0 <= kk < nz and 0 <= jj < ny and 0 <= ii < nx and inset[kk, jj, ii]:
                        indices[pos] = idx[kk, jj, ii]
                        data[pos] = -1.0
                        pos += 1
                row += 1
                indptr[row] = pos
    return pos


#: Gradient components (0 = x) of the three plaquette planes of :class:`CurlNormal`.
_PLANES = ((0, 1), (0, 2), (1, 2))


@nb.njit(cache=True)
def _plaquettes(colmap, n):
    """Corners of every 2x2 plaquette of the three coordinate planes with at least one
    corner in the set: ``(P, 4)`` unknown indices ``(p, p+e_a, p+e_c, p+e_a+e_c)`` (``n`` =
    outside the set, i.e. zero) and the plane (index into ``_PLANES``) of each."""
    nz, ny, nx = colmap.shape
    # a voxel is a corner of at most 4 plaquettes per plane: at most 12 n of them
    cap = 12 * n
    corners = np.empty((cap, 4), np.int32)
    planes = np.empty(cap, np.int8)
    k = 0
    for plane in range(3):
        ca, cc = _PLANES[plane]
        a, c = 2 - ca, 2 - cc  # grid axes (z, y, x order) of components ca, cc
        da = np.zeros(3, np.int64)
        dc = np.zeros(3, np.int64)
        da[a] = 1
        dc[c] = 1
        for z in range(nz - da[0] - dc[0]):
            for y in range(ny - da[1] - dc[1]):
                for x in range(nx - da[2] - dc[2]):
                    q0 = colmap[z, y, x]
                    qa = colmap[z + da[0], y + da[1], x + da[2]]
                    qc = colmap[z + dc[0], y + dc[1], x + dc[2]]
                    qac = colmap[z + da[0] + dc[0], y + da[1] + dc[1], x + da[2] + dc[2]]
                    if q0 < 0 and qa < 0 and qc < 0 and qac < 0:
                        continue
                    corners[k, 0] = q0 if q0 >= 0 else n
                    corners[k, 1] = qa if qa >= 0 else n
                    corners[k, 2] = qc if qc >= 0 else n
                    corners[k, 3] = qac if qac >= 0 else n
                    planes[k] = plane
                    k += 1
    return corners[:k].copy(), planes[:k].copy()


@nb.njit(cache=True, fastmath=True)
def _curl_apply(corners, planes, x, w, out):
    """``out += w C^T C x`` (``x``, ``out`` (n, 3); corner index ``n`` = outside, zero)."""
    n = x.shape[0]
    for k in range(corners.shape[0]):
        ca, cc = _PLANES[planes[k]]
        p0 = corners[k, 0]
        pa = corners[k, 1]
        pc = corners[k, 2]
        pac = corners[k, 3]
        # circulation: (g_c(pa) + g_c(pac) - g_c(p0) - g_c(pc)) - (g_a(pc) + g_a(pac) - g_a(p0) - g_a(pa))
        v = 0.0
        if p0 < n:
            v += x[p0, ca] - x[p0, cc]
        if pa < n:
            v += x[pa, cc] + x[pa, ca]
        if pc < n:
            v -= x[pc, cc] + x[pc, ca]
        if pac < n:
            v += x[pac, cc] - x[pac, ca]
        v *= w
        if p0 < n:
            out[p0, ca] += v
            out[p0, cc] -= v
        if pa < n:
            out[pa, cc] += v
            out[pa, ca] += v
        if pc < n:
            out[pc, cc] -= v
            out[pc, ca] -= v
        if pac < n:
            out[pac, cc] += v
            out[pac, ca] -= v


@nb.njit(cache=True)
def _curl_diagonal(corners, planes, n):
    d = np.zeros((n, 3))
    for k in range(corners.shape[0]):
        ca, cc = _PLANES[planes[k]]
        for q in range(4):
            j = corners[k, q]
            if j < n:
                d[j, ca] += 1.0
                d[j, cc] += 1.0
    return d
