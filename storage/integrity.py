"""Chunk integrity of the result store: checksums, completion coverage and scans.

The design (docs/design.md, "Integrity, resume and preflight"):

* **Checksums in the codec chain.** Every array the store creates ends its codecs with
  zarr's ``crc32c`` codec (``bytes``, ``zstd``, ``crc32c``), so zarr itself computes and
  checks a CRC-32C per chunk on any store (folder or object storage), and
  :mod:`schlieren.storage.chunkio` does the same byte for byte on the fast path.
* **Empty chunks are stored.** The data arrays are written with
  ``write_empty_chunks=True``: a task stores every chunk it writes, even one equal to the
  fill value (an all-False mask, a NaN flow field outside the image). A completion marker
  set therefore means *every chunk of the task's outputs has a file*; a missing file under
  a set marker was lost, never "legitimately empty". (Zarr's default drops fill-valued
  chunks, which made "deleted" and "empty" indistinguishable; storing them costs a few
  hundred bytes each once compressed.) Markers keep zarr's default: unset = no file.
* **Coverage in the root attributes.** ``integrity`` records the format version, the
  checksum, the stage that produces each data array (``producers``: its completion marker
  covers the array's chunks) and the static arrays written with the template
  (coordinates). A chunk's marker position is its grid position along the marker's dims.
* **Readers never return lost or corrupt data.** :class:`CheckedStore` wraps the zarr
  store every project reader opens (``evaluate``, ``export``, ``report``, the tasks,
  :func:`open_dataset` for xarray): a chunk that fails its checksum, or is missing although
  its stage is marked done, raises :class:`~schlieren.storage.errors.ChunkError` naming the
  store, the array and the chunk.
* **Older stores** (no ``integrity`` attribute: written before checksums) are read as
  before, without checks (a missing chunk reads as the fill value, as their writer meant);
  a run refuses to resume them (``store/template.py``).

:func:`scan_store` lists (cheap) or reads (``full``) every chunk and reports what is
missing or corrupt; ``workers/verify.py`` turns that into recomputation.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from zarr.storage import WrapperStore

from schlieren.storage.chunkio import CorruptChunk, strip_checksum
from schlieren.storage.errors import ChunkError
from schlieren.storage.layout import MARKER_GROUP

__all__ = ["INTEGRITY_VERSION", "CheckedStore", "Problem", "ScanResult", "scan_store", "chunk_error",
           "marker_index", "open_dataset", "format_chunk", "not_kept_error", "dropped_of"]

log = logging.getLogger(__name__)

#: Version of the ``integrity`` root attribute (crc32c on every chunk, empty chunks stored).
INTEGRITY_VERSION = 1


def format_chunk(coords) -> str:
    return "(" + ", ".join(str(int(c)) for c in coords) + (",)" if len(coords) == 1 else ")")


def chunk_error(location: str, array: str, coords, what: str) -> ChunkError:
    """The one-line error of a bad chunk, with the command that repairs it."""
    return ChunkError(f"chunk {format_chunk(coords)} {what}; `schlieren verify {location} --repair` "
                      "and a rerun recompute it (or `schlieren run ... --verify`)",
                      file=location, array=array, chunk=tuple(int(c) for c in coords), reason=what)


def not_kept_error(location: str, array: str, coords, keep: str | None = None) -> ChunkError:
    """The one-line error of a chunk the run's retention dropped (``schlieren run --keep``)."""
    policy = f"--keep {keep}" if keep else "--keep"
    return ChunkError(f"chunk {format_chunk(coords)} was not kept: the run's retention ({policy}) drops {array} "
                      f"once the stages reading it are done; a run with --keep all (or --keep {array}) stores "
                      "it again", file=location, array=array, chunk=tuple(int(c) for c in coords), reason="not kept")


def _json_attr(attrs, name: str) -> dict | None:
    """Root attribute ``name`` (stored as JSON text, netCDF-safe) as a dict, or None."""
    info = attrs.get(name) if hasattr(attrs, "get") else None
    if isinstance(info, str):
        try:
            info = json.loads(info)
        except ValueError:
            info = None
    return info if isinstance(info, dict) else None


