"""The zarr group of a result store, opened so that every chunk read is checked."""

from __future__ import annotations

import os

import zarr

from schlieren.storage import location
from schlieren.storage.integrity import checked


def store_location(path) -> str:
    """The store's location as messages name it: a normalised folder path or URL, or the
    type (and root) of a store object."""
    if isinstance(path, (str, os.PathLike)):
        return location.normalize(path)
    root = getattr(path, "root", None)  # LocalStore and friends
    return f"{type(path).__name__}({root})" if root is not None else type(path).__name__


def open_group(path, **kwargs) -> zarr.Group:
    """``zarr.open_group`` of a folder, an fsspec URL (zarr's FsspecStore) or a store object,
    through :class:`~schlieren.storage.integrity.CheckedStore` (every chunk read checked)."""
    return zarr.open_group(checked(path, read_only=kwargs.get("mode") == "r",
                                   location=store_location(path)), **kwargs)
