"""Direct whole-chunk file I/O for the result store's Zarr v3 arrays (folder stores).

Every task reads and writes single whole chunks (one camera-frame flow field, one frame's
volume, one completion marker). Through zarr's API each such access is scheduled on
zarr's I/O event-loop thread and waited for: about 1 ms per access in one process, and
2-3 ms in a busy Dask worker, whose own event loop competes for the GIL. A run of 8
cameras x 16 frames makes some 3,000 of them. This module encodes and decodes exactly
what zarr does for the arrays the store creates, in the calling thread:

* the chunk file is ``<array>/c/<i>/<j>/...`` (default chunk key encoding, ``/``);
* its bytes are the chunk in C order, little endian (``bytes`` codec), compressed by
  ``zstd`` at the array's level without checksum (numcodecs, which zarr itself calls);
* a chunk equal to the fill value everywhere is not stored (zarr's default
  ``write_empty_chunks=False``): writing one removes the file, reading a missing file
  gives the fill value;
* a write goes to a temporary file in the same folder and is renamed over the chunk,
  so a reader (or a killed task) never sees half a chunk.

:func:`chunk_layout` returns ``None`` for any array outside that pattern (other codecs,
string dtypes, sharding, a non-folder store); the store then goes through zarr. The
tests check byte-identity with zarr's files both ways.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass

import numpy as np

__all__ = ["ChunkLayout", "chunk_layout", "chunk_of"]


@dataclass(frozen=True)
class ChunkLayout:
    """How one array's chunks are laid out as files."""

    root: str  # the array's folder
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dtype: np.dtype  # little-endian storage dtype
    fill_value: object
    level: int  # zstd level

    def chunk_of(self, region: tuple[slice, ...]) -> tuple[int, ...] | None:
        """Grid coordinates of the single whole chunk ``region`` covers, or None."""
        return chunk_of(region, self.chunks, self.shape)

    def path(self, coords: tuple[int, ...]) -> str:
        if not coords:  # a 0-d array has the single chunk "c"
            return os.path.join(self.root, "c")
        return os.path.join(self.root, "c", *(str(i) for i in coords))

    def read(self, coords: tuple[int, ...], region_shape: tuple[int, ...]) -> np.ndarray:
        """The chunk at ``coords`` (its fill value if never written), cut to ``region_shape``."""
        from numcodecs import Zstd

        try:
            with open(self.path(coords), "rb") as f:
                blob = f.read()
        except FileNotFoundError:
            return np.full(region_shape, self.fill_value, dtype=self.dtype.newbyteorder("="))
        raw = Zstd().decode(blob)
        # zarr stores edge chunks at the full chunk shape (the padding holds the fill value)
        a = np.frombuffer(raw, dtype=self.dtype).reshape(self.chunks)
        if a.shape != tuple(region_shape):
            a = a[tuple(slice(0, n) for n in region_shape)]
        return a.astype(self.dtype.newbyteorder("="), copy=True)

    def write(self, coords: tuple[int, ...], data: np.ndarray) -> None:
        """Store ``data`` (the chunk's region, already of the array's dtype) as the chunk file."""
        from numcodecs import Zstd

        path = self.path(coords)
        chunk = np.asarray(data, dtype=self.dtype)
        if chunk.shape != self.chunks:  # an edge chunk: pad with the fill value, as zarr does
            full = np.full(self.chunks, self.fill_value, dtype=self.dtype)
            full[tuple(slice(0, n) for n in chunk.shape)] = chunk
            chunk = full
        if _all_fill(chunk, self.fill_value):
            try:
                os.remove(path)
            except FileNotFoundError:
                pass
            return
        blob = Zstd(level=self.level).encode(np.ascontiguousarray(chunk).tobytes())
        folder = os.path.dirname(path)
        tmp = f"{path}.{uuid.uuid4().hex}.partial"
        try:
            f = open(tmp, "wb")
        except FileNotFoundError:
            os.makedirs(folder, exist_ok=True)
            f = open(tmp, "wb")
        try:
            with f:
                f.write(blob)
            os.replace(tmp, path)
        except BaseException:
            try:
                os.remove(tmp)
            except OSError:
                pass
            raise


def chunk_of(region: tuple[slice, ...], chunks: tuple[int, ...], shape: tuple[int, ...]) -> tuple[int, ...] | None:
    """Grid coordinates of the single whole chunk ``region`` covers (any store), or None."""
    if len(region) != len(chunks):
        return None
    out = []
    for sl, c, n in zip(region, chunks, shape):
        start, stop = sl.start, sl.stop
        if start % c or stop - start != min(c, n - start):
            return None
        out.append(start // c)
    return tuple(out)


def _all_fill(a: np.ndarray, fill) -> bool:
    """zarr's ``all_equal``: NaN equals NaN, and a float fill of 0 compares bit patterns."""
    if a.dtype.kind == "f" and fill == 0.0:
        return not a.view(f"V{a.dtype.itemsize}").tobytes().strip(b"\0")
    if a.dtype.kind in "fc":
        return bool(np.array_equal(a, np.broadcast_to(np.asarray(fill, a.dtype), a.shape), equal_nan=True))
    return bool(np.all(a == np.asarray(fill, a.dtype)))


def chunk_layout(arr, store_root: str | os.PathLike | None, name: str) -> ChunkLayout | None:
    """The :class:`ChunkLayout` of zarr array ``arr`` at ``<store_root>/<name>``, if eligible.

    Eligible: a folder store, a regular chunk grid, the default ``/`` chunk key encoding,
    no sharding, a numeric or bool dtype, and exactly the codecs ``bytes`` (little endian)
    then ``zstd`` without checksum. Anything else returns None (use zarr).
    """
    if store_root is None:
        return None
    try:
        from zarr.codecs import BytesCodec, ZstdCodec
        from zarr.core.chunk_grids import RegularChunkGrid
        from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding
    except ImportError:  # pragma: no cover - another zarr layout
        return None
    meta = arr.metadata
    if getattr(meta, "zarr_format", None) != 3:
        return None
    if not isinstance(meta.chunk_grid, RegularChunkGrid):
        return None
    enc = meta.chunk_key_encoding
    if not isinstance(enc, DefaultChunkKeyEncoding) or enc.separator != "/":
        return None
    codecs = tuple(meta.codecs)
    if len(codecs) != 2 or not isinstance(codecs[0], BytesCodec) or not isinstance(codecs[1], ZstdCodec):
        return None
    endian = getattr(codecs[0].endian, "value", codecs[0].endian)
    if endian not in (None, "little"):
        return None
    if codecs[1].checksum:
        return None
    try:
        dtype = np.dtype(arr.dtype)
    except TypeError:
        return None
    if dtype.kind not in "biuf" or dtype.hasobject:
        return None
    config = getattr(arr, "config", None)
    if getattr(config, "write_empty_chunks", True) or getattr(config, "order", "C") != "C":
        return None
    return ChunkLayout(root=os.path.join(os.fspath(store_root), *name.split("/")),
                       shape=tuple(int(s) for s in arr.shape),
                       chunks=tuple(int(c) for c in meta.chunk_grid.chunk_shape),
                       dtype=dtype.newbyteorder("<"), fill_value=meta.fill_value,
                       level=int(codecs[1].level))
