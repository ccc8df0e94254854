"""Listing and checking a result store's stored chunks, for the integrity scans.

:func:`~schlieren.storage.integrity.scan_store` asks a store which chunks it holds (a
listing of files or objects, nothing read), reads every stored chunk to check its checksum
(``full`` scans), compares each array's ``zarr.json`` with the root's consolidated copy,
and removes damaged chunks before their tasks are recomputed.

:class:`ChunksMixin` holds these as methods of
:class:`~schlieren.storage.store.result_store.ResultStore` (it uses the store's group,
``array``, ``dims``, ``_chunk_files``, ``_members``, ``_remote``, ``_store_arg``,
``_location`` and ``_mode``).
"""

from __future__ import annotations

import json
import logging
import os

import zarr

from schlieren.storage import location
from schlieren.storage.chunkio import CorruptChunk
from schlieren.storage.errors import ChunkError, StoreError

log = logging.getLogger(__name__)


class ChunksMixin:
    """Chunk listing and checks (methods of ``ResultStore``)."""

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
