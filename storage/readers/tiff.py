"""Frames stored as the pages of one TIFF file (:class:`MultiPageTiff`)."""

from __future__ import annotations

import os

import numpy as np

from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.readers.base import FrameSource
from schlieren.storage.readers.decoding import _grey_of_raw


class MultiPageTiff(FrameSource):
    """Frames stored as the pages of one TIFF file (8/16-bit or float, read with Pillow)."""

    def __init__(self, path: str | os.PathLike, *, camera_name: str | None = None):
        self.path = os.fspath(path)
        self.camera_name = camera_name
        if not location.isfile(self.path):
            raise SessionError("TIFF file not found", file=self.path, camera=camera_name)
        self._file = location.stage(self.path)  # a local copy of a TIFF at a URL, once per machine
        self._size = None
        self._raw_dtype = None
        try:
            from PIL import Image

            with Image.open(self._file) as im:
                self._count = int(getattr(im, "n_frames", 1))
        except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
            raise SessionError(f"cannot read the TIFF file ({exc})", file=self.path,
                               camera=camera_name) from None

    def __len__(self) -> int:
        return self._count

    def read_raw(self, i: int) -> np.ndarray:
        """Page ``i`` as stored."""
        from PIL import Image

        i = self._check_index(i)
        if not os.path.isfile(self._file):  # unpickled on another machine
            self._file = location.stage(self.path)
        try:
            with Image.open(self._file) as im:
                im.seek(i)
                page = np.array(im)
        except (OSError, ValueError, EOFError, SyntaxError, Image.DecompressionBombError) as exc:
            raise SessionError(f"cannot decode page {i} of the TIFF file ({exc})", file=self.path,
                               camera=self.camera_name, field=f"frames[{i}]") from None
        if page.ndim == 3 and page.shape[2] in (3, 4):
            page = page[..., [2, 1, 0] + ([3] if page.shape[2] == 4 else [])]  # Pillow RGB -> OpenCV BGR
        return page

    def read(self, i: int) -> np.ndarray:
        raw = self.read_raw(i)
        img = _grey_of_raw(raw, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        size = (img.shape[1], img.shape[0])
        if self._size is None:
            self._size, self._raw_dtype = size, np.dtype(raw.dtype)
        elif size != self._size:
            raise SessionError(f"page {i} is {size[0]}x{size[1]} pixels but page 0 is "
                               f"{self._size[0]}x{self._size[1]}", file=self.path, camera=self.camera_name,
                               field=f"frames[{i}]")
        return img

    def __repr__(self) -> str:
        return f"MultiPageTiff({self.path!r}, n={self._count})"
