"""Direct whole-chunk file I/O for the result store's Zarr v3 arrays (folder stores).

Every task reads and writes single whole chunks (one camera-frame flow field, one frame's
volume, one completion marker). Through zarr's API each such access is scheduled on
zarr's I/O event-loop thread and waited for, which costs more than the access itself,
most in a busy Dask worker, whose own event loop competes for the GIL, and a run makes
thousands of them (docs/tuning.md, "Chunk I/O and object storage"). This module encodes and decodes exactly
what zarr does for the arrays the store creates, in the calling thread:

* the chunk file is ``<array>/c/<i>/<j>/...`` (default chunk key encoding, ``/``);
* its bytes are the chunk in C order, little endian (``bytes`` codec), compressed by
  ``zstd`` at the array's level without checksum (numcodecs, which zarr itself calls),
  then followed by the CRC-32C of those compressed bytes as 4 little-endian bytes (zarr's
  ``crc32c`` codec, google-crc32c as in zarr) in arrays that have it: every store this
  version creates; stores of older versions have no checksum and are still read;
* a chunk equal to the fill value everywhere is stored only if the array is opened with
  ``write_empty_chunks=True`` (the result store's data arrays, so that a missing chunk
  under a set completion marker means "lost", never "empty"); otherwise, as zarr's
  default does, writing one removes the file and reading a missing file gives the fill
  value;
* a chunk that fails its checksum, does not decompress or has the wrong size raises
  :class:`CorruptChunk` (never data);
* a write goes to a temporary file in the same folder and is renamed over the chunk,
  so a reader (or a killed task) never sees half a chunk.

:func:`chunk_layout` returns ``None`` for any array outside that pattern (other codecs,
string dtypes, sharding, a non-folder store); the store then goes through zarr. The
tests check byte-identity with zarr's files both ways.

A store on object storage uses the same encoding (:func:`chunk_encoding`,
:meth:`ChunkLayout.encode` and :meth:`ChunkLayout.key`) to send a task's whole chunk as
one PUT of these bytes (storage/store/writes.py).
"""

from __future__ import annotations

import os
import struct
import uuid
from dataclasses import dataclass

import numpy as np

__all__ = ["ChunkLayout", "CorruptChunk", "chunk_layout", "chunk_encoding", "chunk_of", "add_checksum",
           "strip_checksum"]


class CorruptChunk(ValueError):
    """A chunk's bytes fail their checksum or do not decode (``reason`` says which)."""

    def __init__(self, reason: str, path: str | None = None):
        self.reason = reason
        self.path = path
        super().__init__(reason if path is None else f"{path}: {reason}")


def add_checksum(blob: bytes) -> bytes:
    """``blob`` followed by its CRC-32C, 4 bytes little endian (zarr's ``crc32c`` codec)."""
    import google_crc32c

    return blob + struct.pack("<I", google_crc32c.value(blob))


def strip_checksum(blob: bytes) -> bytes:
    """The bytes before the CRC-32C trailer, after checking it; :class:`CorruptChunk` if wrong."""
    import google_crc32c

    if len(blob) < 4:
        raise CorruptChunk(f"truncated: {len(blob)} bytes, shorter than its checksum")
    inner = blob[:-4]
    stored = struct.unpack("<I", blob[-4:])[0]
    if google_crc32c.value(inner) != stored:
        raise CorruptChunk("fails its CRC-32C checksum (flipped bytes or a truncated file)")
    return inner