def dropped_of(attrs) -> frozenset[str]:
    """The arrays whose chunks the run's retention may have dropped (root attribute
    ``retention``, :mod:`schlieren.storage.store.retention`): a missing chunk of theirs
    under a set marker is "not kept", not lost."""
    info = _json_attr(attrs, "retention") or {}
    return frozenset(str(n) for n in info.get("dropped") or ())


def marker_index(array_dims, array_chunks, marker_dims, coords) -> tuple[int, ...]:
    """Position in the marker (dims ``marker_dims``) of the array chunk at grid ``coords``."""
    out = []
    for d in marker_dims:
        k = list(array_dims).index(d)
        out.append(int(coords[k]) * int(array_chunks[k]))
    return tuple(out)


def covering_stage(info: dict | None, name: str) -> str | None:
    """What says array ``name``'s chunks must exist: ``"template"`` (static arrays), the
    producing stage's name, or None (nothing: a missing chunk is the fill value)."""
    if not info:
        return None
    if name in (info.get("static") or ()):
        return "template"
    return (info.get("producers") or {}).get(name)


def missing_reason(stage: str) -> str:
    if stage == "template":
        return "is missing from a template array (coordinates written when the store was created)"
    return f"is missing although stage {stage} is marked complete"


def check_coverage(name: str, dims, chunks, marker_dims) -> None:
    """Refuse a producer whose marker cannot say which chunks it covers."""
    for d in marker_dims:
        if d not in dims:
            raise ValueError(f"{name}: marker dimension {d!r} is not one of the array's {tuple(dims)}")
        if int(chunks[list(dims).index(d)]) != 1:
            raise ValueError(f"{name}: chunks along the marker dimension {d!r} must hold one index")


# --------------------------------------------------------------------------------------
# the checking zarr store
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Meta:
    dims: tuple[str, ...]
    chunks: tuple[int, ...]
    checksum: bool
    zstd: bool


def _parse_meta(raw: bytes | None) -> _Meta | None:
    if raw is None:
        return None
    try:
        m = json.loads(raw)
    except ValueError:
        return None
    return _meta_from_dict(m) if isinstance(m, dict) else None


def _meta_from_dict(m: dict) -> _Meta | None:
    """The checks' view of an array's ``zarr.json`` (parsed), or None if it is not one they handle."""
    if m.get("node_type") != "array" or m.get("zarr_format") != 3:
        return None
    enc = m.get("chunk_key_encoding") or {}
    if enc.get("name") != "default" or (enc.get("configuration") or {}).get("separator", "/") != "/":
        return None
    grid = m.get("chunk_grid") or {}
    if grid.get("name") != "regular":
        return None
    names = [c.get("name") if isinstance(c, dict) else c for c in m.get("codecs") or []]
    return _Meta(dims=tuple(m.get("dimension_names") or ()),
                 chunks=tuple(int(c) for c in grid["configuration"]["chunk_shape"]),
                 checksum=bool(names) and names[-1] == "crc32c",
                 zstd="zstd" in names and names[0] == "bytes")


def _integrity_attr(attrs) -> dict | None:
    """The ``integrity`` root attribute (stored as JSON text, netCDF-safe), or None."""
    return _json_attr(attrs, "integrity")


def _chunk_key(key: str) -> tuple[str, tuple[int, ...]] | None:
    """``flow/c/0/3/0/0/0`` -> ``("flow", (0, 3, 0, 0, 0))``; None for other keys."""
    parts = key.split("/")
    for i in range(len(parts) - 1, 0, -1):
        if parts[i] == "c":
            rest = parts[i + 1:]
            if all(p.isdigit() for p in rest):
                return "/".join(parts[:i]), tuple(int(p) for p in rest)
            return None
    return None


def _decode_marker(raw: bytes, meta: _Meta) -> bool:
    from numcodecs import Zstd

    blob = strip_checksum(raw) if meta.checksum else raw
    try:
        values = np.frombuffer(Zstd().decode(blob), dtype=np.uint8)
    except Exception as exc:  # noqa: BLE001 - zstd raises RuntimeError and friends
        raise CorruptChunk(f"does not decompress ({type(exc).__name__})") from None
    return bool(values.size) and bool(np.all(values == 1))


