"""The result store of one run: :class:`ResultStore` (SPEC section 2).

Opening a store, access to its arrays and attributes, aligned whole-chunk reads and
writes (the three write paths in :mod:`.writes`), and the coordinator's attribute updates.
Creating the template (:mod:`.template`), completion markers (:mod:`.markers`), chunk
listings for the integrity scans (:mod:`.chunks`) and retention (:mod:`.retention`) are
mixed in from their own modules.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import logging
import os
import warnings
from typing import Any, Mapping, Self

import numpy as np
import zarr

from schlieren.storage import location
from schlieren.storage.chunkio import ChunkLayout, CorruptChunk, chunk_layout, chunk_of
from schlieren.storage.errors import StoreError
from schlieren.storage.integrity import CheckedStore, chunk_error, covering_stage, marker_index, missing_reason
from schlieren.storage.layout import MARKER_GROUP, STORE_FORMAT, assert_aligned, normalize_region
from schlieren.storage.remote import RemoteChunks
from schlieren.storage.store.attrs import JSON_ATTRS, decode_attrs, encode_attrs, now, to_json
from schlieren.storage.store.chunks import ChunksMixin
from schlieren.storage.store.group import open_group, store_location
from schlieren.storage.store.markers import MarkersMixin
from schlieren.storage.store.retention import RetentionMixin
from schlieren.storage.store.template import TemplateMixin
from schlieren.storage.store.writes import (
    ObjectPuts,
    fit_to_region,
    write_chunk_file,
    write_through_zarr,
    write_to_object_store,
)

log = logging.getLogger(__name__)


class ResultStore(TemplateMixin, MarkersMixin, ChunksMixin, RetentionMixin):
    """A run's Zarr v3 group: template creation, aligned writes, completion markers.

    Use :meth:`create` (coordinator) or :meth:`open` (tasks, readers); do not call the
    constructor directly.
    """

    def __init__(self, group: zarr.Group, location_: str, store_arg: Any, mode: str):
        self._group = group
        self._location = location_
        self._store_arg = store_arg
        self._mode = mode
        self._arrays: dict[str, zarr.Array] = {}
        self._layouts: dict[str, ChunkLayout | None] = {}
        self._puts = ObjectPuts(location_)  # object stores: whole chunks as one PUT each
        self._markers_listed: dict[str, set[tuple[int, ...]]] = {}  # object stores: see is_done
        # object stores: chunk cache and background writes (storage/remote.py)
        self._remote = RemoteChunks(write_behind=False) \
            if isinstance(store_arg, str) and location.is_url(location_) else None
        info = decode_attrs(group.attrs).get("integrity")
        self._integrity: dict | None = info if isinstance(info, dict) else None

    @classmethod
    def open(cls, path, *, mode: str = "r+", write_behind: bool = False) -> Self:
        """Open an existing store (``mode="r"`` read-only, ``"r+"`` for task writes).

        ``write_behind`` (object stores only, for the tasks' store): chunk writes go out in
        the background until :meth:`flush` or the next :meth:`mark_done`
        (storage/remote.py). Folder stores write at once either way.
        """
        loc = store_location(path)
        if mode not in ("r", "r+"):
            raise ValueError(f"mode must be 'r' or 'r+', got {mode!r}")
        try:
            group = open_group(path, mode=mode, zarr_format=3)
        except (FileNotFoundError, zarr.errors.GroupNotFoundError, zarr.errors.NodeTypeValidationError):
            raise StoreError("no result store at this path", file=loc) from None
        except (ValueError, OSError, json.JSONDecodeError) as exc:
            raise StoreError(f"cannot open the result store ({exc})", file=loc) from None
        if group.attrs.get("format") != STORE_FORMAT:
            raise StoreError(f"not a {STORE_FORMAT} store (format {group.attrs.get('format')!r})", file=loc,
                             field="format")
        store = cls(group, loc, path, mode)
        if store._remote is not None:
            store._prefetch(store._members())
            store._remote.write_behind = write_behind and mode == "r+"
        return store

    def _members(self) -> dict[str, Any]:
        """Every array and group below the root by path (zarr fetches their metadata concurrently)."""
        with warnings.catch_warnings():  # the geometry cache folder beside the arrays
            warnings.filterwarnings("ignore", message=".*not recognized as a component of a Zarr hierarchy")
            return dict(self._group.members(max_depth=None))

    def _prefetch(self, members: Mapping[str, Any]) -> None:
        """Keep the arrays of ``members`` (:meth:`_members`: one concurrent fetch of every
        array's metadata; in an object store, instead of two requests per array on first use)."""
        arrays = {k: v for k, v in members.items() if isinstance(v, zarr.Array)}
        self._arrays.update((k, self._configured(k, v)) for k, v in arrays.items())
        store = self._group.store
        if isinstance(store, CheckedStore):  # its chunk checks need the same metadata: no refetch
            store.seed({k: v.metadata.to_dict() for k, v in arrays.items()}, dict(self._group.attrs))

    def _configured(self, name: str, arr: zarr.Array) -> zarr.Array:
        """Data arrays of a checksummed store store fill-valued chunks too: a set marker then
        means every chunk of its task has a file (markers keep zarr's default)."""
        if self._integrity is not None and not name.startswith(f"{MARKER_GROUP}/"):
            return arr.with_config({"write_empty_chunks": True})
        return arr

    @property
    def integrity(self) -> dict | None:
        """The ``integrity`` root attribute (None for a store of an older version)."""
        return self._integrity

    @property
    def remote(self) -> bool:
        """Is the store on object storage (an fsspec URL)?"""
        return self._remote is not None

    def __reduce__(self):
        if isinstance(self._store_arg, (str, os.PathLike)):
            return (_reopen, (os.fspath(self._store_arg), self._mode))
        raise TypeError("a ResultStore on an in-memory store cannot be pickled; open it by path")

    # -- access ---------------------------------------------------------------------
    @property
    def path(self) -> str:
        """The store's location (folder path, or the store type for in-memory stores)."""
        return self._location

    @property
    def group(self) -> zarr.Group:
        return self._group

    @property
    def attrs(self) -> dict:
        """Root attributes (a fresh copy), nested ones parsed from their JSON text."""
        return decode_attrs(self._group.attrs)

    def array(self, name: str) -> zarr.Array:
        """The zarr array ``name`` (``flow``, ``status/tomography``), cached."""
        arr = self._arrays.get(name)
        if arr is None:
            try:
                arr = self._group[name]
            except KeyError:
                raise StoreError("no such array in the store", file=self._location, field=name) from None
            if not isinstance(arr, zarr.Array):
                raise StoreError("is a group, not an array", file=self._location, field=name)
            arr = self._arrays[name] = self._configured(name, arr)
        return arr

    def _chunk_files(self, name: str) -> ChunkLayout | None:
        """Direct chunk-file access to ``name`` (storage/chunkio.py), or None to use zarr."""
        try:
            return self._layouts[name]
        except KeyError:
            pass
        root = self._location if isinstance(self._store_arg, (str, os.PathLike)) \
            and not location.is_url(self._location) else None
        lay = self._layouts[name] = chunk_layout(self.array(name), root, name)
        return lay

    def __contains__(self, name: str) -> bool:
        try:
            self.array(name)
        except StoreError:
            return False
        return True

    def array_names(self) -> list[str]:
        """Names of the data and coordinate arrays at the root (markers excluded)."""
        return sorted(name for name, _ in self._group.arrays())

    def dims(self, name: str) -> tuple[str, ...]:
        return tuple(self.array(name).metadata.dimension_names or ())

    # -- data -----------------------------------------------------------------------
    def write(self, name: str, index, data) -> None:
        """Write whole chunks of array ``name`` at ``index``.

        Parameters
        ----------
        name : str
        index : int, slice or tuple of them
            Ints pick single positions (e.g. ``(camera, frame)``), trailing dimensions
            are whole; the region must be a union of whole chunks.
        data : array_like
            Shape of the region, or of the region without the int-indexed dimensions
            (so ``write("flow", (c, f), flow_hw2)`` works). Cast to the array's dtype.

        Raises
        ------
        AlignmentError
            For a region that would cut a chunk.
        ValueError
            For data of the wrong shape.
        """
        if self._mode == "r":
            raise StoreError("the store is open read-only", file=self._location, field=name)
        arr = self.array(name)
        region = assert_aligned(index, arr)
        a = fit_to_region(name, index, region, data)
        lay = self._chunk_files(name)
        coords = lay.chunk_of(region) if lay is not None else None
        if coords is not None:  # one whole chunk: write its file directly (same bytes as zarr)
            write_chunk_file(lay, coords, a, arr.dtype)
        elif self._remote is not None:
            a = a.astype(arr.dtype, copy=False)
            write_to_object_store(self._remote, self._puts, arr, name, index, region, a)
        else:
            write_through_zarr(arr, region, a.astype(arr.dtype, copy=False))

    def read(self, name: str, index=()) -> np.ndarray:
        """Read ``array[index]`` (numpy indexing semantics: int entries drop their axis)."""
        arr = self.array(name)
        if index is Ellipsis:
            index = ()
        if not isinstance(index, tuple):
            index = (index,)
        lay = self._chunk_files(name)
        if lay is not None and all(isinstance(i, (int, np.integer)) and not isinstance(i, bool)
                                   for i in index):
            try:
                region = normalize_region(index, arr.shape)
            except IndexError:
                region = None
            coords = lay.chunk_of(region) if region is not None else None
            if coords is not None:  # exactly one whole chunk: read its file directly
                a = self._load_chunk(name, lay, coords)
                shape = tuple(s.stop - s.start for s in region)
                if a is None:
                    a = np.full(shape, lay.fill_value, dtype=lay.dtype.newbyteorder("="))
                else:
                    a = a[tuple(slice(0, n) for n in shape)].astype(lay.dtype.newbyteorder("="), copy=True)
                return a.reshape(a.shape[len(index):])
        if self._remote is not None:
            a = self._written(name, index)
            if a is not None:  # written by this process: no request
                return a
            self._remote.barrier()  # what this process sent is stored before it is read back
        if index == ():
            return np.asarray(arr[...])
        return np.asarray(arr[index])

    def _written(self, name: str, index: tuple) -> np.ndarray | None:
        """Object stores: ``array[index]`` if it is one whole chunk this process wrote, else None."""
        if not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in index):
            return None
        arr = self.array(name)
        try:
            coords = chunk_of(normalize_region(index, arr.shape), tuple(arr.chunks), tuple(arr.shape))
        except IndexError:
            return None
        a = self._remote.get((name, coords)) if coords is not None else None
        return None if a is None else a.reshape(a.shape[len(index):])

    def read_many(self, name: str, indices: list) -> list[np.ndarray]:
        """``[self.read(name, i) for i in indices]``; from an object store the chunks not in
        this process's memory are requested together instead of one after another."""
        if self._remote is None:
            return [self.read(name, i) for i in indices]
        out = [self._written(name, i if isinstance(i, tuple) else (i,)) for i in indices]
        missing = [j for j, a in enumerate(out) if a is None]
        if len(missing) > 1:
            self._remote.barrier()  # what this process sent is stored before it is read back
            got = self._remote.read_all(functools.partial(self.read, name), [indices[j] for j in missing])
        else:
            got = [self.read(name, indices[j]) for j in missing]
        for j, a in zip(missing, got):
            out[j] = a
        return out

    def _load_chunk(self, name: str, lay: ChunkLayout, coords) -> np.ndarray | None:
        """The stored chunk (None if it has no file and need not have one); ChunkError if
        it is corrupt or lost under a set marker."""
        try:
            a = lay.load(coords)
        except CorruptChunk as exc:
            raise chunk_error(self._location, name, coords, exc.reason) from None
        if a is None:
            why = self._required(name, coords)
            if why is not None:
                raise self._not_kept(name, coords) or chunk_error(self._location, name, coords, why)
        return a

    def _required(self, name: str, coords) -> str | None:
        """Why the chunk ``name[coords]`` must have a file, or None if it need not."""
        stage = covering_stage(self._integrity, name)
        if stage in (None, "template"):
            return None if stage is None else missing_reason(stage)
        done = self._marker_set(stage, self.marker_position(name, stage, coords))  # ChunkError if corrupt
        return missing_reason(stage) if done else None

    def marker_position(self, name: str, stage: str, coords) -> tuple[int, ...]:
        """Position in ``status/<stage>`` of the chunk at grid ``coords`` of array ``name``."""
        arr = self.array(name)
        return marker_index(self.dims(name), arr.chunks, self.marker_dims(stage), coords)

    def marker_dims(self, stage: str) -> tuple[str, ...]:
        m = self._marker(stage)
        return tuple(m.metadata.dimension_names or ()) if m.shape else ()

    # -- coordinator-only attribute updates -----------------------------------------------
    def set_stage_completed(self, stage: str, timestamp: str | _dt.datetime | None = None) -> None:
        """Record in the root attrs (``stages_completed``) when ``stage`` completed.

        Only the coordinator calls this (concurrent metadata writes are unsafe in zarr 3).
        """
        ts = timestamp.isoformat() if isinstance(timestamp, _dt.datetime) else (timestamp or now())
        done = dict(self.attrs.get("stages_completed", {}))
        done[stage] = ts
        self.update_attrs({"stages_completed": done})

    def update_attrs(self, values: Mapping[str, Any]) -> None:
        """Merge ``values`` into the root attrs (coordinator only) and re-consolidate the metadata.

        Nested values are stored as JSON text (netCDF-compatible, see :func:`decode_attrs`).
        """
        values = to_json(dict(values))
        if "format" in values and values["format"] != STORE_FORMAT:
            raise ValueError("the store format attribute cannot be changed")
        encoded = set(str(self._group.attrs.get(JSON_ATTRS, "") or "").split())
        self._group.attrs.update(encode_attrs(values, encoded))
        self._consolidate()

    def _consolidate(self) -> None:
        """Write the consolidated metadata (one read opens the store: xarray's default).

        Only the coordinator calls this, after the template and after attribute updates;
        tasks write chunks only, which leaves the metadata unchanged.
        """
        if self._remote is not None and self._group.metadata.consolidated_metadata is not None:
            # an object store: the arrays' metadata never changes after the template, and an
            # attribute update keeps the root's consolidated copy; re-consolidating would
            # read every array's metadata again (some 45 requests)
            return
        import warnings

        with warnings.catch_warnings():
            # "consolidated metadata is not part of the Zarr v3 specification": xarray, zarr-python
            # and the other main readers use it; readers without it read the metadata files
            warnings.simplefilter("ignore", category=UserWarning)
            zarr.consolidate_metadata(self._group.store, zarr_format=3)

    def __repr__(self) -> str:
        return f"ResultStore({self._location!r}, mode={self._mode!r})"


def remove_store(path: str | os.PathLike) -> None:
    """Delete a result store folder (``--overwrite``), and its cache; refuses anything else.

    Raises
    ------
    StoreError
        The path is not a folder holding a ``schlieren-store/1`` group.
    """
    import shutil

    from schlieren.storage.arrays_cache import remove_cache

    loc = location.normalize(path)
    if not location.exists(loc):
        return
    ResultStore.open(loc, mode="r")  # a StoreError unless it is one of our stores: never delete anything else
    remove_cache(loc)
    if location.is_url(loc):
        location.remove_tree(loc)
        return
    shutil.rmtree(loc)


def _reopen(path: str, mode: str) -> ResultStore:
    return ResultStore.open(path, mode=mode)
