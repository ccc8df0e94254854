"""Ray-cast projection operator of the normalised radial basis (paper sec. 5, eqs. 4-6).

Basis: one radially symmetric linear function per voxel centre,
``phi_hat_i(x) = max(0, 1 - |x - x_i| / h)`` (support radius one voxel, i.e. one voxel
overlap in each dimension), normalised as ``phi_i = phi_hat_i / sum_j phi_hat_j`` over
*all* grid nodes (so the normalisation is geometry only and does not depend on the hull).
A point in the cell spanned by eight voxel centres is only inside the supports of those
eight centres (any other centre is at least one voxel away along some axis), and at least
one of them is closer than ``sqrt(3)/2 h``, so the normalisation never divides by zero.
Since ``phi_i(x_j) = delta_ij`` the coefficients are the field values at voxel centres.

Entries ``S[ray, i] = integral phi_i ds`` (metres) are approximated by the midpoint rule
on straight rays (the paper's paraxial approximation) clipped to the box spanned by the
voxel centres, with ``ceil(L / (step * h))`` equal sub-intervals.

Here: the full-grid matrix ``S`` (:func:`build_projection`, one pass over the rays in
numba kernels, :mod:`~schlieren.pipeline.tomography._projection_kernels`), the pruning of
the entries a ray only grazes (:func:`prune_rows`) and the buffers they live in.
"""

from __future__ import annotations

import mmap

import numba as nb
import numpy as np
import scipy.sparse as sp

from schlieren.pipeline.tomography._projection_kernels import (
    _basis_weights_kernel,
    _clip_kernel,
    _project_pass,
    _prune_kernel,
)
from schlieren.pipeline.tomography.params import TomoParams

__all__ = ["clip_rays_to_box", "basis_weights", "build_projection", "prune_rows", "csr_view", "large_empty"]

#: Buffers from this size on are backed by transparent huge pages (:func:`large_empty`).
_HUGE_PAGE_BYTES = 32 << 20


def large_empty(size: int, dtype) -> np.ndarray:
    """``np.empty(size, dtype)`` for a large 1-D buffer, backed by transparent huge pages
    where the kernel offers them on request (``madvise`` mode; a no-op elsewhere).

    The first write to fresh memory faults one page at a time, and 4 KiB pages make the
    first pass over a large new buffer far slower than 2 MiB pages (docs/tuning.md,
    "Speed"). Below 32 MiB, or without ``MADV_HUGEPAGE``, this is plain ``np.empty``.
    """
    dtype = np.dtype(dtype)
    size = int(size)
    nbytes = size * dtype.itemsize
    if nbytes < _HUGE_PAGE_BYTES or not hasattr(mmap, "MADV_HUGEPAGE"):
        return np.empty(size, dtype)
    buf = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    try:
        buf.madvise(mmap.MADV_HUGEPAGE)
    except OSError:  # pragma: no cover - kernels without transparent huge pages
        pass
    return np.frombuffer(buf, dtype=dtype, count=size)  # the array keeps the mapping alive


