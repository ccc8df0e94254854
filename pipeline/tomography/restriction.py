"""The projection restricted to a frame's basis functions and the rays that hit them.

The products are numba kernels on plain arrays
(:mod:`~schlieren.pipeline.tomography._restriction_kernels`); :class:`RestrictedOperator`
wraps the per-frame restriction (hull basis functions x rays that hit them) with fused
three-column forward and adjoint products (one pass over the matrix for the three gradient
components: scipy's ``S @ X`` with three columns costs about five single SpMVs).

Determinism: the adjoint products accumulate into per-chunk partial sums over a *fixed*
partition of the rows into :data:`ADJOINT_CHUNKS` contiguous blocks (each block is summed
serially in row order, the blocks are then added in block order), so every product is
bit-identical for any number of numba threads; the forward products are per row.
"""

from __future__ import annotations

import threading

import numba as nb
import numpy as np
import scipy.sparse as sp

from schlieren.pipeline.tomography._restriction_kernels import (
    _colsumsq,
    _count_kept,
    _live_rows,
    _matvec3_f32,
    _move3,
    _restrict_fill,
    _restrict_setup3,
    _rmatvec3,
    _scatter_blocks_f32_parallel,
    _scatter_blocks_f32_serial,
    _setup3_parallel,
    _setup3_serial,
    matvec3,
)
from schlieren.pipeline.tomography.projection import large_empty

__all__ = [
    "restrict_rows_cols",
    "restrict_with_setup",
    "RestrictedOperator",
    "SubsetOperator",
    "shared_restriction",
    "ADJOINT_CHUNKS",
    "SHARED_RESTRICTIONS",
]

#: Fixed number of row blocks of the adjoint accumulations (independent of the thread
#: count, so results do not depend on it; also the maximum useful number of threads).
ADJOINT_CHUNKS = 8

#: ``live`` argument of the row-skipping kernels that means "every row".
_ALL_ROWS = np.zeros(0, np.uint8)


def _restrict_count(indptr, indices, rows, colmap, counts):
    """``counts[k]`` = entries of row ``rows[k]`` whose column ``colmap`` keeps (>= 0)."""
    _count_kept(indptr, indices, rows, (np.asarray(colmap) >= 0).astype(np.uint8), counts)


def _restricted_layout(S: sp.csr_matrix, rows: np.ndarray, colmap: np.ndarray, reuse_buffers: bool,
                       allocate: bool = True):
    """Count pass of a restriction: the rows of ``rows`` with at least one kept column,
    their CSR row pointer and (unfilled) index and value arrays (this thread's scratch
    buffers with ``reuse_buffers``, see :func:`_scratch`; None without ``allocate``)."""
    counts = np.empty(len(rows), np.int64)
    _restrict_count(S.indptr, S.indices, rows, colmap, counts)
    keep = counts > 0
    rows_k = rows[keep]
    new_indptr = np.zeros(len(rows_k) + 1, np.int64)
    np.cumsum(counts[keep], out=new_indptr[1:])
    nnz = int(new_indptr[-1])
    if not allocate:
        return keep, rows_k, new_indptr, None, None
    if reuse_buffers:
        new_indices = _scratch("indices", nnz, np.int32)
        new_data = _scratch("data", nnz, np.float32)
    else:
        new_indices = np.empty(nnz, np.int32)
        new_data = np.empty(nnz, np.float32)
    return keep, rows_k, new_indptr, new_indices, new_data


def _fill(S: sp.csr_matrix, rows_k, colmap, indptr, indices, data, n: int, rhs=None, x=None, valid=None):
    """Fill a restriction laid out by :func:`_restricted_layout`; with ``rhs`` also run the
    solver's setup pass on each row while it is hot (:func:`_restrict_setup3`; ``x`` the warm
    start in the new numbering, ``valid`` (M,) bool rays left out of the products).
    Returns None, or ``(b, products)`` over the kept rows."""
    if rhs is None:
        _restrict_fill(S.indptr, S.indices, S.data, rows_k, colmap, indptr, indices, data)
        return None
    b = np.ascontiguousarray(rhs(rows_k), dtype=np.float64).reshape(len(rows_k), 3)
    with_x = x is not None
    xx = (np.ascontiguousarray(x, dtype=np.float32).reshape(n, 3) if with_x
          else np.zeros((0, 3), np.float32))
    prods = _restrict_setup3(S.indptr, S.indices, S.data, rows_k, colmap, indptr, indices, data,
                             b, xx, int(n), ADJOINT_CHUNKS, with_x,
                             _ALL_ROWS if valid is None else np.ascontiguousarray(valid, dtype=bool).view(np.uint8))
    return b, prods


