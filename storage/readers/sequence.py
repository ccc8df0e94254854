"""Frames stored one image file each, named by a printf pattern (:class:`ImageSequence`)."""

from __future__ import annotations

import logging
import os
import posixpath
import re
from collections import OrderedDict

import cv2
import numpy as np

from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.readers import decoding
from schlieren.storage.readers.base import FrameSource, format_ranges
from schlieren.storage.readers.decoding import _decode_image, _grey_of_raw
from schlieren.storage.readers.kinds import _DIRECTIVE, is_pattern

log = logging.getLogger(__name__)


class ImageSequence(FrameSource):
    """Frames stored one file each, named by a printf pattern.

    The first file index is detected: ``0`` if that file exists, else ``1``. Frame ``i``
    of the source is file ``pattern % (first + i)``, up to the last numbered file. A
    missing number between existing files is a frame the camera dropped
    (:attr:`dropped`): its slot is kept, so the index stays the capture time.
    """

    def __init__(self, pattern: str | os.PathLike, *, camera_name: str | None = None):
        self.path = os.fspath(pattern)
        self.camera_name = camera_name
        if not is_pattern(self.path):
            raise SessionError("not a printf pattern with one integer directive such as %05d",
                               file=self.path, camera=camera_name)
        self._dropped: tuple[int, ...] = ()
        self.first, self._count = self._scan()
        self._size = None
        self._raw_dtype = None
        self._blobs: OrderedDict[str, bytes] = OrderedDict()  # frames fetched from a URL

    #: Bytes of encoded frames a reader at a URL keeps: stages read the same frames
    #: (statistics, strobe search, deflection), and each fetch is a request.
    BLOB_CACHE_BYTES = 32 * 2 ** 20

    def _fetch(self, url: str) -> bytes:
        blob = self._blobs.get(url)
        if blob is None:
            blob = location.read_bytes(url)
            self._keep(url, blob)
        else:
            self._blobs.move_to_end(url)
        return blob

    def _keep(self, url: str, blob: bytes) -> None:
        self._blobs[url] = blob
        while sum(len(b) for b in self._blobs.values()) > self.BLOB_CACHE_BYTES and len(self._blobs) > 1:
            self._blobs.popitem(last=False)

    def file_heads(self, indices) -> list[bytes | None]:
        """The first :data:`HEADER_BYTES` of the files of frames ``indices`` at a URL, in one
        concurrent batch (None for a missing file); a file no longer than that is whole
        and kept for the reads that follow. Only for URLs."""
        urls = [self.file_of(k) for k in indices]
        heads = {u: self._blobs[u] for u in urls if u in self._blobs}
        todo = sorted(set(u for u in urls if u not in heads))
        for url, blob in zip(todo, location.read_many(todo, 0, decoding.HEADER_BYTES)):
            heads[url] = blob
            if blob is not None and len(blob) < decoding.HEADER_BYTES:
                self._keep(url, blob)
        return [heads[u] if heads[u] is None else heads[u][:decoding.HEADER_BYTES] for u in urls]

    def prefetch(self, indices) -> None:
        """Fetch the files of frames ``indices`` from a URL in one concurrent batch (kept
        for the reads that follow, within :attr:`BLOB_CACHE_BYTES`); nothing for folders."""
        if not location.is_url(self.path):
            return
        urls = [self.file_of(k) for k in sorted(set(int(k) for k in indices)) if 0 <= k < self._count]
        urls = [u for u in urls if u not in self._blobs]
        for url, blob in zip(urls, location.read_many(urls)):
            if blob is not None:  # a missing file is reported by the read itself
                self._keep(url, blob)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_blobs"] = OrderedDict()
        return state

    def _scan(self) -> tuple[int, int]:
        directory, base = (posixpath if location.is_url(self.path) else os.path).split(self.path)
        directory = directory or "."
        if _DIRECTIVE.search(directory):
            return self._scan_by_stat()
        sizes = None
        try:
            if location.is_url(directory):  # sizes come with the listing: kept for integrity checks
                sizes = location.listdir_sizes(directory)
                names = list(sizes)
            else:
                names = location.listdir(directory)
        except OSError:
            raise SessionError("the frame folder does not exist or cannot be listed",
                               file=self.path, camera=self.camera_name) from None
        m = _DIRECTIVE.search(base)
        regex = re.compile(re.escape(base[:m.start()]) + r"(\d+)" + re.escape(base[m.end():]) + r"\Z")
        indices = set()
        for name in names:
            mm = regex.match(name)
            if mm:
                k = int(mm.group(1))
                if base % k == name:  # exact printf form (width/padding)
                    indices.add(k)
        if 0 in indices:
            first = 0
        elif 1 in indices:
            first = 1
        else:
            raise SessionError(
                f"no frame file found: neither {self.path % 0} nor {self.path % 1} exists",
                file=self.path, camera=self.camera_name, field="frames[0]")
        n = max(indices) - first + 1
        self._dropped = tuple(k - first for k in range(first, first + n) if k not in indices)
        if self._dropped:
            log.info("camera %s: frame file(s) %s missing between the numbered frames of %s: taken as "
                        "frames the camera dropped", self.camera_name, format_ranges(self._dropped), self.path)
        if sizes is not None:  # 8 bytes a frame, not the listing's names (-1: a dropped frame)
            self._listed_sizes = np.fromiter((sizes.get(base % (first + i), -1) for i in range(n)), np.int64, n)
        return first, n

    def _scan_by_stat(self) -> tuple[int, int]:
        if location.isfile(self.path % 0):
            first = 0
        elif location.isfile(self.path % 1):
            first = 1
        else:
            raise SessionError(
                f"no frame file found: neither {self.path % 0} nor {self.path % 1} exists",
                file=self.path, camera=self.camera_name, field="frames[0]")
        n = 0
        while location.isfile(self.path % (first + n)):
            n += 1
        return first, n

    def __len__(self) -> int:
        return self._count

    def file_of(self, i: int) -> str:
        return self.path % (self.first + int(i))

    def listed_size(self, i: int) -> int | None:
        """Size in bytes of frame ``i``'s file as listed when the source was opened on an
        object store (None for folders or if unknown)."""
        sizes = getattr(self, "_listed_sizes", None)
        if sizes is None or not 0 <= int(i) < len(sizes) or sizes[int(i)] < 0:
            return None
        return int(sizes[int(i)])

    _one_channel = True  # every frame read so far had one channel (see one_channel)

    @property
    def one_channel(self) -> bool:
        return self._one_channel and self._raw_dtype is not None

    def read(self, i: int) -> np.ndarray:
        i = self._check_index(i)
        field = f"frames[{i}]"
        raw = _decode_image(self.file_of(i), camera_name=self.camera_name, field=field, fetch=self._fetch)
        img = _grey_of_raw(raw, file=self.file_of(i), camera=self.camera_name, field=field)
        self._remember(img, raw.dtype, i)
        if raw.ndim != 2 or raw.dtype != self._raw_dtype:
            self._one_channel = False
        return img

    def _remember(self, img: np.ndarray, raw: np.dtype, i: int) -> None:
        size = (img.shape[1], img.shape[0])
        if self._size is None:
            self._size, self._raw_dtype = size, np.dtype(raw)
        elif size != self._size:
            raise SessionError(
                f"frame is {size[0]}x{size[1]} pixels but the frames read before are "
                f"{self._size[0]}x{self._size[1]}",
                file=self.file_of(i), camera=self.camera_name, field=f"frames[{i}]")

    def read_raw(self, i: int) -> np.ndarray:
        """Frame ``i`` as stored (8/16-bit or float, grey or BGR), for lossless copies."""
        i = self._check_index(i)
        img = cv2.imread(self.file_of(i), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SessionError("cannot decode the image (corrupt or unsupported format)", file=self.file_of(i),
                               camera=self.camera_name, field=f"frames[{i}]")
        return img

    def __repr__(self) -> str:
        return f"ImageSequence({self.path!r}, first={self.first}, n={self._count})"