def clip_rays_to_box(origins: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Ray parameters where straight rays enter and leave an axis-aligned box (slab method).

    Parameters
    ----------
    origins, dirs : ndarray, shape (M, 3)
        Ray origins and unit directions (any consistent frame).
    lo, hi : ndarray, shape (3,)
        Box corners in the same frame.

    Returns
    -------
    s0, s1 : ndarray, shape (M,)
        Entry and exit parameters (``s1 <= s0`` when the ray misses; ``s0 >= 0``).
    """
    o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    s0 = np.empty(len(o))
    s1 = np.empty(len(o))
    _clip_kernel(o, d, np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64), s0, s1)
    return s0, s1


def basis_weights(q: np.ndarray, shape_zyx) -> tuple[np.ndarray, np.ndarray]:
    """Normalised basis values at continuous voxel-index points (for tests and resampling).

    Parameters
    ----------
    q : ndarray, shape (P, 3)
        Continuous indices ``(ix, iy, iz)`` inside ``[0, n - 1]``.
    shape_zyx : tuple of int

    Returns
    -------
    idx : ndarray, shape (P, 8) int64
        Flat voxel indices (C order of ``(nz, ny, nx)``).
    w : ndarray, shape (P, 8)
        ``phi_i(q)``; rows sum to 1.
    """
    nz, ny, nx = shape_zyx
    return _basis_weights_kernel(np.ascontiguousarray(q, dtype=np.float64), nx, ny, nz)


def _row_caps(a: np.ndarray, b: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Upper bound on each row's entries (see :func:`build_projection`): 8 + 4 x the cell
    index changes between the ray's entry and exit, +1 per axis of slack; 0 for a miss."""
    hit = s1 > s0
    qa = a + np.where(hit, s0, 0.0)[:, None] * b
    qb = a + np.where(hit, s1, 0.0)[:, None] * b
    return np.where(hit, 20 + 4 * np.abs(np.floor(qb) - np.floor(qa)).sum(axis=1), 0).astype(np.int64)


def build_projection(origins: np.ndarray, dirs: np.ndarray, shape_zyx, origin_xyz, h: float,
                     *, step: float = TomoParams.step) -> sp.csr_matrix:
    """Full-grid projection matrix of line integrals of the normalised basis (eq. 6).

    Parameters
    ----------
    origins, dirs : ndarray, shape (M, 3)
        Ray origins (metres, world) and unit directions.
    shape_zyx : tuple of int
        Grid shape ``(nz, ny, nx)``.
    origin_xyz : ndarray, shape (3,)
        World position of voxel centre ``[0, 0, 0]``.
    h : float
        Voxel size, metres.
    step : float
        Sampling step along the ray in voxels (midpoint rule).

    Returns
    -------
    S : scipy.sparse.csr_matrix, shape (M, nz*ny*nx), float32 data, int32 indices
        Entries in metres; within each row the columns are in marching order.
    """
    nz, ny, nx = (int(v) for v in shape_zyx)
    if min(nx, ny, nz) < 2:
        raise ValueError("the grid needs at least two voxels along every axis")
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    a = (origins - np.asarray(origin_xyz, dtype=np.float64)) / h
    b = dirs / h
    hi = np.array([nx - 1, ny - 1, nz - 1], dtype=np.float64)
    s0, s1 = clip_rays_to_box(a, b, np.zeros(3), hi)
    m = len(a)
    counts = np.zeros(m, np.int64)
    indptr = np.zeros(m + 1, np.int64)
    nchunks = max(1, min(m, 8 * nb.get_num_threads()))
    bounds = np.linspace(0, m, nchunks + 1).astype(np.int64)
    # One pass into buffers sized by a bound on each row's length, then the chunks moved
    # together (a count pass first took a third of the build; docs/tuning.md, "Speed").
    # The bound: a row's entries are the distinct nodes of the cells
    # its samples visit; the first cell has 8, and a step into a cell that differs in k
    # indices adds at most 8 - 2^(3-k) <= 4k new ones, so a row has at most
    # 8 + 4 x (cell-index changes along x, y, z); along a straight ray each index is
    # monotone, so its changes are at most |floor(exit) - floor(entry)| (+1 of slack per
    # axis for rounding). The bound exceeds the entries (docs/tuning.md, "Speed"), but
    # pages never written cost no memory.
    cap = _row_caps(a, b, s0, s1)
    csum = np.zeros(m + 1, np.int64)
    np.cumsum(cap, out=csum[1:])
    starts = csum[bounds[:-1]].copy()
    limits = csum[bounds[1:]].copy()
    total = int(csum[-1])
    indices = large_empty(total, np.int32)
    data = large_empty(total, np.float32)
    _project_pass(a, b, s0, s1, nx, ny, nz, step * h, bounds, counts, starts, limits, indices, data, True)
    np.cumsum(counts, out=indptr[1:])
    nnz = int(indptr[-1])
    if np.all(limits >= 0):
        for c in range(nchunks):  # chunk c's rows to just after chunk c - 1's (left moves only)
            n = int(indptr[bounds[c + 1]] - indptr[bounds[c]])
            dst, src = int(indptr[bounds[c]]), int(starts[c])
            if n and dst != src:
                indices[dst:dst + n] = indices[src:src + n]  # numpy copes with the overlap
                data[dst:dst + n] = data[src:src + n]
        indices, data = indices[:nnz], data[:nnz]
    else:  # the bound above holds; kept as a guard (tests force it)
        indices = large_empty(nnz, np.int32)
        data = large_empty(nnz, np.float32)
        _project_pass(a, b, s0, s1, nx, ny, nz, step * h, bounds, counts, indptr, limits, indices, data,
                      False)
    if nnz < np.iinfo(np.int32).max:
        indptr = indptr.astype(np.int32)
    return sp.csr_matrix((data, indices, indptr), shape=(m, nx * ny * nz))


def prune_rows(S: sp.csr_matrix, fraction: float) -> sp.csr_matrix:
    """Drop the entries of each row below ``fraction`` of the row's largest, in place.

    The kept entries of a row are scaled so that its sum is unchanged: the row's sum is
    the ray's length through the basis (a constant field keeps its exact line integral).
    The entries a ray only grazes (a node just under one voxel from it) are the row's
    smallest (what the default ``tomography.prune`` drops and gains: docs/tuning.md,
    "Projection pruning").

    Parameters
    ----------
    S : scipy.sparse.csr_matrix
        Float32 data; its arrays are compacted in place and returned as a new matrix.
    fraction : float
        In [0, 1).

    Returns
    -------
    scipy.sparse.csr_matrix
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"fraction must be in [0, 1), not {fraction}")
    indptr = np.asarray(S.indptr, dtype=np.int64).copy()
    nnz = _prune_kernel(indptr, S.indices, S.data, np.float64(fraction))
    if nnz < np.iinfo(np.int32).max:
        indptr = indptr.astype(np.int32)
    return csr_view(S.data[:nnz], S.indices[:nnz], indptr, S.shape)


def csr_view(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, shape) -> sp.csr_matrix:
    """A CSR matrix on exactly these arrays (no copy), after scipy's O(1) format checks.

    scipy's constructor copies ``data`` and ``indices`` when they view less than half of
    their buffer (``_prune_array``), which pruning a projection built into
    :func:`large_empty`'s bounded buffers just crosses, and the copy into fresh pages cost a
    sizeable share of the geometry task (docs/tuning.md, "Speed"). The buffer's
    unused tail stays mapped while the matrix lives (the geometry task saves it and lets
    it go). Checked here: the arrays' lengths against ``shape`` and ``indptr``'s ends.
    """
    m, n = (int(v) for v in shape)
    if not (data.ndim == indices.ndim == indptr.ndim == 1 and len(indptr) == m + 1
            and len(data) == len(indices) and indptr[0] == 0 and indptr[-1] == len(data)):
        raise ValueError(f"not a CSR matrix of shape {(m, n)}: {len(data)} entries, "
                         f"{len(indices)} indices, {len(indptr)} row pointers ending at {indptr[-1]}")
    S = sp.csr_matrix((m, n), dtype=data.dtype)
    # not check_format(): its prune() would make the same copy
    S.data, S.indices, S.indptr = data, indices, indptr
    return S