class CheckedStore(WrapperStore):
    """A zarr store that refuses to hand out lost or corrupt chunks of a result store.

    Every whole-chunk ``get`` of an array whose codecs end with ``crc32c`` is checked
    against its checksum here, before zarr decodes it, so that the error can name the
    array and the chunk (zarr's own check says only "checksum mismatch"). A chunk with no
    stored value is looked up in the store's ``integrity`` coverage: if its stage's
    completion marker is set (or it belongs to a static coordinate array), the chunk was
    lost and :class:`~schlieren.storage.errors.ChunkError` is raised instead of returning
    the fill value. Everything else passes through unchanged, so any zarr or xarray
    reader can use it.
    """

    def __init__(self, store, location: str | None = None):
        super().__init__(store)
        self.location = location if location is not None else str(store)
        self._meta: dict[str, _Meta | None] = {}
        self._integrity: dict | None = None
        self._integrity_read = False
        self._consolidated: dict = {}  # array -> its metadata in the root's consolidated copy
        self._retention: dict = {}  # the root attribute ``retention``
        self._gone: set[str] = set()  # arrays whose own zarr.json is missing (the array was deleted)
        # metadata fetches in flight, by key: zarr requests the chunks of a read together,
        # and each would otherwise fetch the array's zarr.json again before the first
        # answer is cached (one fetch per chunk of a multi-chunk read from an object store)
        self._fetching: dict[str, asyncio.Task] = {}

    def _with_store(self, store):
        return type(self)(store, self.location)

    def __repr__(self) -> str:
        return f"CheckedStore({self._store!r})"

    def seed(self, metadata: dict[str, dict], root_attrs: dict | None = None) -> None:
        """Take array metadata (``{name: zarr.json as a dict}``) and the root attributes
        already read by the caller (e.g. :meth:`ResultStore.open`'s concurrent fetch of every
        member), so the first chunk read of each array needs no request of its own."""
        for name, m in metadata.items():
            if name not in self._meta:
                meta = _meta_from_dict(m)
                if meta is not None:
                    self._meta[name] = meta
        if root_attrs is not None and not self._integrity_read:
            self._integrity = _integrity_attr(root_attrs)
            self._retention = _json_attr(root_attrs, "retention") or {}
            self._integrity_read = True

    async def _fetch_once(self, key: str, prototype):
        """``self._store.get(key)``, shared by the concurrent callers of one event loop."""
        loop = asyncio.get_running_loop()
        task = self._fetching.get(key)
        if task is None or task.get_loop() is not loop:
            task = loop.create_task(self._store.get(key, prototype))
            self._fetching[key] = task
            # forgotten when it ends, even if every caller was cancelled meanwhile (a finished
            # fetch left here would answer later calls with a stale "no such array")
            task.add_done_callback(lambda t: self._fetching.pop(key) if self._fetching.get(key) is t else None)
        return await asyncio.shield(task)

    async def _get_meta(self, name: str, prototype) -> _Meta | None:
        if name not in self._meta:
            buf = await self._fetch_once(f"{name}/zarr.json", prototype)
            meta = _parse_meta(buf.to_bytes() if buf is not None else None)
            if meta is None and buf is None:
                # no zarr.json: an array deleted from the store (``rm -rf STORE/temperature``)
                # is still listed in the root's consolidated metadata, which readers use
                await self._get_integrity(prototype)
                meta = _meta_from_dict(self._consolidated.get(name) or {})
                if meta is not None:
                    self._gone.add(name)
            if meta is None:
                return None  # not cached: the array may be created later
            self._meta[name] = meta
        return self._meta[name]

    async def _get_integrity(self, prototype) -> dict | None:
        if not self._integrity_read:
            buf = await self._fetch_once("zarr.json", prototype)
            try:
                root = json.loads(buf.to_bytes()) if buf is not None else {}
            except ValueError:
                root = {}
            attrs = root.get("attributes") or {}
            self._integrity = _integrity_attr(attrs)
            self._retention = _json_attr(attrs, "retention") or {}
            self._consolidated = dict(((root.get("consolidated_metadata") or {}).get("metadata")) or {})
            self._integrity_read = buf is not None
        return self._integrity

    async def _required(self, name: str, meta: _Meta, coords, prototype) -> str | None:
        """Why the missing chunk ``name[coords]`` should exist, or None if it need not."""
        stage = covering_stage(await self._get_integrity(prototype), name)
        if stage in (None, "template"):
            return None if stage is None else missing_reason(stage)
        mname = f"{MARKER_GROUP}/{stage}"
        mmeta = await self._get_meta(mname, prototype)
        if mmeta is None or not mmeta.zstd:
            return None
        idx = marker_index(meta.dims, meta.chunks, mmeta.dims, coords)
        mkey = f"{mname}/c" + "".join(f"/{i}" for i in idx)
        buf = await self._store.get(mkey, prototype)
        if buf is None:
            return None
        try:
            done = _decode_marker(buf.to_bytes(), mmeta)
        except CorruptChunk as exc:
            raise chunk_error(self.location, mname, idx, exc.reason) from None
        if not done:
            return None
        return missing_reason(stage) + (" (the whole array is gone: its zarr.json too)" if name in self._gone else "")

    async def get(self, key, prototype, byte_range=None):
        buf = await self._store.get(key, prototype, byte_range)
        if byte_range is not None or key.endswith("zarr.json"):
            return buf
        parsed = _chunk_key(key)
        if parsed is None:
            return buf
        name, coords = parsed
        meta = await self._get_meta(name, prototype)
        if meta is None:
            return buf
        if buf is None:
            why = await self._required(name, meta, coords, prototype)
            if why is not None:
                if name in dropped_of({"retention": self._retention}):
                    raise not_kept_error(self.location, name, coords, self._retention.get("keep"))
                raise chunk_error(self.location, name, coords, why)
            return None
        if meta.checksum:
            try:
                strip_checksum(buf.to_bytes())
            except CorruptChunk as exc:
                raise chunk_error(self.location, name, coords, exc.reason) from None
        return buf

    async def _get_many(self, requests):
        for key, prototype, byte_range in requests:
            yield key, await self.get(key, prototype, byte_range)


