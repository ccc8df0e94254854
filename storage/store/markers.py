"""Completion markers: a task's last write says that its chunks are stored.

A marker is a uint8 array ``status/<stage>`` with one chunk per task index; 1 means done.
Markers, not chunk presence, mean "done": a killed task can leave some of its chunks
written. In a folder store a marker is read and written straight from its chunk file
(storage/chunkio.py); in an object store the first question lists every marker chunk
once (see :meth:`MarkersMixin.is_done`), and a marker is sent only after the writes it
vouches for are stored.

:class:`MarkersMixin` holds these as methods of
:class:`~schlieren.storage.store.result_store.ResultStore` (it uses the store's ``array``,
``_chunk_files``, ``_remote``, ``_puts`` and ``_markers_listed``).
"""

from __future__ import annotations

import itertools
import logging
import os

import numpy as np
import zarr

from schlieren.storage import location
from schlieren.storage.chunkio import CorruptChunk, chunk_of
from schlieren.storage.errors import ChunkError, StoreError
from schlieren.storage.integrity import chunk_error
from schlieren.storage.layout import MARKER_GROUP, normalize_region

log = logging.getLogger(__name__)


class MarkersMixin:
    """Completion markers (methods of ``ResultStore``)."""

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
            put = self._puts.call(arr, name, chunk_of(region, tuple(arr.chunks), tuple(arr.shape)), ones)

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
        written holds the fill value 0 (not done), without a hop through zarr's I/O thread
        (docs/tuning.md, "Chunk I/O and object storage").

        In an object store one request per position would cost more than many tasks: the
        first question about a stage lists the
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