@dataclass(frozen=True)
class ChunkLayout:
    """How one array's chunks are laid out as files."""

    root: str  # the array's folder ("" where only bytes and keys are used: object stores)
    shape: tuple[int, ...]
    chunks: tuple[int, ...]
    dtype: np.dtype  # little-endian storage dtype
    fill_value: object
    level: int  # zstd level
    checksum: bool = False  # a crc32c codec follows zstd
    write_empty: bool = False  # fill-value chunks are stored (write_empty_chunks=True)
    name: str = ""  # the array's path in the store

    def chunk_of(self, region: tuple[slice, ...]) -> tuple[int, ...] | None:
        """Grid coordinates of the single whole chunk ``region`` covers, or None."""
        return chunk_of(region, self.chunks, self.shape)

    def path(self, coords: tuple[int, ...]) -> str:
        if not coords:  # a 0-d array has the single chunk "c"
            return os.path.join(self.root, "c")
        return os.path.join(self.root, "c", *(str(i) for i in coords))

    def load(self, coords: tuple[int, ...]) -> np.ndarray | None:
        """The whole stored chunk at ``coords`` (full chunk shape, a read-only view), or
        None if it has no file. :class:`CorruptChunk` if its bytes do not decode."""
        path = self.path(coords)
        try:
            with open(path, "rb") as f:
                blob = f.read()
        except FileNotFoundError:
            return None
        return self.decode(blob, path)

    def decode(self, blob: bytes, path: str | None = None) -> np.ndarray:
        """A chunk's stored bytes as the full chunk (:class:`CorruptChunk` if they do not decode)."""
        from numcodecs import Zstd

        try:
            if self.checksum:
                blob = strip_checksum(blob)
            raw = Zstd().decode(blob)
        except CorruptChunk as exc:
            raise CorruptChunk(exc.reason, path) from None
        except Exception as exc:  # noqa: BLE001 - zstd raises RuntimeError and friends
            raise CorruptChunk(f"does not decompress ({type(exc).__name__}: {exc})", path) from None
        # zarr stores edge chunks at the full chunk shape (the padding holds the fill value)
        want = int(np.prod(self.chunks)) * self.dtype.itemsize
        if len(raw) != want:
            raise CorruptChunk(f"decodes to {len(raw)} bytes, not the chunk's {want}", path)
        return np.frombuffer(raw, dtype=self.dtype).reshape(self.chunks)

    def read(self, coords: tuple[int, ...], region_shape: tuple[int, ...]) -> np.ndarray:
        """The chunk at ``coords`` (its fill value if never written), cut to ``region_shape``."""
        a = self.load(coords)
        if a is None:
            return np.full(region_shape, self.fill_value, dtype=self.dtype.newbyteorder("="))
        if a.shape != tuple(region_shape):
            a = a[tuple(slice(0, n) for n in region_shape)]
        return a.astype(self.dtype.newbyteorder("="), copy=True)

    def encode(self, data: np.ndarray) -> bytes | None:
        """The stored bytes of a chunk holding ``data`` (the chunk's region, already of the
        array's dtype), or None if zarr stores no object for it (fill value everywhere,
        without ``write_empty``)."""
        from numcodecs import Zstd

        chunk = np.asarray(data, dtype=self.dtype)
        if chunk.shape != self.chunks:  # an edge chunk: pad with the fill value, as zarr does
            full = np.full(self.chunks, self.fill_value, dtype=self.dtype)
            full[tuple(slice(0, n) for n in chunk.shape)] = chunk
            chunk = full
        if not self.write_empty and _all_fill(chunk, self.fill_value):
            return None
        blob = Zstd(level=self.level).encode(np.ascontiguousarray(chunk).tobytes())
        return add_checksum(blob) if self.checksum else blob

    def key(self, coords: tuple[int, ...]) -> str:
        """The chunk's key below the store's root, ``/``-separated (``flow/c/0/3/0/0/0``)."""
        return "/".join([self.name, "c", *(str(i) for i in coords)])

    def write(self, coords: tuple[int, ...], data: np.ndarray) -> None:
        """Store ``data`` (the chunk's region, already of the array's dtype) as the chunk file."""
        path = self.path(coords)
        blob = self.encode(data)
        if blob is None:
            try:
                os.remove(path)
            except FileNotFoundError:
                pass
            return
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
    then ``zstd`` without its own checksum, optionally followed by ``crc32c``. Anything
    else returns None (use zarr).
    """
    if store_root is None:
        return None
    return _layout(arr, store_root, name)


def chunk_encoding(arr, name: str) -> ChunkLayout | None:
    """Like :func:`chunk_layout` for an array of any store (an object store's): only its
    :meth:`ChunkLayout.encode`, :meth:`~ChunkLayout.decode` and :meth:`~ChunkLayout.key`
    are meaningful (no folder)."""
    return _layout(arr, None, name)


def _layout(arr, store_root, name: str) -> ChunkLayout | None:
    try:
        from zarr.codecs import BytesCodec, Crc32cCodec, ZstdCodec
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
    checksum = len(codecs) == 3 and isinstance(codecs[2], Crc32cCodec)
    if len(codecs) != 2 + checksum or not isinstance(codecs[0], BytesCodec) \
            or not isinstance(codecs[1], ZstdCodec):
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
    if config is None or getattr(config, "order", "C") != "C":
        return None
    root = "" if store_root is None else os.path.join(os.fspath(store_root), *name.split("/"))
    return ChunkLayout(root=root, name=name,
                       shape=tuple(int(s) for s in arr.shape),
                       chunks=tuple(int(c) for c in meta.chunk_grid.chunk_shape),
                       dtype=dtype.newbyteorder("<"), fill_value=meta.fill_value,
                       level=int(codecs[1].level), checksum=checksum,
                       write_empty=bool(config.write_empty_chunks))
