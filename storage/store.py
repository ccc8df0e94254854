"""The result store: one Zarr v3 group per run (SPEC section 2, docs/design.md).

The coordinator creates the group and every array up front
(:meth:`ResultStore.create`, the *template*); tasks then open the store by path, write
whole chunks (:meth:`ResultStore.write` refuses partial-chunk regions, which lose data
under concurrent writers) and set their completion marker last
(:meth:`ResultStore.mark_done`). Markers, not chunk presence, mean "done": a killed task
can leave some of its chunks written.

Integrity (``storage/integrity.py``): every array ends its codecs with ``crc32c``, the data
arrays store even fill-valued chunks (``write_empty_chunks=True``), and the root attribute
``integrity`` records which stage's marker covers each array. A read never returns a
chunk that fails its checksum or that is missing under a set marker: it raises
:class:`~schlieren.storage.errors.ChunkError` naming the array and the chunk. Stores of
older versions (no ``integrity``) are read without these checks and are not resumed.

An existing path is never overwritten or deleted: :meth:`create` on an existing store
resumes it only if its ``fingerprint`` attribute (a hash of session + configuration,
see :func:`fingerprint`) equals the caller's; anything else raises
:class:`~schlieren.storage.errors.StoreError` naming the path.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import hashlib
import itertools
import json
import logging
import math
import os
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from schlieren.storage import location
from schlieren.storage.chunkio import ChunkLayout, CorruptChunk, chunk_encoding, chunk_layout, chunk_of
from schlieren.storage.errors import ChunkError, StoreError
from schlieren.storage.integrity import (
    INTEGRITY_VERSION,
    check_coverage,
    CheckedStore,
    checked,
    chunk_error,
    covering_stage,
    marker_index,
    missing_reason,
)
from schlieren.storage.layout import STORE_FORMAT, ArraySpec, assert_aligned, normalize_region
from schlieren.storage.remote import RemoteChunks

__all__ = ["ResultStore", "fingerprint", "to_json", "decode_attrs", "JSON_ATTRS", "remove_store"]

log = logging.getLogger(__name__)

MARKER_GROUP = "status"
#: zstd, then zarr's CRC-32C of the compressed bytes (checked on every read)
_COMPRESSORS = (ZstdCodec(level=3), Crc32cCodec())


# --------------------------------------------------------------------------------------
# JSON helpers for attributes
# --------------------------------------------------------------------------------------
def to_json(obj: Any) -> Any:
    """Plain JSON data from numpy values, tuples, paths, dataclasses and datetimes.

    Non-finite floats become the strings ``"NaN"``, ``"Infinity"``, ``"-Infinity"``
    (JSON has no such numbers).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_json(obj.tolist())
    if isinstance(obj, np.generic):
        return to_json(obj.item())
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        return "NaN" if math.isnan(obj) else ("Infinity" if obj > 0 else "-Infinity")
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    raise TypeError(f"cannot store a {type(obj).__name__} in the store attributes")


#: Root attribute listing (space-separated) the root attributes stored as JSON text.
JSON_ATTRS = "json_attrs"


def _flat(v: Any) -> bool:
    """A value netCDF can hold as an attribute: a number, text, or a flat list of numbers."""
    if isinstance(v, (str, int, float)) or v is None:
        return True
    return isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)


def _encode_attrs(values: dict, encoded: set[str]) -> dict:
    """Nested values (mappings, lists of text or of mappings) and booleans as JSON text, so
    that the attributes survive ``xarray.Dataset.to_netcdf``; updates ``encoded``."""
    out = {}
    for k, v in values.items():
        if k == JSON_ATTRS:
            continue
        if _flat(v) and not isinstance(v, bool):
            encoded.discard(k)
            out[k] = v
        else:
            encoded.add(k)
            out[k] = json.dumps(v, separators=(",", ":"), allow_nan=False)
    out[JSON_ATTRS] = " ".join(sorted(encoded))
    return out


def decode_attrs(raw: Mapping[str, Any]) -> dict:
    """Root attributes as written: the JSON-text ones (listed in ``json_attrs``) parsed back."""
    d = dict(raw)
    for k in str(d.pop(JSON_ATTRS, "") or "").split():
        if isinstance(d.get(k), str):
            d[k] = json.loads(d[k])
    return d


