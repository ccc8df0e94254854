"""Frames stored one image file each, from a glob pattern or a folder (:class:`ImageFiles`)."""

from __future__ import annotations

import os
import re
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

    When every name is the same but for one number (``00003.png``, ``00004.png``,
    ``00006.png``: :func:`numbering`), the numbers are capture indices as in a printf
    pattern: frame ``i`` is number ``first + i``, and a number missing between two files
    is a frame the camera dropped (:attr:`dropped`), so later frames keep their times.
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
        self._slots: dict[int, str] | None = None
        self._naming: tuple[str, int, str, int] | None = None  # head, width, tail, first number
        self.first, self._count = 0, len(self.files)
        numbers = numbering(self.files)
        if numbers is not None:
            by_number, head, width, tail = numbers
            first = min(by_number)
            self._count = max(by_number) - first + 1
            self._slots = {n - first: f for n, f in by_number.items()}
            self._naming = (head, width, tail, first)
            self._dropped = tuple(i for i in range(self._count) if i not in self._slots)
            self.files = [self._slots[i] for i in sorted(self._slots)]
        self._size = None
        self._raw_dtype = None

    def file_of(self, i: int) -> str:
        if self._slots is None:
            return self.files[int(i)]
        f = self._slots.get(int(i))
        if f is None:  # a dropped frame: the name it would have
            head, width, tail, first = self._naming
            f = f"{head}{first + int(i):0{width}d}{tail}"
        return f

    def __repr__(self) -> str:
        return f"ImageFiles({self.path!r}, n={self._count})"


_NUMBERED = re.compile(r"\A(.*?)(\d+)(\D*)\Z")


def numbering(files: list[str]):
    """``({number: file}, head, width, tail)`` if every file's name is one text around one
    number (the last run of digits: ``cam0/frame_00041.png``), else None. Number ``n``'s
    name is ``f"{head}{n:0{width}d}{tail}"`` (zero-padded like the others when they all
    share one width, else ``width`` 0)."""
    parts = [_NUMBERED.match(f) for f in files]
    if not parts or any(m is None for m in parts):
        return None
    heads = {m.group(1) for m in parts}
    tails = {m.group(3) for m in parts}
    if len(heads) != 1 or len(tails) != 1:
        return None
    by_number = {int(m.group(2)): f for m, f in zip(parts, files)}
    if len(by_number) != len(files):  # 7.png and 007.png
        return None
    widths = {len(m.group(2)) for m in parts}
    width = widths.pop() if len(widths) == 1 else 0
    return by_number, heads.pop(), width, tails.pop()