def restrict_rows_cols(S: sp.csr_matrix, rows: np.ndarray, colmap: np.ndarray, *, reuse_buffers: bool = False):
    """Rows ``rows`` of ``S`` with columns renumbered by ``colmap`` (-1 = dropped).

    ``reuse_buffers``: write into this thread's scratch buffers (as
    :func:`restrict_with_setup`; valid until the next restriction in this thread).

    Returns
    -------
    indptr (int64), indices (int32), data (float32), keep : rows with at least one entry.
    The returned CSR arrays cover only the kept rows, ``rows[keep]``.
    """
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    colmap = np.ascontiguousarray(colmap, dtype=np.int32)
    keep, rows_k, new_indptr, new_indices, new_data = _restricted_layout(S, rows, colmap, reuse_buffers)
    _fill(S, rows_k, colmap, new_indptr, new_indices, new_data, 0)
    return new_indptr, new_indices, new_data, keep


_SCRATCH = threading.local()


def _scratch(name: str, size: int, dtype) -> np.ndarray:
    """A per-thread reusable buffer of at least ``size`` elements (grown when needed).

    The restricted matrix of a paper-scale frame is large: writing it into fresh memory
    every frame costs a page fault per 4 KiB. A buffer that has to grow comes from
    :func:`large_empty` (huge pages where granted) with 25 % headroom, as the shared
    restrictions' buffers do (:func:`shared_restriction`: a growing plume's next block
    would otherwise fault a fresh buffer; docs/tuning.md, "Speed").
    """
    buf = getattr(_SCRATCH, name, None)
    if buf is None or buf.size < size or buf.dtype != np.dtype(dtype):
        buf = None  # release the old buffer first
        setattr(_SCRATCH, name, None)
        buf = large_empty(max(size + size // 4, 1), dtype)
        setattr(_SCRATCH, name, buf)
    return buf[:size]


def restrict_with_setup(S: sp.csr_matrix, colmap: np.ndarray, n: int, rhs, x: np.ndarray | None = None,
                        *, reuse_buffers: bool = False, rows: np.ndarray | None = None,
                        valid: np.ndarray | None = None):
    """Restrict ``S`` (all rays, columns by ``colmap``) and run the solver's setup pass with it.

    Equivalent to ``RestrictedOperator.from_full(S, arange(M), colmap, n)`` followed by
    :meth:`RestrictedOperator.setup_products`, but the products are accumulated while
    each restricted row is written (one pass over the restricted matrix less).

    Parameters
    ----------
    S : scipy.sparse.csr_matrix, shape (M, N)
    colmap : ndarray, shape (N,) int
        New column of each old one (-1 = dropped).
    n : int
        Number of kept columns.
    rhs : callable
        ``rhs(rows) -> (len(rows), 3)`` right-hand side of the kept rays (flat indices).
    x : ndarray, shape (n, 3), optional
        Warm start for ``S^T S x``.
    reuse_buffers : bool
        Write the restricted matrix into this thread's scratch buffers instead of fresh
        memory. The returned operator is then only valid until the next call with
        ``reuse_buffers=True`` in the same thread.
    rows : ndarray of int, optional
        Candidate rays (default all); e.g. only those with a valid measurement.
    valid : ndarray of bool, shape (M,), optional
        Rays kept in the operator but left out of the products (their ``rhs`` is not used).

    Returns
    -------
    op : RestrictedOperator
    b : ndarray, shape (op.m, 3)
        ``rhs(op.rows)``.
    products : tuple
        ``(diag(S^T S), S^T b, S^T S x)`` as from :meth:`RestrictedOperator.setup_products`.
    """
    rows = np.arange(S.shape[0], dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
    colmap = np.ascontiguousarray(colmap, dtype=np.int32)
    _, rows_k, new_indptr, new_indices, new_data = _restricted_layout(S, rows, colmap, reuse_buffers)
    b, prods = _fill(S, rows_k, colmap, new_indptr, new_indices, new_data, n, rhs, x, valid)
    return RestrictedOperator(new_indptr, new_indices, new_data, n, rows_k), b, prods


def _normal3(indptr, indices, data, x, n, nchunks):
    """``S^T S x`` for three columns in one pass over ``S`` (each row read once).

    ``x`` is float32 (n, 3); the row products and the per-block partial sums are float32
    (the matrix itself is float32, so this keeps about 6 significant digits, far below
    the solver's tolerance) and the blocks are summed in float64: the product is bound by
    its multiply-add chain, which float32 shortens (docs/tuning.md, "Speed").
    """
    return _scatter_blocks_f32(indptr, indices, data, x, x, n, nchunks, True, _ALL_ROWS)


def _scatter_blocks_f32(indptr, indices, data, x, y, n, nchunks, fused, live):
    """``S^T t`` with float32 per-block sums, ``t_r = S_r x`` (``fused``, i.e. ``S^T S x``) or
    ``t_r = y_r``; the blocks are summed in float64 in block order. Rows with ``live[r] ==
    0`` are skipped (``live`` uint8; empty: every row).

    With several numba threads the blocks run in parallel, each into its own partial sums
    (``nchunks`` float32 copies of the result, summed at the end). On one thread (the
    workers, the serial executor) they run one after another into one reused buffer, each
    added to the result as it is done: the same sums in the same order (bit-identical), with
    a working set of one buffer instead of ``nchunks`` (docs/tuning.md, "Speed").
    """
    kernel = _scatter_blocks_f32_serial if nb.get_num_threads() == 1 else _scatter_blocks_f32_parallel
    return kernel(indptr, indices, data, x, y, n, nchunks, fused, live)


def _setup3(indptr, indices, data, b, x, n, nchunks, with_x, live):
    """``diag(S^T S)``, ``S^T b`` and (if ``with_x``) ``S^T S x`` in one pass over ``S``
    (rows with ``live[r] == 0`` skipped, as in :func:`_scatter_blocks_f32`; on one thread
    the blocks run one after another into one buffer, bit-identical, as there)."""
    kernel = _setup3_serial if nb.get_num_threads() == 1 else _setup3_parallel
    return kernel(indptr, indices, data, b, x, n, nchunks, with_x, live)


class RestrictedOperator:
    """The projection restricted to a set of basis functions and the rays that hit them.

    Applies to three columns at once (the three gradient components share ``S``,
    eq. 5). Shapes: ``matvec3`` maps (n, 3) -> (m, 3), ``rmatvec3`` (m, 3) -> (n, 3).

    Parameters
    ----------
    indptr, indices, data : CSR arrays of the restricted matrix (m rows, n columns).
    n : int
        Number of columns (basis functions).
    rows : ndarray, shape (m,)
        Indices of the kept rays in the full ray list.
    """

    def __init__(self, indptr, indices, data, n: int, rows: np.ndarray):
        self.indptr = indptr
        self.indices = indices
        self.data = data
        self.n = int(n)
        self.m = len(indptr) - 1
        self.rows = rows
        self._nchunks = ADJOINT_CHUNKS

    @classmethod
    def from_full(cls, S: sp.csr_matrix, rows: np.ndarray, colmap: np.ndarray, n: int):
        indptr, indices, data, keep = restrict_rows_cols(S, rows, colmap)
        return cls(indptr, indices, data, n, np.asarray(rows)[keep])

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1])

    @property
    def shape(self) -> tuple[int, int]:
        return self.m, self.n

    def matvec3(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(self.n, 3)
        y = np.empty((self.m, 3))
        matvec3(self.indptr, self.indices, self.data, x, y)
        return y

    def rmatvec3(self, y: np.ndarray) -> np.ndarray:
        y = np.ascontiguousarray(y, dtype=np.float64).reshape(self.m, 3)
        return _rmatvec3(self.indptr, self.indices, self.data, y, self.n, self._nchunks)

    def normal3(self, x: np.ndarray) -> np.ndarray:
        """``S^T S x`` for x of shape (n, 3) in a single pass over the matrix."""
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(self.n, 3)
        return _normal3(self.indptr, self.indices, self.data, x, self.n, self._nchunks)

    def matvec3_f32(self, x: np.ndarray) -> np.ndarray:
        """``S x`` in float32 (as the normal product's row sums), shape (m, 3) float32."""
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(self.n, 3)
        y = np.empty((self.m, 3), np.float32)
        _matvec3_f32(self.indptr, self.indices, self.data, x, y)
        return y

    def rmatvec3_f32(self, y: np.ndarray) -> np.ndarray:
        """``S^T y`` with float32 partial sums (as the normal product), float64 (n, 3)."""
        y = np.ascontiguousarray(y, dtype=np.float32).reshape(self.m, 3)
        return _scatter_blocks_f32(self.indptr, self.indices, self.data, y, y, self.n, self._nchunks, False,
                                   _ALL_ROWS)

    def column_sumsq(self) -> np.ndarray:
        """``diag(S^T S)``, shape (n,)."""
        return _colsumsq(self.indices, self.data, self.n, self._nchunks)

    def setup_products(self, b: np.ndarray, x: np.ndarray | None = None):
        """``diag(S^T S)``, ``S^T b`` and ``S^T S x`` in a single pass over the matrix.

        Parameters
        ----------
        b : ndarray, shape (m, 3)
        x : ndarray, shape (n, 3), optional
            Without it the third output is zero.

        Returns
        -------
        colsumsq : ndarray, shape (n,)
        Stb, StSx : ndarray, shape (n, 3)
        """
        b = np.ascontiguousarray(b, dtype=np.float64).reshape(self.m, 3)
        with_x = x is not None
        x = (np.ascontiguousarray(x, dtype=np.float32).reshape(self.n, 3) if with_x
             else np.zeros((0, 3), np.float32))
        return _setup3(self.indptr, self.indices, self.data, b, x, self.n, self._nchunks, with_x, _ALL_ROWS)

    def to_scipy(self) -> sp.csr_matrix:
        return sp.csr_matrix((self.data, self.indices, self.indptr), shape=(self.m, self.n))


#: Shared restrictions a thread keeps (:func:`shared_restriction`): two, because a Dask
#: worker holds its next task before the one it runs finishes, so the solves of two
#: warm-start blocks alternate on it.
SHARED_RESTRICTIONS = 2


def shared_restriction(S: sp.csr_matrix, support: np.ndarray, key, *, rhs=None, x: np.ndarray | None = None,
                       valid: np.ndarray | None = None):
    """``S`` restricted to the columns ``support`` marks and every ray that hits them, kept
    by this thread for later calls with the same ``key`` (the :data:`SHARED_RESTRICTIONS`
    most recently used ones, each in its own buffers; an evicted one's buffers are reused).

    The frames of a warm-start block differ little (docs/tuning.md, "Speed"), so their
    systems are restricted once to the block's union and then
    selected inside it (:class:`SubsetOperator`); the restriction is deterministic, so a
    thread that has not seen the block builds the same operator.

    Parameters
    ----------
    S : scipy.sparse.csr_matrix, shape (M, N)
    support : ndarray, shape (N,) bool
    key : hashable
        Identifies ``(S, support)`` (e.g. the geometry's content hash and a digest of the
        support).
    rhs, x, valid : optional
        When the restriction is built by this call and ``rhs`` is given, the setup products
        of :func:`restrict_with_setup` (``x`` in the support's numbering, rays ``valid``)
        are accumulated while it is written.

    Returns
    -------
    op : RestrictedOperator
    fused : tuple or None
        ``(b, products)`` over all of ``op``'s rows when the products were computed (None
        when ``op`` was kept from an earlier call).
    """
    held = getattr(_SCRATCH, "shared", None)
    if held is None:
        held = _SCRATCH.shared = []  # [(key, op, indices buffer, data buffer)], most recent last
    for i, entry in enumerate(held):
        if entry[0] == key:
            held.append(held.pop(i))
            return entry[1], None
    flat = np.asarray(support, dtype=bool).ravel()
    if flat.size != S.shape[1]:
        raise ValueError(f"support has {flat.size} voxels, the projection {S.shape[1]} columns")
    n = int(flat.sum())
    colmap = np.full(flat.size, -1, np.int32)
    colmap[flat] = np.arange(n, dtype=np.int32)
    spare = held.pop(0)[2:] if len(held) >= SHARED_RESTRICTIONS else None
    rows = np.arange(S.shape[0], dtype=np.int64)
    _, rows_k, indptr, _, _ = _restricted_layout(S, rows, colmap, False, allocate=False)
    nnz = int(indptr[-1])
    bufs = []
    for j, dtype in enumerate((np.int32, np.float32)):
        old = spare[j] if spare is not None else None
        bufs.append(old if old is not None and old.size >= nnz else large_empty(max(nnz + nnz // 4, 1), dtype))
    del spare
    indices, data = bufs[0][:nnz], bufs[1][:nnz]
    fused = _fill(S, rows_k, colmap, indptr, indices, data, n, rhs, x, valid)
    op = RestrictedOperator(indptr, indices, data, n, rows_k)
    held.append((key, op, bufs[0], bufs[1]))
    return op, fused


class SubsetOperator:
    """A frame's system inside a shared restriction (:func:`shared_restriction`).

    The columns ``sel`` of ``base`` and the rows ``live`` marks: those with a valid
    measurement that hit at least one of the columns (the rows :meth:`RestrictedOperator.
    from_full` would keep). Products equal those of the frame's own restriction: the
    other columns are held at zero and the other rows skipped; a product costs a pass over
    ``base`` (``nnz`` is its size).

    Parameters
    ----------
    base : RestrictedOperator
    sel : ndarray of int, shape (n,)
        The frame's columns in ``base``'s numbering, increasing.
    valid : ndarray of bool, shape (base.m,), optional
        Rows with a valid measurement (default all).
    """

    def __init__(self, base: RestrictedOperator, sel: np.ndarray, valid: np.ndarray | None = None):
        self.base = base
        self.sel = np.ascontiguousarray(sel, dtype=np.int64)
        keep = np.zeros(base.n, np.uint8)
        keep[self.sel] = 1
        valid = (np.ones(base.m, np.uint8) if valid is None
                 else np.ascontiguousarray(valid, dtype=bool).view(np.uint8))
        self.live = np.empty(base.m, np.uint8)
        _live_rows(base.indptr, base.indices, keep, valid, self.live)
        self._live_idx = np.flatnonzero(self.live)
        self.rows = base.rows[self._live_idx]
        self.n = len(self.sel)
        self.m = len(self.rows)
        self._nchunks = base._nchunks
        self._xe: np.ndarray | None = None  # _embed's buffer

    @property
    def nnz(self) -> int:
        return self.base.nnz

    def _embed(self, x: np.ndarray) -> np.ndarray:
        """``x`` (n, 3) on the base's columns, float32, zero off ``sel``: one buffer per
        operator, rewritten in place at ``sel`` only (its other entries stay zero), valid until
        the next call (each product uses it at once)."""
        out = self._xe
        if out is None:
            out = self._xe = np.zeros((self.base.n, 3), np.float32)
        _move3(np.ascontiguousarray(x).reshape(self.n, 3), out, self.sel, True)
        return out

    def _restrict(self, full: np.ndarray) -> np.ndarray:
        """The ``sel`` rows of a (base.n, 3) product."""
        out = np.empty((self.n, 3), full.dtype)
        _move3(full, out, self.sel, False)
        return out

    def normal3(self, x: np.ndarray) -> np.ndarray:
        """``S^T S x`` of the frame's system (x of shape (n, 3))."""
        b = self.base
        xe = self._embed(x)
        return self._restrict(_scatter_blocks_f32(b.indptr, b.indices, b.data, xe, xe, b.n, self._nchunks, True,
                                                  self.live))

    def setup_products(self, b: np.ndarray, x: np.ndarray | None = None):
        """As :meth:`RestrictedOperator.setup_products`, ``b`` over the frame's rows (m, 3)."""
        base = self.base
        bb = np.zeros((base.m, 3))
        bb[self._live_idx] = np.asarray(b, dtype=np.float64).reshape(self.m, 3)
        with_x = x is not None
        xx = self._embed(x) if with_x else np.zeros((0, 3), np.float32)
        d, sb, sx = _setup3(base.indptr, base.indices, base.data, bb, xx, base.n, self._nchunks, with_x, self.live)
        return d[self.sel], self._restrict(sb), self._restrict(sx)