def checked(path_or_store, *, read_only: bool, location: str | None = None) -> CheckedStore:
    """A :class:`CheckedStore` over a folder path or a zarr store object."""
    if isinstance(path_or_store, CheckedStore):
        return path_or_store
    if isinstance(path_or_store, (str, os.PathLike)):
        from schlieren.storage import location as loc_mod

        loc = loc_mod.normalize(path_or_store)  # a folder (LocalStore) or a URL (FsspecStore)
        return CheckedStore(loc_mod.zarr_store(loc, read_only=read_only), location if location is not None else loc)
    return CheckedStore(path_or_store, location)


def open_dataset(path, **kwargs):
    """The result store as an ``xarray.Dataset`` whose reads are checked chunk by chunk.

    Same as ``xarray.open_zarr(path, consolidated=False)`` except that reading a chunk
    that is corrupt, or lost under a set completion marker, raises
    :class:`~schlieren.storage.errors.ChunkError` naming the array and chunk.
    """
    import xarray as xr

    kwargs.setdefault("consolidated", False)
    return xr.open_zarr(checked(path, read_only=True), **kwargs)


# --------------------------------------------------------------------------------------
# scans
# --------------------------------------------------------------------------------------
@dataclass
class Problem:
    """One damaged chunk.

    ``kind``: ``missing`` (no file under a set marker or in a static array), ``corrupt``
    (fails its checksum or does not decode), ``corrupt-marker`` (a completion marker that
    does not decode: its task is recomputed), ``stray`` (a corrupt chunk no set marker
    covers: removed, its task is not done anyway), ``corrupt-metadata`` (an array's or
    group's ``zarr.json`` missing, corrupt or changed: rewritten from the root's
    consolidated copy, no data is recomputed). ``stage``/``index`` name the task
    whose recomputation repairs it (None for static arrays and stray chunks).
    """

    array: str
    chunk: tuple[int, ...]
    kind: str
    reason: str
    stage: str | None = None
    index: tuple[int, ...] | None = None

    def __str__(self) -> str:
        task = f" (task {self.stage} {format_chunk(self.index)})" if self.stage is not None else ""
        where = f"{self.array} chunk {format_chunk(self.chunk)}" if self.chunk else self.array
        return f"{where}: {self.kind}: {self.reason}{task}"


