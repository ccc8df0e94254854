"""Frames stored one image file each, from a glob pattern or a folder (:class:`ImageFiles`)."""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.readers.kinds import IMAGE_EXTENSIONS, _natural_key, is_glob
from schlieren.storage.readers.sequence import ImageSequence


class ImageFiles(ImageSequence):
    """Frames stored one image file each, from a glob pattern or a folder.

    The files are taken in natural name order (``img2`` before ``img10``); frame ``i`` is
    the ``i``-th. A folder takes every image file in it (:data:`IMAGE_EXTENSIONS`).
    """

    def __init__(self, spec: str | os.PathLike, *, camera_name: str | None = None):
        import glob

        self.path = os.fspath(spec)
        self.camera_name = camera_name
        self._blobs = OrderedDict()
        if location.is_url(self.path):  # a glob or a folder on object storage: one listing
            fs, path = location.filesystem(self.path)
            scheme = self.path.split("://", 1)[0] + "://"
            try:
                names = [scheme + f for f in fs.glob(path)] if is_glob(self.path) else \
                    [location.join(self.path, f) for f in location.listdir(self.path)]
            except OSError:
                names = []
            files = [f for f in names if Path(f).suffix.lower() in IMAGE_EXTENSIONS]
            what = "the pattern or folder matches no image files"
        elif is_glob(self.path):
            files = [f for f in glob.glob(self.path) if os.path.isfile(f)
                     and Path(f).suffix.lower() in IMAGE_EXTENSIONS]
            what = "the pattern matches no image files"
        elif os.path.isdir(self.path):
            files = [os.path.join(self.path, f) for f in os.listdir(self.path)
                     if Path(f).suffix.lower() in IMAGE_EXTENSIONS and os.path.isfile(os.path.join(self.path, f))]
            what = f"the folder holds no image files ({', '.join(sorted(IMAGE_EXTENSIONS))})"
        else:
            raise SessionError("the frame folder does not exist", file=self.path, camera=camera_name)
        if not files:
            raise SessionError(what, file=self.path, camera=camera_name, field="frames[0]")
        self.files = sorted(files, key=_natural_key)
        self._dropped = ()
        self.first, self._count = 0, len(self.files)
        self._size = None
        self._raw_dtype = None

    def file_of(self, i: int) -> str:
        return self.files[int(i)]

    def __repr__(self) -> str:
        return f"ImageFiles({self.path!r}, n={self._count})"
