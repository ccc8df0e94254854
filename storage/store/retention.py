"""Retention: which intermediates a store keeps once the stages reading them are done.

The run's policy (``schlieren run --keep``, :mod:`schlieren.workers.retention`) may drop
``flow_raw``, ``flow`` and ``potential``: each chunk is deleted as soon as every task that
reads it has completed, and at the end of a complete run an array with no chunk left is
removed altogether, so ``xarray`` and the readers see the store without it. The root
attribute ``retention`` records the policy and the arrays whose chunks may be missing
because of it (``dropped``): for them a missing chunk under a set completion marker is
"not kept", never "lost" (the integrity scans skip it; readers say so in one line).
docs/store.md, "Retention", and benchmarks/results/retention.md (the sizes).

:class:`RetentionMixin` holds these as methods of
:class:`~schlieren.storage.store.result_store.ResultStore` (it uses the store's ``attrs``,
``update_attrs``, ``remove_chunk``, ``_folder``, ``_group``, ``_store_arg``,
``_location``, ``_arrays``, ``_layouts`` and ``_mode``).
"""

from __future__ import annotations

import logging
import os
import shutil
import warnings

import zarr

from schlieren.storage import location
from schlieren.storage.errors import ChunkError, StoreError
from schlieren.storage.integrity import dropped_of, not_kept_error

log = logging.getLogger(__name__)

__all__ = ["RetentionMixin", "not_kept_error", "dropped_of"]


class RetentionMixin:
    """The store side of retention (methods of ``ResultStore``)."""

    @property
    def dropped_arrays(self) -> frozenset[str]:
        """Arrays whose chunks the retention policy may have dropped (root attrs ``retention``)."""
        return dropped_of(self.attrs)

    @property
    def retention(self) -> dict:
        """The root attribute ``retention``: ``keep`` (the policy as given) and ``dropped``."""
        info = self.attrs.get("retention")
        return dict(info) if isinstance(info, dict) else {}

    def set_retention(self, keep: str, dropped) -> None:
        """Record the run's policy and the arrays whose chunks may be missing (coordinator only)."""
        self.update_attrs({"retention": {"keep": str(keep), "dropped": sorted(set(dropped))}})

    def drop_chunk(self, name: str, index) -> None:
        """Delete the chunk of a dropped intermediate at its producer's ``index`` (one
        camera-frame per chunk: the chunk's grid coordinates are ``index`` then zeros)."""
        ndims = self.__dict__.setdefault("_ndims", {})
        if name not in ndims:  # from its own zarr.json: the group's consolidated copy may predate it
            import json

            meta = json.loads(location.read_bytes(location.join(self._location, *name.split("/"), "zarr.json"))) \
                if isinstance(self._store_arg, (str, os.PathLike)) else self.array(name).metadata.to_dict()
            ndims[name] = len(meta["shape"])
        self.remove_chunk(name, tuple(int(i) for i in index) + (0,) * (ndims[name] - len(index)))

    def remove_arrays(self, names) -> list[str]:
        """Remove whole arrays (their metadata and any chunk) and rewrite the consolidated
        metadata without them (coordinator only, no task running); returns the names removed."""
        if self._mode == "r":
            raise StoreError("the store is open read-only", file=self._location)
        removed = []
        folder = self._folder()
        for name in names:  # the group's consolidated copy may predate arrays a resume created
            if folder is not None:
                path = location.join(folder, *name.split("/"))
                if not os.path.isdir(path):
                    continue
                shutil.rmtree(path)
            elif isinstance(self._store_arg, str) and location.is_url(self._location):
                if not location.remove_tree(location.join(self._location, name)):
                    continue
            else:  # a store object
                try:
                    del self._group[name]
                except KeyError:
                    continue
            self._arrays.pop(name, None)
            self._layouts.pop(name, None)
            removed.append(name)
        if removed:  # forced on object stores too (_consolidate keeps their metadata as it is)
            with warnings.catch_warnings():  # consolidated metadata is not in the v3 spec (see _consolidate)
                warnings.simplefilter("ignore", category=UserWarning)
                self._group = zarr.consolidate_metadata(self._group.store, zarr_format=3)
        return removed

    def _not_kept(self, name: str, coords) -> ChunkError | None:
        """The error of a missing chunk of an array the retention dropped, or None."""
        if name not in self.dropped_arrays:
            return None
        return not_kept_error(self._location, name, coords, self.retention.get("keep"))