@dataclass
class ScanResult:
    problems: list[Problem] = field(default_factory=list)
    done: dict[str, set] = field(default_factory=dict)  # marker positions set and readable
    partial_files: list[str] = field(default_factory=list)  # orphans of killed writers
    chunks_listed: int = 0
    chunks_read: int = 0
    legacy: bool = False

    @property
    def ok(self) -> bool:
        return not self.problems


class ScannedStore(Protocol):
    """What :func:`scan_store` asks of a store (:class:`~schlieren.storage.store.ResultStore`
    has it; this module does not import the store, which reads through :class:`CheckedStore`)."""

    @property
    def integrity(self) -> dict | None: ...
    @property
    def remote(self) -> bool: ...
    @property
    def dropped_arrays(self) -> frozenset[str]: ...
    def check_metadata(self) -> list[tuple[str, str]]: ...
    def list_all_chunks(self) -> dict[str, set[tuple[int, ...]]] | None: ...
    def list_chunks(self, name: str) -> tuple[set[tuple[int, ...]], list[str]]: ...
    def stages(self) -> list[str]: ...
    def marker_chunk_set(self, stage: str, coords) -> bool: ...
    def marker_dims(self, stage: str) -> tuple[str, ...]: ...
    def all_array_names(self) -> list[str]: ...
    def chunk_grid(self, name: str) -> tuple[tuple[str, ...], tuple[int, ...], tuple[int, ...]]: ...
    def check_chunk(self, name: str, coords) -> str | None: ...


def scan_store(store: ScannedStore, *, full: bool = False) -> ScanResult:
    """Check a result store's chunks against its completion markers.

    Parameters
    ----------
    store : ResultStore
    full : bool
        Also read every stored chunk and check its checksum and decoding (reads the
        whole store). Without it, the scan lists the chunk files and reads only the
        markers: cheap enough for every resume.

    Returns
    -------
    ScanResult
        ``done`` holds, per stage, the marker positions that are set (corrupt ones are
        problems, not done); ``problems`` every missing or corrupt chunk.
    """
    res = ScanResult()
    info = store.integrity
    res.legacy = info is None
    # metadata: every array's and group's zarr.json against the root's consolidated copy
    # (a few small reads; on object storage only with ``full``)
    if full or not store.remote:
        for name, why in store.check_metadata():
            res.problems.append(Problem(name, (), "corrupt-metadata", why))
    listing = _Listing(store, res)
    _scan_markers(store, listing, res)
    # data arrays: a set marker needs every chunk of its producer's outputs
    producers = dict((info or {}).get("producers") or {})
    static = set((info or {}).get("static") or ())
    dropped = store.dropped_arrays  # the run's retention deletes their chunks: missing is "not kept"
    for name in store.all_array_names():
        if name.startswith(f"{MARKER_GROUP}/"):
            continue
        have = listing(name)
        grid = store.chunk_grid(name)
        if name not in dropped:
            _scan_missing(store, name, grid, have, producers.get(name), name in static, res)
        if full:
            _scan_stored(store, name, grid, have, producers.get(name), name in static, res)
    return res


