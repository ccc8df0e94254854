"""The three ways a task's chunk reaches the store, behind :meth:`ResultStore.write`.

1. **Folder store, one whole chunk** (:func:`write_chunk_file`): the chunk file is written
   directly (storage/chunkio.py: the same bytes zarr writes, renamed into place), in the
   calling thread.
2. **Object storage** (:func:`write_to_object_store`): through the store's
   :class:`~schlieren.storage.remote.RemoteChunks` (kept in memory for reads, sent at once
   or in the background); a whole chunk is encoded here and sent as one PUT of its bytes
   (:class:`ObjectPuts`), anything else through zarr.
3. **Zarr** (:func:`write_through_zarr`): a region of several chunks, an array whose codecs
   the fast paths do not handle, or a store object (``MemoryStore``).

Every path writes only regions that :func:`~schlieren.storage.layout.assert_aligned`
accepted: whole chunks, never part of one.
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np
import zarr

from schlieren.storage import location
from schlieren.storage.chunkio import ChunkLayout, chunk_encoding, chunk_of
from schlieren.storage.remote import RemoteChunks


def fit_to_region(name: str, index, region: tuple[slice, ...], data) -> np.ndarray:
    """``data`` shaped as ``region``: given with that shape, or without the int-indexed
    dimensions of ``index`` (so ``write("flow", (c, f), flow_hw2)`` works)."""
    full = tuple(s.stop - s.start for s in region)
    idx = index if isinstance(index, tuple) else (index,)
    squeezed = tuple(n for k, n in enumerate(full)
                     if not (k < len(idx) and not isinstance(idx[k], slice)))
    a = np.asarray(data)
    if a.shape == squeezed and squeezed != full:
        a = a.reshape(full)
    elif a.shape != full:
        raise ValueError(f"{name}: data of shape {a.shape} does not fit the region of shape {full} "
                         f"(or {squeezed} without the indexed dimensions)")
    return a


def write_chunk_file(lay: ChunkLayout, coords: tuple[int, ...], a: np.ndarray, dtype) -> None:
    """Path 1: one whole chunk of a folder store, written as its file (same bytes as zarr)."""
    lay.write(coords, a.astype(dtype, copy=False))


def write_to_object_store(remote: RemoteChunks, puts: "ObjectPuts", arr: zarr.Array, name: str, index,
                          region: tuple[slice, ...], a: np.ndarray) -> None:
    """Path 2: object storage. A whole chunk is kept for reads in this process and sent as
    one PUT of its encoded bytes (or through zarr if :class:`ObjectPuts` cannot encode it);
    a region of several chunks goes through zarr and drops what was kept of the array."""
    coords = chunk_of(region, tuple(arr.chunks), tuple(arr.shape))
    if coords is None:
        remote.forget(lambda key: key[0] == name)
    send = puts.call(arr, name, coords, a) if coords is not None else None
    remote.put(None if coords is None else (name, coords), a,
               send or functools.partial(arr.__setitem__, region, a), f"{name} at {index}")


def write_through_zarr(arr: zarr.Array, region: tuple[slice, ...], a: np.ndarray) -> None:
    """Path 3: zarr writes the region (several chunks, other codecs, store objects)."""
    arr[region] = a


class ObjectPuts:
    """Whole chunks of a store on object storage sent as one PUT of their encoded bytes.

    The bytes are encoded here, in the calling thread, exactly as zarr encodes them
    (storage/chunkio.py; the tests compare object and folder stores byte for byte), and
    the call is one PUT of them. zarr's own path adds a hop to its event loop and its codec
    pipeline to every chunk: a sixth of the PUTs' client CPU in a profile of the tests'
    tiny session, whose run is mostly small chunks.
    """

    def __init__(self, loc: str):
        self._location = loc
        self._encodings: dict[str, ChunkLayout | None] = {}
        self._fs = None  # (fsspec filesystem, root path), on first use

    def call(self, arr: zarr.Array, name: str, coords: tuple[int, ...] | None,
             data: np.ndarray) -> Callable[[], None] | None:
        """A call storing ``data`` as the whole chunk ``name[coords]``, or None (zarr writes
        it: a region of several chunks, another codec, a fill-valued chunk that zarr
        deletes instead)."""
        if name not in self._encodings:
            self._encodings[name] = chunk_encoding(arr, name)
        enc = self._encodings[name]
        blob = enc.encode(data) if enc is not None else None
        if blob is None:
            return None
        if self._fs is None:
            self._fs = location.filesystem(self._location)
        fs, root = self._fs
        return functools.partial(fs.pipe_file, f"{root.rstrip('/')}/{enc.key(coords)}", blob)
