"""Creating a result store's template, and resuming the same run's store.

The coordinator creates the group and every array up front (SPEC section 2; no resizes
or metadata writes during a run), or, if the path already holds this run's store (same
``fingerprint``), completes what an interrupted creation left out and repairs the
template arrays. Anything else at the path is refused, never deleted or overwritten.

:class:`TemplateMixin` holds these steps as methods of
:class:`~schlieren.storage.store.result_store.ResultStore` (it uses the store's group,
``_remote``, ``array``, ``_members``, ``update_attrs`` and ``_consolidate``).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any, Iterable, Mapping, Self

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from schlieren.storage import location
from schlieren.storage.errors import ChunkError, StoreError
from schlieren.storage.integrity import INTEGRITY_VERSION, check_coverage
from schlieren.storage.layout import MARKER_GROUP, STORE_FORMAT, ArraySpec, marker_spec
from schlieren.storage.store.attrs import decode_attrs, differences, encode_attrs, now, to_json
from schlieren.storage.store.group import open_group, store_location

log = logging.getLogger(__name__)

#: zstd, then zarr's CRC-32C of the compressed bytes (checked on every read)
_COMPRESSORS = (ZstdCodec(level=3), Crc32cCodec())


class TemplateMixin:
    """Template creation and resumption (methods of ``ResultStore``)."""

    @classmethod
    def create(cls, path, layout: Iterable[ArraySpec], *, attrs: Mapping[str, Any],
               markers: Mapping[str, tuple], producers: Mapping[str, str] | None = None) -> Self:
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
        loc = store_location(path)
        root_attrs = _root_attrs(attrs, loc)
        specs = _all_specs(layout, markers)
        root_attrs["integrity"] = _integrity_attr(layout, specs, markers, producers)
        existing = cls._try_open_existing(path, loc)
        if existing is not None:
            return existing._resume(root_attrs, specs)
        if location.is_url(loc) and isinstance(path, str):
            return cls._create_by_upload(loc, root_attrs, specs)
        return cls._create_new(path, loc, root_attrs, specs)

    @classmethod
    def _create_new(cls, path, loc: str, root_attrs: dict, specs: list[ArraySpec]) -> Self:
        """Create the group and every array at a folder or a store object."""
        try:
            group = open_group(path, mode="w-", attributes=encode_attrs({**root_attrs, "created": now()}, set()),
                               zarr_format=3)
        except (FileExistsError, zarr.errors.ContainsGroupError, zarr.errors.ContainsArrayError):
            # created concurrently by someone else
            raise StoreError("the store already exists (created concurrently); not overwriting it",
                             file=loc) from None
        store = cls(group, loc, path, "r+")
        store._create_missing(specs)
        store.update_attrs({"template_complete": True})  # also consolidates the metadata
        return store

    def _resume(self, root_attrs: dict, specs: list[ArraySpec]) -> Self:
        """This run's existing store, its missing arrays created and its template repaired."""
        if self._remote is None:  # before zarr re-reads them to consolidate
            self.check_metadata(repair=True)
        loc = self._location
        members = self._members()
        self._check_resume(root_attrs, specs, members)
        if self._remote is not None and any(sp.name not in members for sp in specs):
            # an interrupted upload: complete it through zarr, past the root's array list
            self._group = open_group(loc, mode="r+", zarr_format=3, use_consolidated=False)
        created = self._create_missing(specs, existing=members)
        self._repair_static(specs)
        if not self.attrs.get("template_complete", False):
            self.update_attrs({"template_complete": True})
        else:
            self._consolidate()
        if self._remote is not None:
            self._prefetch(self._members() if created else members)
        log.info("resuming the existing store %s", loc)
        return self

    @classmethod
    def _create_by_upload(cls, loc: str, root_attrs: dict, specs: list[ArraySpec]) -> Self:
        """Create the template at an object-store URL: built in memory, uploaded in one batch.

        Through zarr's API each array costs several sequential requests (existence checks
        of the node and its parents, then the metadata): hundreds for the result layout
        (docs/tuning.md, "Chunk I/O and object storage"). The same objects are built here in a MemoryStore
        and uploaded concurrently, between a first root metadata (``template_complete``
        false, so a run killed meanwhile resumes through :meth:`_create_missing`) and the
        final one, which also holds every array's metadata (zarr's consolidated metadata:
        a worker opening the store then reads one object instead of one per array).
        """
        from zarr.storage import MemoryStore

        objects: dict = {}
        group = zarr.open_group(MemoryStore(store_dict=objects), mode="w-", zarr_format=3,
                                attributes=encode_attrs({**root_attrs, "created": now()}, set()))
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
        store = cls(open_group(loc, mode="r+", zarr_format=3), loc, loc, "r+")
        store._prefetch(store._members())
        return store

    @classmethod
    def _try_open_existing(cls, path, loc: str) -> Self | None:
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
            if not check_store_target(path):
                return None
        try:
            group = open_group(path, mode="r+", zarr_format=3)
        except (FileNotFoundError, zarr.errors.GroupNotFoundError, zarr.errors.NodeTypeValidationError):
            if isinstance(path, (str, os.PathLike)):
                raise StoreError("the folder holds Zarr data that is not a result store group; not "
                                 "overwriting it", file=loc) from None
            return None
        except (ValueError, OSError, json.JSONDecodeError) as exc:
            raise StoreError(f"the path holds something that is not a readable result store ({exc}); "
                             "not overwriting it", file=loc) from None
        return cls(group, loc, path, "r+")

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
            diff = differences({k: old.get(k) for k in ("session", "params", "run")},
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


def check_store_target(path) -> bool:
    """Whether the folder ``path`` holds a store (a ``zarr.json``) to open; False for a
    missing or empty folder (a new store goes there). Anything else is refused, before
    any work: a file, or a folder that is not empty and holds no store.

    Raises
    ------
    StoreError
        Naming the path; nothing is touched.
    """
    p = Path(path)
    if not p.exists():
        return False
    loc = store_location(path)
    if p.is_file():
        raise StoreError("the path exists and is a file, not a result store; not overwriting it", file=loc)
    if (p / "zarr.json").is_file():
        return True
    if any(p.iterdir()):
        raise StoreError("the folder exists, is not empty and is not a result store; not overwriting it",
                         file=loc)
    return False


def _root_attrs(attrs: Mapping[str, Any], loc: str) -> dict:
    """The caller's root attributes as JSON, with ``format`` and ``template_complete`` false."""
    try:
        root_attrs = to_json(dict(attrs))
    except TypeError as exc:
        raise StoreError(str(exc), file=loc, field="attrs") from None
    root_attrs["format"] = STORE_FORMAT
    root_attrs["template_complete"] = False
    return root_attrs


def _all_specs(layout: list[ArraySpec], markers: Mapping[str, tuple]) -> list[ArraySpec]:
    """The layout's arrays and the markers' (``status/<stage>``), dimension sizes consistent."""
    sizes: dict[str, int] = {}
    for spec in layout:
        for d, n in zip(spec.dims, spec.shape):
            if sizes.setdefault(d, n) != n:
                raise ValueError(f"dimension {d} has sizes {sizes[d]} and {n} ({spec.name})")
    specs = layout + [marker_spec(stage, m, sizes) for stage, m in markers.items()]
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate array names in the layout: {sorted(n for n in names if names.count(n) > 1)}")
    return specs


def _integrity_attr(layout: list[ArraySpec], specs: list[ArraySpec], markers: Mapping[str, tuple],
                    producers: Mapping[str, str] | None) -> dict:
    """The ``integrity`` root attribute; refuses a producer whose marker cannot cover its array."""
    by_name = {s.name: s for s in specs}
    for array, stage in dict(producers or {}).items():
        if array not in by_name or stage not in markers:
            raise ValueError(f"producer {stage!r} of {array!r}: unknown array or stage")
        mspec = by_name[f"{MARKER_GROUP}/{stage}"]
        check_coverage(array, by_name[array].dims, by_name[array].chunks,
                       mspec.dims if mspec.shape else ())
    return {
        "version": INTEGRITY_VERSION, "checksum": "crc32c", "empty_chunks": "stored",
        "producers": dict(producers or {}),
        "static": sorted(s.name for s in layout if s.data is not None),
    }


def _same_dtype(actual, wanted: str) -> bool:
    if wanted == "str":
        return np.dtype(actual).kind in ("T", "O", "U") or "str" in str(actual).lower()
    try:
        return np.dtype(actual) == np.dtype(wanted)
    except TypeError:
        return False