class _Listing:
    """The stored chunks of each array, listed once (an object store lists them all in one
    pass, not one request per array); counts them and the orphaned ``*.partial`` files."""

    def __init__(self, store: ScannedStore, res: ScanResult):
        self.store, self.res = store, res
        self.everything = store.list_all_chunks()  # object stores: one listing, not one per array
        self.listed: dict[str, set] = {}

    def __call__(self, name: str) -> set:
        if self.everything is not None:
            keys = self.everything.get(name, set())
            if name not in self.listed:
                self.listed[name] = keys
                self.res.chunks_listed += len(keys)
            return keys
        if name not in self.listed:
            keys, partial = self.store.list_chunks(name)
            self.listed[name] = keys
            self.res.partial_files += partial
            self.res.chunks_listed += len(keys)
        return self.listed[name]


def _scan_markers(store: ScannedStore, listing: _Listing, res: ScanResult) -> None:
    """Read every stored marker chunk: ``res.done`` gets the set ones, corrupt ones are problems."""
    for stage in store.stages():
        mname = f"{MARKER_GROUP}/{stage}"
        done = set()
        for coords in sorted(listing(mname)):
            res.chunks_read += 1
            try:
                ok = store.marker_chunk_set(stage, coords)
            except ChunkError as exc:
                res.problems.append(Problem(mname, coords, "corrupt-marker", _reason(exc), stage, coords))
                continue
            if ok:
                done.add(tuple(coords))
        res.done[stage] = done


def _scan_missing(store: ScannedStore, name: str, grid, have: set, stage: str | None, static: bool,
                  res: ScanResult) -> None:
    """Chunks of array ``name`` (``grid``: its :meth:`chunk_grid`) without a file: any in a
    template array, or under a set marker."""
    dims, chunks, counts = grid
    if static:
        for coords in np.ndindex(*counts):
            if coords not in have:
                res.problems.append(Problem(name, coords, "missing", "no chunk file in a template array"))
    elif stage is not None and stage in res.done:
        mdims = store.marker_dims(stage)
        for coords in np.ndindex(*counts):
            idx = marker_index(dims, chunks, mdims, coords)
            if idx in res.done[stage] and coords not in have:
                res.problems.append(Problem(name, coords, "missing",
                                            f"no chunk file although stage {stage} is marked complete",
                                            stage, idx))


def _scan_stored(store: ScannedStore, name: str, grid, have: set, stage: str | None, static: bool,
                 res: ScanResult) -> None:
    """Read every stored chunk of array ``name`` (``grid``: its :meth:`chunk_grid`): a damaged
    one under a set marker (or in a template array) is ``corrupt``, its task recomputed; any
    other is ``stray``."""
    dims, chunks, _ = grid
    for coords in sorted(have):
        res.chunks_read += 1
        reason = store.check_chunk(name, coords)
        if reason is None:
            continue
        idx = None
        if stage is not None and stage in res.done:
            idx = marker_index(dims, chunks, store.marker_dims(stage), coords)
            if idx not in res.done[stage]:
                idx = None
        if static or idx is not None:
            res.problems.append(Problem(name, coords, "corrupt", reason, stage if idx is not None else None, idx))
        else:
            res.problems.append(Problem(name, coords, "stray", reason))


def _reason(exc: ChunkError) -> str:
    return exc.reason


def describe(res: ScanResult, limit: int = 20) -> list[str]:
    """One line per problem (at most ``limit``, then a count)."""
    lines = [str(p) for p in res.problems[:limit]]
    if len(res.problems) > limit:
        lines.append(f"... and {len(res.problems) - limit} more")
    return lines


def summary_line(res: ScanResult) -> str:
    kinds: dict[str, int] = {}
    for p in res.problems:
        kinds[p.kind] = kinds.get(p.kind, 0) + 1
    found = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) or "no damaged chunk"
    return f"{res.chunks_listed} chunks listed, {res.chunks_read} read: {found}"


def as_json(res: ScanResult) -> dict[str, Any]:
    return {"ok": res.ok, "legacy": res.legacy, "chunks_listed": res.chunks_listed,
            "chunks_read": res.chunks_read, "partial_files": len(res.partial_files),
            "problems": [{"array": p.array, "chunk": list(p.chunk), "kind": p.kind, "reason": p.reason,
                          "stage": p.stage, "index": list(p.index) if p.index is not None else None}
                         for p in res.problems]}