def fingerprint(*parts: Any) -> str:
    """SHA-256 of the canonical JSON of ``parts`` (e.g. the manifest and the run config).

    Equal inputs give equal fingerprints across processes and machines; dict key order
    does not matter.
    """
    text = json.dumps(to_json(list(parts)), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


# --------------------------------------------------------------------------------------
# the store
# --------------------------------------------------------------------------------------
def _location(path) -> str:
    if isinstance(path, (str, os.PathLike)):
        return location.normalize(path)
    root = getattr(path, "root", None)  # LocalStore and friends
    return f"{type(path).__name__}({root})" if root is not None else type(path).__name__


def _marker_spec(stage: str, dims_or_shape, sizes: dict[str, int]) -> ArraySpec:
    entries = tuple(dims_or_shape)
    if entries and all(isinstance(d, str) for d in entries):
        missing = [d for d in entries if d not in sizes]
        if missing:
            raise ValueError(f"marker {stage}: unknown dimension(s) {missing}; the layout has {sorted(sizes)}")
        dims = entries
        shape = tuple(sizes[d] for d in entries)
    elif not all(isinstance(d, (int, np.integer)) and not isinstance(d, bool) for d in entries):
        raise ValueError(f"marker {stage}: give dimension names or a shape of ints, got {entries!r}")
    else:
        shape = tuple(int(s) for s in entries)
        dims = tuple(f"{stage}_{k}" for k in range(len(shape)))
    return ArraySpec(f"{MARKER_GROUP}/{stage}", dims, shape, (1,) * len(shape), "uint8", 0,
                     {"long_name": f"completion of stage {stage} (1 = done)", "stage": stage})


class ResultStore:
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
        self._encodings: dict[str, ChunkLayout | None] = {}  # object stores: see _object_put
        self._fs = None  # object stores: (fsspec filesystem, root path), on first use
        self._markers_listed: dict[str, set[tuple[int, ...]]] = {}  # object stores: see is_done
        # object stores: chunk cache and background writes (storage/remote.py)
        self._remote = RemoteChunks(write_behind=False) \
            if isinstance(store_arg, str) and location.is_url(location_) else None
        info = decode_attrs(group.attrs).get("integrity")
        self._integrity: dict | None = info if isinstance(info, dict) else None

    # -- construction ---------------------------------------------------------------
    @classmethod
    def create(cls, path, layout: Iterable[ArraySpec], *, attrs: Mapping[str, Any],
               markers: Mapping[str, tuple], producers: Mapping[str, str] | None = None) -> "ResultStore":
        """Create the group and every array (or resume the same run's store).

        Parameters
        ----------
        path : str, Path or zarr store
            A folder (LocalStore) or a store object such as ``zarr.storage.MemoryStore``.
        layout : iterable of ArraySpec
            Usually :func:`storage.layout.result_layout`.
        attrs : mapping
            Root attributes (manifest, parameters, version, ``fingerprint``); converted
            with :func:`to_json`. ``format`` is set to ``schlieren-store/1``.
        markers : mapping of str to tuple
            Stage -> marker dimension names (sizes from the layout, e.g.
            ``("camera", "frame")``) or a shape of ints. Each marker is a uint8 array
            ``status/<stage>`` with one chunk per index.
        producers : mapping of str to str, optional
            Array -> the stage whose marker says its chunks are written (``flow`` ->
            ``resample``). Readers then refuse a chunk missing under a set marker.
            The marker's dims must be dims of the array, chunked one index per chunk.

        Returns
        -------
        ResultStore
            Opened read-write.

        Raises
        ------
        StoreError
            If ``path`` exists and is not this run's store (different or missing
            fingerprint, not a schlieren store, a non-empty folder), or if its arrays do
            not match the layout. Nothing existing is deleted or overwritten.
        """
        layout = list(layout)
        loc = _location(path)
        try:
            root_attrs = to_json(dict(attrs))
        except TypeError as exc:
            raise StoreError(str(exc), file=loc, field="attrs") from None
        root_attrs["format"] = STORE_FORMAT
        root_attrs["template_complete"] = False
        sizes: dict[str, int] = {}
        for spec in layout:
            for d, n in zip(spec.dims, spec.shape):
                if sizes.setdefault(d, n) != n:
                    raise ValueError(f"dimension {d} has sizes {sizes[d]} and {n} ({spec.name})")
        specs = layout + [_marker_spec(stage, m, sizes) for stage, m in markers.items()]
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate array names in the layout: {sorted(n for n in names if names.count(n) > 1)}")
        by_name = {s.name: s for s in specs}
        for array, stage in dict(producers or {}).items():
            if array not in by_name or stage not in markers:
                raise ValueError(f"producer {stage!r} of {array!r}: unknown array or stage")
            mspec = by_name[f"{MARKER_GROUP}/{stage}"]
            check_coverage(array, by_name[array].dims, by_name[array].chunks,
                           mspec.dims if mspec.shape else ())
        root_attrs["integrity"] = {
            "version": INTEGRITY_VERSION, "checksum": "crc32c", "empty_chunks": "stored",
            "producers": dict(producers or {}),
            "static": sorted(s.name for s in layout if s.data is not None),
        }

        existing = cls._try_open_existing(path, loc)
        if existing is not None:
            if existing._remote is None:  # before zarr re-reads them to consolidate
                existing.check_metadata(repair=True)
            members = existing._members()
            existing._check_resume(root_attrs, specs, members)
            if existing._remote is not None and any(sp.name not in members for sp in specs):
                # an interrupted upload: complete it through zarr, past the root's array list
                existing._group = _open_group(loc, mode="r+", zarr_format=3, use_consolidated=False)
            created = existing._create_missing(specs, existing=members)
            existing._repair_static(specs)
            if not existing.attrs.get("template_complete", False):
                existing.update_attrs({"template_complete": True})
            else:
                existing._consolidate()
            if existing._remote is not None:
                existing._prefetch(existing._members() if created else members)
            log.info("resuming the existing store %s", loc)
            return existing

        if location.is_url(loc) and isinstance(path, str):
            return cls._create_by_upload(loc, root_attrs, specs)
        try:
            group = _open_group(path, mode="w-", attributes=_encode_attrs({**root_attrs, "created": _now()}, set()),
                                zarr_format=3)
        except (FileExistsError, zarr.errors.ContainsGroupError, zarr.errors.ContainsArrayError):
            # created concurrently by someone else
            raise StoreError("the store already exists (created concurrently); not overwriting it",
                             file=loc) from None
        store = cls(group, loc, path, "r+")
        store._create_missing(specs)
        store.update_attrs({"template_complete": True})  # also consolidates the metadata
        return store

    @classmethod
    def _create_by_upload(cls, loc: str, root_attrs: dict, specs: list[ArraySpec]) -> "ResultStore":
        """Create the template at an object-store URL: built in memory, uploaded in one batch.

        Through zarr's API each array costs several sequential requests (existence checks
        of the node and its parents, then the metadata): some 370 for the result layout,
        4 s against a local S3 server. The same objects are built here in a MemoryStore
        and uploaded concurrently, between a first root metadata (``template_complete``
        false, so a run killed meanwhile resumes through :meth:`_create_missing`) and the
        final one, which also holds every array's metadata (zarr's consolidated metadata:
        a worker opening the store then reads one object instead of one per array).
        """
        from zarr.storage import MemoryStore

        objects: dict = {}
        group = zarr.open_group(MemoryStore(store_dict=objects), mode="w-", zarr_format=3,
                                attributes=_encode_attrs({**root_attrs, "created": _now()}, set()))
        in_memory = cls(group, loc, None, "r+")
        in_memory._create_missing(specs)
        first_root = objects["zarr.json"].to_bytes()
        in_memory.update_attrs({"template_complete": True})  # and consolidates the metadata
        blobs = {key: buf.to_bytes() for key, buf in objects.items()}
        final_root = blobs.pop("zarr.json")
        try:
            location.write_bytes(location.join(loc, "zarr.json"), first_root)
            location.write_many({location.join(loc, key): blob for key, blob in blobs.items()})
            location.write_bytes(location.join(loc, "zarr.json"), final_root)
        except OSError as exc:  # no such bucket, no write permission...
            raise StoreError(f"cannot write the store ({type(exc).__name__}: {exc})", file=loc) from None
        store = cls(_open_group(loc, mode="r+", zarr_format=3), loc, loc, "r+")
        store._prefetch(store._members())
        return store

    def _members(self) -> dict[str, Any]:
        """Every array and group below the root by path (zarr fetches their metadata concurrently)."""
        with warnings.catch_warnings():  # the geometry cache folder beside the arrays
            warnings.filterwarnings("ignore", message=".*not recognized as a component of a Zarr hierarchy")
            return dict(self._group.members(max_depth=None))

    @staticmethod
    def _try_open_existing(path, loc: str) -> "ResultStore | None":
        if location.is_url(loc):
            try:
                found = location.isfile(location.join(loc, "zarr.json"))
                if not found and location.exists(loc):
                    raise StoreError("the location holds objects but no result store; not overwriting it",
                                     file=loc)
            except (OSError, ValueError) as exc:  # no such bucket, no credentials, a bad endpoint...
                raise StoreError(f"cannot reach the store ({type(exc).__name__}: {exc})", file=loc) from None
            if not found:
                return None
        elif isinstance(path, (str, os.PathLike)):
            p = Path(path)
            if not p.exists():
                return None
            if p.is_file():
                raise StoreError("the path exists and is a file, not a result store; not overwriting it",
                                 file=loc)
            if not (p / "zarr.json").is_file():
                if any(p.iterdir()):
                    raise StoreError("the folder exists, is not empty and is not a result store; not "
                                     "overwriting it", file=loc)
                return None
        try:
            group = _open_group(path, mode="r+", zarr_format=3)
        except (FileNotFoundError, zarr.errors.GroupNotFoundError, zarr.errors.NodeTypeValidationError):
            if isinstance(path, (str, os.PathLike)):
                raise StoreError("the folder holds Zarr data that is not a result store group; not "
                                 "overwriting it", file=loc) from None
            return None
        except (ValueError, OSError, json.JSONDecodeError) as exc:
            raise StoreError(f"the path holds something that is not a readable result store ({exc}); "
                             "not overwriting it", file=loc) from None
        return ResultStore(group, loc, path, "r+")

    def _check_resume(self, new_attrs: dict, specs: list[ArraySpec], members: Mapping[str, Any]) -> None:
        old = decode_attrs(self._group.attrs)
        loc = self._location
        if old.get("format") != STORE_FORMAT:
            raise StoreError(f"the path holds a Zarr group that is not a {STORE_FORMAT} store; not "
                             "overwriting it", file=loc)
        if not isinstance(old.get("integrity"), dict) or \
                old["integrity"].get("version") != new_attrs.get("integrity", {}).get("version"):
            raise StoreError("this store was written by an older schlieren without chunk checksums; it stays "
                             "readable (evaluate, report, export, verify) but is not resumed: write the run "
                             "to a new --out", file=loc, field="integrity")
        new_fp, old_fp = new_attrs.get("fingerprint"), old.get("fingerprint")
        if new_fp is None or old_fp is None:
            raise StoreError("a result store already exists here and no fingerprint tells whether it is "
                             "the same run; not overwriting it (choose another output path)", file=loc,
                             field="fingerprint")
        if new_fp != old_fp:
            diff = _differences({k: old.get(k) for k in ("session", "params", "run")},
                                {k: new_attrs.get(k) for k in ("session", "params", "run")})
            shown = "; ".join(diff[:6]) + (f"; and {len(diff) - 6} more" if len(diff) > 6 else "")
            raise StoreError(f"a result store of a different session or configuration exists here (differing: "
                             f"{shown or 'the fingerprint'}); not overwriting it: choose another output "
                             "path, or pass --overwrite to replace it", file=loc, field="fingerprint")
        for spec in specs:
            arr = members.get(spec.name)
            if arr is None:
                continue
            if not isinstance(arr, zarr.Array):
                raise StoreError(f"{spec.name} is a group, expected an array", file=loc, field=spec.name)
            same = (tuple(arr.shape) == spec.shape and tuple(arr.chunks) == spec.chunks
                    and _same_dtype(arr.dtype, spec.dtype)
                    and tuple(arr.metadata.dimension_names or ()) == spec.dims)
            if not same:
                raise StoreError(f"existing array {spec.name} {tuple(arr.shape)} chunks {tuple(arr.chunks)} "
                                 f"{arr.dtype} does not match the layout {spec.shape} chunks {spec.chunks} "
                                 f"{spec.dtype}; not overwriting it", file=loc, field=spec.name)

    def _create_missing(self, specs: list[ArraySpec], existing: Iterable[str] = ()) -> int:
        """Create the arrays of ``specs`` not in ``existing``; returns how many."""
        existing = set(existing)
        created = 0
        for spec in specs:
            if spec.name in existing:
                continue
            parent_name, _, leaf = spec.name.rpartition("/")
            parent = self._group
            if parent_name:
                try:
                    parent = self._group[parent_name]
                except KeyError:
                    parent = self._group.create_group(parent_name)
            if leaf in parent:
                continue
            kwargs = dict(
                shape=spec.shape, chunks=spec.chunks, dtype=spec.dtype, fill_value=spec.fill_value,
                dimension_names=spec.dims, attributes=to_json(spec.attrs), overwrite=False,
            )
            # _COMPRESSORS at the array's zstd level (layout.FAST_ZSTD for the float fields)
            kwargs["compressors"] = tuple(ZstdCodec(level=spec.zstd_level) if isinstance(c, ZstdCodec) else c
                                          for c in _COMPRESSORS)
            arr = parent.create_array(leaf, **kwargs)
            created += 1
            if spec.data is not None:
                arr[...] = np.asarray(spec.data) if spec.dtype != "str" else np.asarray(spec.data, dtype=str)
        self._arrays.clear()
        return created

    def _repair_static(self, specs: list[ArraySpec]) -> None:
        """Rewrite template arrays (coordinates) whose chunks are lost, corrupt or changed."""
        for spec in specs:
            if spec.data is None:
                continue
            want = np.asarray(spec.data) if spec.dtype != "str" else np.asarray(spec.data, dtype=str)
            arr = self.array(spec.name)
            try:
                have = np.asarray(arr[...])
                same = have.shape == want.shape and (
                    [str(v) for v in have.ravel()] == [str(v) for v in want.ravel()] if spec.dtype == "str"
                    else np.array_equal(have, want, equal_nan=True))
            except (ChunkError, ValueError, RuntimeError) as exc:
                log.warning("%s: %s; rewriting it from the template", spec.name, exc)
                same = False
            if not same:
                arr[...] = want

    @classmethod
    def open(cls, path, *, mode: str = "r+", write_behind: bool = False) -> "ResultStore":
        """Open an existing store (``mode="r"`` read-only, ``"r+"`` for task writes).

        ``write_behind`` (object stores only, for the tasks' store): chunk writes go out in
        the background until :meth:`flush` or the next :meth:`mark_done`
        (storage/remote.py). Folder stores write at once either way.
        """
        loc = _location(path)
        if mode not in ("r", "r+"):
            raise ValueError(f"mode must be 'r' or 'r+', got {mode!r}")
        try:
            group = _open_group(path, mode=mode, zarr_format=3)
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

    def _object_put(self, name: str, coords: tuple[int, ...] | None, data: np.ndarray):
        """Object stores: a call storing ``data`` as the whole chunk ``name[coords]``, or None
        (zarr writes it: a region of several chunks, another codec, a fill-valued chunk
        that zarr deletes instead).

        The bytes are encoded here, in the calling thread, exactly as zarr encodes them
        (storage/chunkio.py; the tests compare object and folder stores byte for byte), and
        the call is one PUT of them. zarr's own path adds a hop to its event loop and its codec
        pipeline to every chunk: a sixth of the PUTs' client CPU in a profile of the tests'
        tiny session, whose run is mostly small chunks.
        """
        if coords is None:
            return None
        if name not in self._encodings:
            self._encodings[name] = chunk_encoding(self.array(name), name)
        enc = self._encodings[name]
        blob = enc.encode(data) if enc is not None else None
        if blob is None:
            return None
        if self._fs is None:
            self._fs = location.filesystem(self._location)
        fs, root = self._fs
        return functools.partial(fs.pipe_file, f"{root.rstrip('/')}/{enc.key(coords)}", blob)

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
        lay = self._chunk_files(name)
        coords = lay.chunk_of(region) if lay is not None else None
        if coords is not None:  # one whole chunk: write its file directly (same bytes as zarr)
            lay.write(coords, a.astype(arr.dtype, copy=False))
            return
        a = a.astype(arr.dtype, copy=False)
        if self._remote is not None:
            coords = chunk_of(region, tuple(arr.chunks), tuple(arr.shape))
            if coords is None:
                self._remote.forget(lambda key: key[0] == name)
            send = self._object_put(name, coords, a) if coords is not None else None
            self._remote.put(None if coords is None else (name, coords), a,
                             send or functools.partial(arr.__setitem__, region, a), f"{name} at {index}")
            return
        arr[region] = a

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
                raise chunk_error(self._location, name, coords, why)
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

    # -- integrity: listing and checking chunks ---------------------------------------
    def _folder(self) -> str | None:
        """The store's folder (None on object storage or for store objects)."""
        if isinstance(self._store_arg, (str, os.PathLike)) and not location.is_url(self._location):
            return os.fspath(self._store_arg)
        return None

    def check_metadata(self, *, repair: bool = False) -> list[tuple[str, str]]:
        """``(node, reason)`` of every array or group whose ``zarr.json`` is missing, does not
        parse or differs from the root's consolidated copy of it; ``repair`` rewrites each
        from that copy (byte for byte what zarr wrote: the arrays' metadata never changes
        after the template). Readers open the store through the consolidated metadata, so
        a damaged ``zarr.json`` goes unseen until zarr re-reads it (re-consolidation on the
        next run, readers without consolidated metadata). Nothing for store objects or a
        store without consolidated metadata.
        """
        import dataclasses as _dc

        from zarr.core.buffer import default_buffer_prototype

        cm = self._group.metadata.consolidated_metadata
        if cm is None or not isinstance(self._store_arg, (str, os.PathLike)):
            return []
        want = {}
        for name, meta in cm.flattened_metadata.items():
            if hasattr(meta, "consolidated_metadata"):  # a group: its own file holds no children
                meta = _dc.replace(meta, consolidated_metadata=None)
            want[name] = meta.to_buffer_dict(default_buffer_prototype())["zarr.json"].to_bytes()
        files = {name: location.join(self._location, *name.split("/"), "zarr.json") for name in want}
        found = dict(zip(want, location.read_many(list(files.values()))))
        bad = []
        for name, blob in want.items():
            have = found[name]
            if have == blob:
                continue
            if have is None:
                why = "its zarr.json is missing"
            else:
                try:
                    json.loads(have)
                    why = "its zarr.json differs from the root's consolidated metadata"
                except ValueError:
                    why = "its zarr.json does not parse (truncated or corrupt)"
            bad.append((name, why))
            if repair:
                location.write_bytes(files[name], blob)
                log.warning("%s: %s; rewritten from the root's consolidated metadata", name, why)
        return bad

    def all_array_names(self) -> list[str]:
        """Every array of the store, markers (``status/<stage>``) included."""
        return sorted(k for k, v in self._members().items() if isinstance(v, zarr.Array))

    def chunk_grid(self, name: str) -> tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...]]:
        """``(dims, chunk shape, number of chunks per dim)`` of array ``name``."""
        arr = self.array(name)
        counts = tuple(-(-int(s) // int(c)) for s, c in zip(arr.shape, arr.chunks))
        return self.dims(name), tuple(int(c) for c in arr.chunks), counts

    def list_chunks(self, name: str) -> tuple[set[tuple[int, ...]], list[str]]:
        """Grid coordinates of the stored chunks of ``name`` (a listing, nothing read), and
        the orphaned ``*.partial`` files of killed writers among them."""
        keys: set[tuple[int, ...]] = set()
        partial: list[str] = []
        folder = self._folder()
        if folder is not None:
            base = os.path.join(folder, *name.split("/"), "c")
            if os.path.isfile(base):
                return {()}, partial
            for sub, _, files in os.walk(base):
                rel = os.path.relpath(sub, base)
                head = () if rel == "." else tuple(rel.split(os.sep))
                if not all(p.isdigit() for p in head):
                    continue
                for f in files:
                    if f.isdigit():
                        keys.add(tuple(int(p) for p in head + (f,)))
                    elif f.endswith(".partial"):
                        partial.append(os.path.join(sub, f))
            return keys, partial
        from zarr.core.sync import sync

        inner = self._group.store

        async def collect():
            return [k async for k in inner.list_prefix(f"{name}/c")]

        for key in sync(collect()):
            rest = key[len(name) + 2:]
            if rest == "":
                keys.add(())
            elif rest.startswith("/") and all(p.isdigit() for p in rest[1:].split("/")):
                keys.add(tuple(int(p) for p in rest[1:].split("/")))
        return keys, partial

    def list_all_chunks(self) -> dict[str, set[tuple[int, ...]]] | None:
        """Grid coordinates of the stored chunks of every array, by array name, from one
        listing of the whole store (an object store answers 1000 keys per request, where
        :meth:`list_chunks` of each array costs a request per array); None for folder
        stores and store objects, which :meth:`list_chunks` lists locally."""
        if self._remote is None:
            return None
        from zarr.core.sync import sync

        inner = self._group.store

        async def collect():
            return [k async for k in inner.list_prefix("")]

        out: dict[str, set[tuple[int, ...]]] = {}
        for key in sync(collect()):
            parts = key.split("/")
            # <array>/c[/<i>...]: a "c" followed by grid indices only (an array may be named "c")
            for i in range(1, len(parts)):
                if parts[i] == "c" and all(p.isdigit() for p in parts[i + 1:]):
                    out.setdefault("/".join(parts[:i]), set()).add(tuple(int(p) for p in parts[i + 1:]))
                    break
        return out

    def check_chunk(self, name: str, coords) -> str | None:
        """Read the stored chunk ``name[coords]``: None if it decodes and passes its
        checksum, else the reason."""
        lay = self._chunk_files(name)
        if lay is not None:
            try:
                lay.load(tuple(coords))
            except CorruptChunk as exc:
                return exc.reason
            return None
        arr = self.array(name)
        region = tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(coords, arr.chunks, arr.shape))
        try:
            arr[region]
        except ChunkError as exc:
            return exc.reason
        except Exception as exc:  # noqa: BLE001 - any decoding failure is damage
            return f"does not decode ({type(exc).__name__}: {exc})"
        return None

    def remove_chunk(self, name: str, coords) -> None:
        """Delete a stored chunk (a damaged one, before its task is recomputed)."""
        if self._mode == "r":
            raise StoreError("the store is open read-only", file=self._location, field=name)
        folder = self._folder()
        if folder is not None:
            path = os.path.join(folder, *name.split("/"), "c", *(str(int(i)) for i in coords))
            try:
                os.remove(path)
            except FileNotFoundError:
                pass
            return
        from zarr.core.sync import sync

        sync(self._group.store.delete(f"{name}/c" + "".join(f"/{int(i)}" for i in coords)))

    # -- completion markers -----------------------------------------------------------
    def _marker(self, stage: str) -> zarr.Array:
        try:
            return self.array(f"{MARKER_GROUP}/{stage}")
        except StoreError:
            raise StoreError(f"no completion marker for stage {stage!r}", file=self._location,
                             field=f"{MARKER_GROUP}/{stage}") from None

    def stages(self) -> list[str]:
        """Stages that have completion markers."""
        prefix = MARKER_GROUP + "/"
        if self._remote is not None and any(k.startswith(prefix) for k in self._arrays):
            return sorted(k[len(prefix):] for k in self._arrays if k.startswith(prefix))
        try:
            grp = self._group[MARKER_GROUP]
        except KeyError:
            return []
        return sorted(name for name, _ in grp.arrays())

    def mark_done(self, stage: str, index) -> None:
        """Set the marker of ``stage`` at ``index`` (a task's last write)."""
        if self._mode == "r":
            raise StoreError("the store is open read-only", file=self._location, field=stage)
        arr = self._marker(stage)
        region = normalize_region(index, arr.shape)
        ones = np.ones(tuple(s.stop - s.start for s in region), dtype=np.uint8)
        name = f"{MARKER_GROUP}/{stage}"
        lay = self._chunk_files(name)
        coords = lay.chunk_of(region) if lay is not None else None
        if coords is not None:
            lay.write(coords, ones)
        elif self._remote is not None:
            put = self._object_put(name, chunk_of(region, tuple(arr.chunks), tuple(arr.shape)), ones)

            def send():
                if put is not None:
                    put()
                else:
                    arr[region] = ones
                listed = self._markers_listed.get(stage)
                if listed is not None:
                    listed.update(itertools.product(*(range(s.start, s.stop) for s in region)))
            # sent once the data it vouches for is stored, never if that failed
            self._remote.put(None, None, send, f"the {stage} marker at {index}", after_pending=True)
        else:
            arr[region] = ones

    def flush(self) -> None:
        """Wait until every write made through this object is stored (see :meth:`open`).

        Raises
        ------
        OSError
            A background write failed (naming the array and index); its marker was not sent.
        """
        if self._remote is not None:
            self._remote.barrier()

    def unmark(self, stage: str, index=()) -> None:
        """Clear the marker of ``stage`` at ``index``: its task runs again on the next run."""
        if self._mode == "r":
            raise StoreError("the store is open read-only", file=self._location, field=stage)
        arr = self._marker(stage)
        region = normalize_region(index, arr.shape)
        self.flush()
        lay = self._chunk_files(f"{MARKER_GROUP}/{stage}")
        coords = lay.chunk_of(region) if lay is not None else None
        if coords is not None:  # an unset marker has no file (zarr's default for the fill value)
            try:
                os.remove(lay.path(coords))
            except FileNotFoundError:
                pass
        else:
            arr[region] = np.zeros(tuple(s.stop - s.start for s in region), dtype=np.uint8)
        listed = self._markers_listed.get(stage)
        if listed is not None:
            listed.difference_update(itertools.product(*(range(s.start, s.stop) for s in region)))

    def is_done(self, stage: str, index) -> bool:
        """True if every position of ``index`` in ``stage``'s marker is set.

        Every task asks this before it runs, so in a folder store a single position is
        read straight from its marker chunk file (storage/chunkio.py): a chunk never
        written holds the fill value 0 (not done). Through zarr's I/O thread a read costs
        about 1 ms, several in a busy worker.

        In an object store one request per position (8-10 ms against a local S3 server)
        would cost more than many tasks: the first question about a stage lists the
        marker's chunks once (a set marker is a stored chunk; an unset one holds the fill
        value and is not stored), and later questions in this process are answered from
        that listing plus the markers set through this object. A marker set elsewhere since
        the listing reads as not done, which only repeats a task whose writes are
        idempotent; a set marker never reads as unset.

        A marker chunk that is corrupt counts as not done (its task is recomputed and
        rewrites it), with a warning.
        """
        arr = self._marker(stage)
        region = normalize_region(index, arr.shape)
        if self._remote is not None:
            listed = self._listed_markers(stage)
            return all(c in listed for c in itertools.product(*(range(s.start, s.stop) for s in region)))
        try:
            return self._marker_region_set(stage, arr, region)
        except ChunkError as exc:
            log.warning("%s; counted as not done", exc)
            return False

    def _marker_set(self, stage: str, index) -> bool:
        """Like :meth:`is_done` but read from the marker itself (not an object store's
        listing), and a corrupt marker raises :class:`ChunkError`."""
        arr = self._marker(stage)
        return self._marker_region_set(stage, arr, normalize_region(index, arr.shape))

    def _marker_region_set(self, stage: str, arr, region) -> bool:
        name = f"{MARKER_GROUP}/{stage}"
        lay = self._chunk_files(name)
        coords = lay.chunk_of(region) if lay is not None else None
        if coords is not None:
            try:
                a = lay.load(coords)
            except CorruptChunk as exc:
                raise chunk_error(self._location, name, coords, exc.reason) from None
            return a is not None and bool(np.all(a == 1))
        return bool(np.all(np.asarray(arr[region]) == 1))

    def marker_chunk_set(self, stage: str, coords) -> bool:
        """Is the marker chunk at grid ``coords`` set? :class:`ChunkError` if it is corrupt."""
        return self._marker_set(stage, tuple(int(c) for c in coords))

    def _listed_markers(self, stage: str) -> set[tuple[int, ...]]:
        """Positions of ``stage``'s marker whose chunk is stored.

        The first call lists every marker chunk of every stage (one listing request per
        1000 of them), later ones reuse it.
        """
        if not self._markers_listed:
            for stage_ in self.stages():
                arr = self._marker(stage_)
                if tuple(arr.chunks) != (1,) * arr.ndim:  # pragma: no cover - markers are made so
                    raise StoreError("marker chunks must hold one position", file=self._location,
                                     field=f"{MARKER_GROUP}/{stage_}")
                self._markers_listed[stage_] = set()
            for key in location.find(location.join(self._location, MARKER_GROUP)):
                if key.endswith("/c"):  # "<stage>/c": the single chunk of a 0-d marker
                    stage_, pos = key[:-2], ()
                else:  # "<stage>/c/<i>/<j>" (and "<stage>/zarr.json", skipped)
                    stage_, sep, rest = key.partition("/c/")
                    try:
                        pos = tuple(int(p) for p in rest.split("/")) if sep else None
                    except ValueError:
                        pos = None
                if pos is not None and stage_ in self._markers_listed:
                    self._markers_listed[stage_].add(pos)
        return self._markers_listed[stage]

    def done(self, stage: str) -> np.ndarray:
        """The whole marker of ``stage`` as a bool array (corrupt marker chunks: not done)."""
        self.flush()
        arr = self._marker(stage)
        try:
            return np.asarray(arr[...]) == 1
        except ChunkError:
            out = np.zeros(arr.shape, dtype=bool)
            for idx in np.ndindex(*arr.shape):
                out[idx] = self.is_done(stage, idx)
            return out

    # -- coordinator-only attribute updates -----------------------------------------------
    def set_stage_completed(self, stage: str, timestamp: str | _dt.datetime | None = None) -> None:
        """Record in the root attrs (``stages_completed``) when ``stage`` completed.

        Only the coordinator calls this (concurrent metadata writes are unsafe in zarr 3).
        """
        ts = timestamp.isoformat() if isinstance(timestamp, _dt.datetime) else (timestamp or _now())
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
        self._group.attrs.update(_encode_attrs(values, encoded))
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


def _open_group(path, **kwargs) -> zarr.Group:
    """``zarr.open_group`` of a folder, an fsspec URL (zarr's FsspecStore) or a store object,
    through :class:`~schlieren.storage.integrity.CheckedStore` (every chunk read checked)."""
    return zarr.open_group(checked(path, read_only=kwargs.get("mode") == "r",
                                   location=_location(path)), **kwargs)


def _differences(old: Any, new: Any, where: str = "") -> list[str]:
    """Dotted names of the values that differ between two nested mappings, ``name: old -> new``."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        out = []
        for k in list(old) + [k for k in new if k not in old]:
            out += _differences(old.get(k), new.get(k), f"{where}.{k}" if where else str(k))
        return out
    if old == new or to_json(old) == to_json(new):
        return []
    def short(v):
        r = json.dumps(to_json(v)) if v is not None else "(none)"
        return r if len(r) <= 40 else r[:37] + "..."
    return [f"{where}: {short(old)} -> {short(new)}"]


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


def _same_dtype(actual, wanted: str) -> bool:
    if wanted == "str":
        return np.dtype(actual).kind in ("T", "O", "U") or "str" in str(actual).lower()
    try:
        return np.dtype(actual) == np.dtype(wanted)
    except TypeError:
        return False
