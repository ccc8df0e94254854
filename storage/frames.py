"""Lazy random-access readers for camera frames and reference images.

A camera's frames are an image sequence (a printf pattern ``cam00/frames/%05d.png``, a
glob pattern ``cam00/frames/*.tif`` or a folder ``cam00/frames/``, images in natural name
order; 8/16-bit PNG or TIFF, colour converted to grey), a multi-page TIFF file, or a video
file read with OpenCV (:data:`VIDEO_EXTENSIONS`, the one list every reader uses).
Interlaced video is split into its two fields (:class:`InterlacedFields`). Frames are returned as ``float32`` grey levels of the raw values
(a 16-bit frame keeps its 0..65535 numbers; nothing is rescaled or quantised, since BOS
deflections are sub-pixel).

Readers open their files lazily and drop open handles when pickled, so a
:class:`FrameSource` can be built on the coordinator and shipped to a worker.

Paths may be fsspec URLs (``s3://bucket/capture/cam00/frames/%05d.png``): image files
are then fetched and decoded from memory (one request per frame, the same decoder as
for files), and a video is staged once per machine into a local file that OpenCV reads
(:func:`schlieren.storage.location.stage`).

Errors are :class:`~schlieren.storage.errors.SessionError` naming the file, the camera
and the frame index (as ``frames[i]``, 0-based within the source).

Dropped frames: a camera that drops a frame leaves a time slot without one. A source's
index is the time slot (frame ``i`` was exposed at ``i / frame_rate`` after frame 0), and
:attr:`FrameSource.dropped` lists the slots that hold no frame: the missing numbers of a
printf-numbered image sequence (``00041.png`` absent between ``00040.png`` and
``00042.png``) and the gaps in a video's presentation timestamps (a step of more than
1.5 frame intervals, :func:`slots_of_timestamps`). Reading a dropped slot raises
:class:`~schlieren.storage.errors.DroppedFrame`; the run excludes it from the
reconstruction and the frames after the gap keep their true times.
"""

from __future__ import annotations

import io
import logging
import os
import posixpath
import re
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from schlieren.storage import location
from schlieren.storage.errors import DroppedFrame, SessionError

__all__ = [
    "FrameSource",
    "slots_of_timestamps",
    "format_ranges",
    "ImageSequence",
    "ImageFiles",
    "MultiPageTiff",
    "InterlacedFields",
    "VideoFrames",
    "frames_kind",
    "is_glob",
    "open_frames",
    "read_reference",
    "read_image",
    "is_pattern",
    "is_video",
    "image_header",
    "image_incomplete",
    "images_incomplete",
    "image_headers",
    "VIDEO_EXTENSIONS",
    "IMAGE_EXTENSIONS",
]

log = logging.getLogger(__name__)

#: Video containers read with OpenCV/FFmpeg, for every reader (session, init, calibrate):
#: camcorder AVCHD (.mts, .m2ts), broadcast MXF and the common desktop containers.
VIDEO_EXTENSIONS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg",
                              ".wmv", ".mj2", ".ogv", ".mts", ".m2ts", ".mxf"})
IMAGE_EXTENSIONS = frozenset({".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm",
                              ".exr"})
TIFF_EXTENSIONS = frozenset({".tif", ".tiff"})

#: Largest jump ahead that a video reader decodes through instead of seeking.
FORWARD_GRAB_LIMIT = 16

# printf integer directive: %d, %5d, %05d (flags '0' only; no '-' or '+')
_DIRECTIVE = re.compile(r"%(0?)(\d*)d")


def is_pattern(spec: str | os.PathLike) -> bool:
    """True if ``spec`` holds exactly one printf integer directive (``%05d``)."""
    return len(_DIRECTIVE.findall(os.fspath(spec))) == 1


def is_video(spec: str | os.PathLike) -> bool:
    """True if ``spec`` names a video file (by its extension) rather than a pattern or image."""
    return (not is_pattern(spec)) and Path(os.fspath(spec)).suffix.lower() in VIDEO_EXTENSIONS


def is_glob(spec: str | os.PathLike) -> bool:
    """True if ``spec`` is a glob pattern (``*``, ``?`` or ``[``) of image files."""
    return not is_pattern(spec) and any(ch in os.fspath(spec) for ch in "*?[")


def frames_kind(spec: str | os.PathLike) -> str | None:
    """How a frames specification is read: ``"sequence"`` (printf pattern), ``"glob"``,
    ``"folder"`` (an existing folder, or a path ending in a slash), ``"video"``,
    ``"tiff"`` (a multi-page TIFF file), ``"image"`` (one other image file) or None."""
    text = os.fspath(spec)
    if is_pattern(text):
        return "sequence"
    if is_glob(text):
        return "glob"
    if text.endswith(("/", os.sep)) or os.path.isdir(text) or _is_remote_folder(text):
        return "folder"
    suffix = Path(text).suffix.lower()
    if suffix in VIDEO_EXTENSIONS:
        return "video"
    if suffix in TIFF_EXTENSIONS:
        return "tiff"
    if suffix in IMAGE_EXTENSIONS:
        return "image"
    return None


def _is_remote_folder(text: str) -> bool:
    """A URL without a file suffix under which objects exist (a folder on object storage)."""
    return location.is_url(text) and not Path(text).suffix and location.exists(text) \
        and not location.isfile(text)


def format_ranges(indices) -> str:
    """``"5, 9-11"`` for indices 5, 9, 10, 11 (sorted)."""
    out: list[list[int]] = []
    for k in sorted(int(i) for i in indices):
        if out and k == out[-1][1] + 1:
            out[-1][1] = k
        else:
            out.append([k, k])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in out)


def slots_of_timestamps(ms, *, gap: float = 1.5) -> np.ndarray:
    """The time slot of every decoded frame of a video, from its presentation timestamps.

    A step between consecutive timestamps of more than ``gap`` frame intervals means the
    camera dropped frames there: ``round(step / interval) - 1`` of them. The interval is
    the mean of the steps below ``gap`` times their median (robust to containers that
    round timestamps to milliseconds, such as Matroska at 29.97 frames/s).

    Parameters
    ----------
    ms : sequence of float
        Presentation time of each decoded frame, milliseconds, in decoding order.

    Returns
    -------
    ndarray of int64
        Slot of each frame (``arange(n)`` without gaps, or when the timestamps are not
        increasing, so carry no timing).
    """
    t = np.asarray(ms, dtype=np.float64)
    n = t.size
    if n < 3:
        return np.arange(n, dtype=np.int64)
    step = np.diff(t)
    if not np.all(np.isfinite(step)) or np.any(step <= 0):
        return np.arange(n, dtype=np.int64)
    med = float(np.median(step))
    period = float(np.mean(step[step <= gap * med]))
    inc = np.where(step > gap * period, np.maximum(np.rint(step / period), 1), 1).astype(np.int64)
    return np.concatenate([[0], np.cumsum(inc)]).astype(np.int64)


def _natural_key(path: str):
    """Name order with numbers compared as numbers (``img2`` before ``img10``)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", os.path.basename(path))]


def _to_grey(img: np.ndarray) -> np.ndarray:
    """Grey levels as float32; colour converted with OpenCV's luma weights (no rounding)."""
    if img.ndim == 3:
        if img.shape[2] in (3, 4) and np.array_equal(img[..., 0], img[..., 1]) \
                and np.array_equal(img[..., 0], img[..., 2]):
            # grey stored as colour (typical of mono cameras in videos): exact, no weighting
            return np.asarray(img[..., 0], dtype=np.float32)
        # convert in float32 so the grey levels are not rounded back to integers
        img = img.astype(np.float32, copy=False)
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            raise ValueError(f"unsupported channel count {img.shape[2]}")
    return np.asarray(img, dtype=np.float32)


def _grey_of_raw(img: np.ndarray, *, file: str, camera: str | None, field: str | None) -> np.ndarray:
    try:
        return _to_grey(img)
    except (ValueError, cv2.error) as exc:
        raise SessionError(f"cannot convert the image to grey levels ({exc})", file=file,
                           camera=camera, field=field) from None


def read_image(path: str | os.PathLike, *, camera_name: str | None = None,
               field: str | None = None, fetch=None) -> tuple[np.ndarray, np.dtype]:
    """Read one image file as float32 grey levels.

    Parameters
    ----------
    path : path-like
        PNG/TIFF (8 or 16 bit, grey or colour) or any format OpenCV reads.
    camera_name, field : str, optional
        Named in the error message if the file is missing or cannot be decoded.
    fetch : callable, optional
        ``fetch(url) -> bytes`` for a URL (default :func:`schlieren.storage.location.read_bytes`).

    Returns
    -------
    image : ndarray, shape (H, W), float32
        Grey levels of the raw values (16-bit values kept as numbers).
    raw_dtype : numpy dtype
        The file's sample type (uint8, uint16, float32, ...).
    """
    img = _decode_image(path, camera_name=camera_name, field=field, fetch=fetch)
    return _grey_of_raw(img, file=os.fspath(path), camera=camera_name, field=field), img.dtype


def _decode_image(path, *, camera_name: str | None, field: str | None, fetch=None) -> np.ndarray:
    """The samples of one image file as stored (any depth and channels; :func:`read_image`)."""
    p = os.fspath(path)
    if location.is_url(p):
        try:
            blob = (fetch or location.read_bytes)(p)
        except (FileNotFoundError, IsADirectoryError):
            raise SessionError("file not found", file=p, camera=camera_name, field=field) from None
        except OSError as exc:
            raise SessionError(f"cannot read the file ({exc})", file=p, camera=camera_name, field=field) from None
        img = cv2.imdecode(np.frombuffer(blob, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if blob else None
    elif not os.path.isfile(p):
        raise SessionError("file not found", file=p, camera=camera_name, field=field)
    else:
        img = cv2.imread(p, cv2.IMREAD_UNCHANGED)  # any depth, any channels, as stored
    if img is None or img.size == 0:
        raise SessionError("cannot decode the image (corrupt or unsupported format)", file=p,
                           camera=camera_name, field=field)
    return img


def image_header(path: str | os.PathLike, head: bytes | None = None) -> tuple[int, int] | None:
    """``(width, height)`` from an image file's header without decoding it, or None.

    Uses Pillow's lazy opener (reads a few bytes). None means the file is not an image
    that Pillow recognises (missing, garbage, unsupported): callers decide whether to
    fall back to a full decode.
    """
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return None
    p = os.fspath(path)
    try:
        # an object store: the first 64 KiB in one ranged request hold any usual header
        # (``head``: those bytes, already fetched with others'; see :func:`image_headers`)
        if head is None and location.is_url(p):
            head = location.read_bytes(p, 0, HEADER_BYTES)
        src = io.BytesIO(head) if head is not None else p
        with Image.open(src) as im:
            return int(im.size[0]), int(im.size[1])
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None


_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def _incomplete(head: bytes, tail: bytes, size: int, tiff_tags=None) -> str | None:
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return None if tail.endswith(_PNG_END) else "the PNG ends before its IEND chunk"
    if head.startswith(b"\xff\xd8"):
        return None if b"\xff\xd9" in tail else "the JPEG has no end-of-image marker"
    if head[:4] in (b"II*\x00", b"MM\x00*") and tiff_tags is not None:
        offsets, counts = tiff_tags
        if offsets and counts:
            end = max(int(o) + int(c) for o, c in zip(offsets, counts))
            if end > size:
                return f"the TIFF's image data ends at byte {end}, past the file's {size} bytes"
    return None


def image_incomplete(path: str | os.PathLike) -> str | None:
    """Why an image file is cut short, or None if its structure is complete.

    Cheap structural checks that read a few bytes, not the pixels: a PNG must end with
    its ``IEND`` chunk, a JPEG with its end-of-image marker, a TIFF's strips or tiles
    must lie inside the file. Other formats are not checked (None).
    """
    p = os.fspath(path)
    try:
        size = os.path.getsize(p)
        with open(p, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError as exc:
        return f"cannot read it ({exc.strerror or exc})"
    tags = None
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        try:
            from PIL import Image

            with Image.open(p) as im:
                t = im.tag_v2
                tags = (t.get(273) or t.get(324), t.get(279) or t.get(325))
        except Exception as exc:  # noqa: BLE001 - Pillow raises many types for broken files
            return f"the TIFF header does not parse ({type(exc).__name__})"
    return _incomplete(head, tail, size, tags)


def images_incomplete(paths: list[str], sizes: list[int | None] | None = None,
                      heads: list[bytes | None] | None = None) -> list[str | None]:
    """:func:`image_incomplete` of each file; on an object store the PNG and JPEG starts and
    ends are fetched in one concurrent batch (TIFF strips are not checked there).

    ``sizes``: the files' sizes if known (e.g. from a folder listing), else asked per file;
    ``heads``: their leading bytes if already fetched (a head as long as its file's size is
    the whole file: its end needs no request either)."""
    if not paths or not location.is_url(os.fspath(paths[0])):
        return [image_incomplete(p) for p in paths]
    locs = [os.fspath(p) for p in paths]
    try:
        sizes = list(sizes) if sizes is not None else [None] * len(locs)
        if any(n is None for n in sizes):
            fs, _ = location.filesystem(locs[0])
            sizes = [int(fs.size(location.filesystem(p)[1])) if n is None else int(n) for p, n in zip(locs, sizes)]
        heads = list(heads) if heads is not None else [None] * len(locs)
        tails = [h[-64:] if h is not None and len(h) == n else None for h, n in zip(heads, sizes)]
        need_head = [j for j, h in enumerate(heads) if h is None]
        need_tail = [j for j, t in enumerate(tails) if t is None]
        got = location.read_ranges([locs[j] for j in need_head + need_tail],
                                   [0] * len(need_head) + [max(0, sizes[j] - 64) for j in need_tail],
                                   [8] * len(need_head) + [sizes[j] for j in need_tail])
        for j, blob in zip(need_head, got):
            heads[j] = blob
        for j, blob in zip(need_tail, got[len(need_head):]):
            tails[j] = blob
    except Exception as exc:  # noqa: BLE001 - a store that cannot answer: decoding will tell
        log.debug("completeness of %d remote frames not checked: %s", len(paths), exc)
        return [None] * len(paths)
    return [_incomplete(h or b"", t or b"", n) for h, t, n in zip(heads, tails, sizes)]


#: Leading bytes of an image file fetched from an object store to read its header.
HEADER_BYTES = 1 << 16


def image_headers(paths: list[str], heads: list[bytes | None] | None = None) -> list[tuple[int, int] | None]:
    """:func:`image_header` of each file; from an object store in one concurrent batch
    (``heads``: their first :data:`HEADER_BYTES`, if already fetched)."""
    if not paths or not location.is_url(os.fspath(paths[0])):
        return [image_header(p) for p in paths]
    if heads is None:
        heads = location.read_many([os.fspath(p) for p in paths], 0, HEADER_BYTES)
    return [image_header(p, h) if h is not None else None for p, h in zip(paths, heads)]


class FrameSource:
    """Random access to the frames of one camera.

    Attributes
    ----------
    path : str
        The pattern or video file.
    camera_name : str or None
    """

    path: str
    camera_name: str | None

    def __len__(self) -> int:  # pragma: no cover - abstract
        raise TypeError("FrameSource is abstract")

    def read(self, i: int) -> np.ndarray:  # pragma: no cover - abstract
        """Frame ``i`` (0-based) as float32 grey levels, shape (H, W)."""
        raise TypeError("FrameSource is abstract")

    def file_of(self, i: int) -> str:
        """The file holding frame ``i`` (the video file for videos)."""
        return self.path

    def prefetch(self, indices) -> None:
        """Frames about to be read (a hint: image files at a URL are fetched together)."""

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels (from frame 0)."""
        self._ensure_info()
        return self._size

    @property
    def raw_dtype(self) -> np.dtype:
        """Sample type of the stored frames (uint8, uint16, ...)."""
        self._ensure_info()
        return self._raw_dtype

    @property
    def one_channel(self) -> bool:
        """Whether every frame read so far was stored as one grey channel of :attr:`raw_dtype`,
        so that its grey levels (:meth:`read`) are its samples themselves, converted to
        float32 (not weighted colour); False when unknown."""
        return False

    def _ensure_info(self) -> None:
        if getattr(self, "_size", None) is None:
            self.read(0)

    @property
    def dropped(self) -> tuple[int, ...]:
        """Time slots (frame indices) the camera dropped: no frame was stored for them."""
        return getattr(self, "_dropped", ())

    def present(self) -> list[int]:
        """The indices that hold a frame (every index but the :attr:`dropped` ones)."""
        gone = set(self.dropped)
        return [i for i in range(len(self)) if i not in gone]

    def _check_index(self, i: int) -> int:
        i = int(i)
        n = len(self)
        if not 0 <= i < n:
            raise SessionError(f"frame index {i} is outside the {n} frames available",
                               file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        if i in self.dropped:
            raise DroppedFrame("the camera dropped this frame (a gap in the numbered files or the video's "
                               "timestamps); it is excluded from the reconstruction",
                               file=self.file_of(i), camera=self.camera_name, field=f"frames[{i}]")
        return i

    def __iter__(self):
        for i in range(len(self)):
            yield self.read(i)


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
        for url, blob in zip(todo, location.read_many(todo, 0, HEADER_BYTES)):
            heads[url] = blob
            if blob is not None and len(blob) < HEADER_BYTES:
                self._keep(url, blob)
        return [heads[u] if heads[u] is None else heads[u][:HEADER_BYTES] for u in urls]

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
        except (OSError, ValueError, SyntaxError) as exc:
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
        except (OSError, ValueError, EOFError, SyntaxError) as exc:
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


class InterlacedFields(FrameSource):
    """The two fields of every interlaced frame, as frames of their own (twice as many).

    Field ``2 f + k`` of frame ``f`` holds the rows of parity ``k`` (``top_first``: even
    rows first, ``bottom_first``: odd rows first); the missing rows are the mean of the
    field rows above and below (linear "bob" deinterlacing), so every field keeps the
    full image size and the camera's calibration. Rows of a field are exposed one field
    line time apart, as the session's rolling-shutter model expects (docs/session.md).
    """

    def __init__(self, frames: FrameSource, order: str = "top_first"):
        if order not in ("top_first", "bottom_first"):
            raise ValueError(f"order must be top_first or bottom_first, got {order!r}")
        self.frames = frames
        self.order = order
        self.path = frames.path
        self.camera_name = frames.camera_name
        self._size = None
        self._raw_dtype = None

    def __len__(self) -> int:
        return 2 * len(self.frames)

    @property
    def dropped(self) -> tuple[int, ...]:
        """Both fields of every frame the camera dropped."""
        return tuple(2 * d + k for d in getattr(self.frames, "dropped", ()) for k in (0, 1))

    def file_of(self, i: int) -> str:
        return self.frames.file_of(int(i) // 2)

    @property
    def size(self) -> tuple[int, int]:
        return self.frames.size

    @property
    def raw_dtype(self) -> np.dtype:
        return self.frames.raw_dtype

    def parity(self, i: int) -> int:
        """Row parity (0 = even rows) held by field ``i``."""
        return (int(i) % 2) ^ (self.order == "bottom_first")

    def read(self, i: int) -> np.ndarray:
        i = self._check_index(i)
        return bob_field(self.frames.read(i // 2), self.parity(i))

    def close(self) -> None:
        if hasattr(self.frames, "close"):
            self.frames.close()

    def __repr__(self) -> str:
        return f"InterlacedFields({self.frames!r}, {self.order})"


def bob_field(frame: np.ndarray, parity: int) -> np.ndarray:
    """The field of rows ``parity, parity + 2, ...`` of ``frame`` at full height: missing
    rows are the mean of their neighbours in the field (the edge row repeats its neighbour)."""
    img = np.asarray(frame, dtype=np.float32)
    out = img.copy()
    h = img.shape[0]
    for r in range(1 - parity, h, 2):
        up, down = r - 1, r + 1
        if up < 0:
            out[r] = img[down]
        elif down >= h:
            out[r] = img[up]
        else:
            out[r] = 0.5 * (img[up] + img[down])
    return out


class VideoFrames(FrameSource):
    """Frames of a video file, decoded with ``cv2.VideoCapture``.

    Random access seeks with ``CAP_PROP_POS_FRAMES``; reads in increasing order (or short
    jumps ahead, up to ``FORWARD_GRAB_LIMIT`` frames) reuse the open decoder. If a seek is
    refused or lands elsewhere, the reader reopens the file and decodes sequentially up to
    the frame. A frame that cannot be decoded raises
    :class:`SessionError` naming the file, the camera and the frame index. A video at a
    URL is decoded from a local copy staged once per machine.

    Indices are time slots: the first use of the length, :attr:`dropped` or a frame
    decodes the whole video once (:meth:`scan`) to read every frame's presentation
    timestamp, and a gap in them is a dropped frame (:func:`slots_of_timestamps`). A run
    scans each video once before scheduling and hands the result (``slots``) to its
    workers, which then decode only the frames they use.

    Parameters
    ----------
    slots : (int, tuple of int), optional
        ``(number of slots, dropped slots)`` from an earlier :meth:`scan` of this file.
    """

    def __init__(self, path: str | os.PathLike, *, camera_name: str | None = None,
                 slots: tuple[int, tuple[int, ...]] | None = None):
        self.path = os.fspath(path)
        self.camera_name = camera_name
        self._file = None  # the local file OpenCV reads (a staged copy for a URL)
        if not location.isfile(self.path):
            raise SessionError("video file not found", file=self.path, camera=camera_name)
        self._cap = None
        self._next = 0  # index of the decoded frame the open decoder returns next
        self._size = None
        self._raw_dtype = None
        cap = self._open()
        #: Frames the container's header announces (its duration times its rate).
        self.header_count = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        self._slots: tuple[int, tuple[int, ...]] | None = None
        if slots is not None:
            self._set_slots(int(slots[0]), tuple(int(k) for k in slots[1]))

    def _set_slots(self, n: int, dropped: tuple[int, ...]) -> None:
        self._slots = (n, dropped)
        self._count = n
        self._dropped_sorted = np.asarray(dropped, dtype=np.int64)

    def scan(self) -> tuple[int, tuple[int, ...]]:
        """Decode every frame once for its timestamp: ``(number of slots, dropped slots)``.

        If decoding stops before the frames the header announces (a corrupt or truncated
        video), drops are looked for among the frames that decode, and the slots after
        them are taken as present: reading one raises the decoding error naming it.
        """
        if self._slots is None:
            self.close()
            cap = self._open()
            ms = []
            while cap.grab():
                ms.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
            self.close()
            self._finish_scan(ms)
        return self._slots

    def _finish_scan(self, ms: list[float]) -> None:
        slot = slots_of_timestamps(ms)
        n = int(slot[-1]) + 1 if len(ms) else 0
        have = set(int(k) for k in slot)
        dropped = tuple(k for k in range(n) if k not in have)
        if n < self.header_count:
            log.warning("camera %s: %s: decoding stops after %d of the %d frames its header announces",
                        self.camera_name, self.path, len(ms), self.header_count)
            n = self.header_count
        if dropped:
            log.warning("camera %s: the timestamps of %s skip frame(s) %s: taken as frames the camera "
                        "dropped", self.camera_name, self.path, format_ranges(dropped))
        self._set_slots(n, dropped)

    @property
    def dropped(self) -> tuple[int, ...]:
        return self.scan()[1]

    def _check_index(self, i: int) -> int:
        if int(i) == 0 and self._slots is None and self.header_count > 0:
            return 0  # slot 0 holds the first decoded frame: no scan needed (a reference's size)
        return super()._check_index(i)

    def _decoded_index(self, i: int) -> int:
        """The decoding-order index of the frame in slot ``i`` (not a dropped one)."""
        if i == 0:
            return 0
        self.scan()
        return i - int(np.searchsorted(self._dropped_sorted, i))

    # -- handle management ------------------------------------------------------
    def _local(self) -> str:
        if self._file is None or not os.path.isfile(self._file):  # unpickled on another machine
            try:
                self._file = location.stage(self.path)
            except OSError as exc:
                raise SessionError(f"cannot fetch the video ({exc})", file=self.path,
                                   camera=self.camera_name) from None
        return self._file

    def _open(self) -> cv2.VideoCapture:
        if self._cap is None:
            cap = cv2.VideoCapture(self._local())
            if not cap.isOpened():
                raise SessionError("cannot open the video (corrupt or unsupported codec)",
                                   file=self.path, camera=self.camera_name)
            self._cap = cap
            self._next = 0
        return self._cap

    def close(self) -> None:
        """Release the decoder (reopened on the next read)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
            self._next = 0

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_cap"] = None
        state["_next"] = 0
        return state

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __len__(self) -> int:
        return self.scan()[0]

    # -- reading --------------------------------------------------------------
    def _decode_error(self, i: int, wanted: int | None = None) -> SessionError:
        self.close()
        extra = f" while seeking to frame {wanted}" if wanted is not None and wanted != i else ""
        return SessionError(f"cannot decode frame {i} of the video (corrupt or truncated){extra}",
                            file=self.path, camera=self.camera_name, field=f"frames[{i}]")

    def _seek(self, i: int) -> bool:
        cap = self._open()
        if self._next == i:
            return True
        if self._next < i <= self._next + FORWARD_GRAB_LIMIT:
            # a short jump ahead: decoding forward is cheaper than OpenCV's seek, which
            # re-decodes from a keyframe (or the start) every time
            for k in range(self._next, i):
                if not cap.grab():
                    raise self._decode_error(k, i)
            self._next = i
            return True
        if cap.set(cv2.CAP_PROP_POS_FRAMES, float(i)):
            pos = int(round(cap.get(cv2.CAP_PROP_POS_FRAMES)))
            if pos == i:
                self._next = i
                return True
        # sequential fallback: reopen and skip forward
        log.debug("seek to frame %d of %s failed; decoding sequentially", i, self.path)
        self.close()
        cap = self._open()
        for k in range(i):
            if not cap.grab():
                raise self._decode_error(k, i)
        self._next = i
        return True

    def read(self, i: int) -> np.ndarray:
        i = self._check_index(i)
        img = self.read_raw(i)
        grey = _grey_of_raw(img, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        size = (grey.shape[1], grey.shape[0])
        if self._size is None:
            self._size, self._raw_dtype = size, np.dtype(img.dtype)
        return grey

    def read_raw(self, i: int) -> np.ndarray:
        """Frame ``i`` as decoded (BGR or grey, 8/16-bit), for lossless copies."""
        i = self._check_index(i)
        j = self._decoded_index(i)
        self._seek(j)
        ok, img = self._cap.read()
        if not ok or img is None or img.size == 0:
            raise self._decode_error(i)
        self._next = j + 1
        return img

    def iter_sequential(self):
        """Decode every frame in order (faster than random access), as float32 grey: the
        frames of :meth:`present`, one per slot that holds a frame. Not yet scanned, the
        pass also reads the timestamps (:meth:`scan`), so the video is decoded once."""
        known = self._slots is not None
        present = self.present() if known else None
        self.close()
        cap = self._open()
        ms: list[float] = []
        j = 0
        while present is None or j < len(present):
            ok, img = cap.read()
            if not ok or img is None:
                if present is None:
                    break
                raise self._decode_error(present[j])
            ms.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
            i = present[j] if present is not None else j
            j += 1
            self._next = j
            yield _grey_of_raw(img, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        self.close()
        if not known:
            self._finish_scan(ms)
            present = self.present()
            if len(ms) < len(present):
                raise self._decode_error(present[len(ms)])

    def __repr__(self) -> str:
        n = self._slots[0] if self._slots is not None else self.header_count
        return f"VideoFrames({self.path!r}, n={n})"


def _source_path_and_name(source, camera_name):
    # a CameraSource (storage.session) or anything with .frames/.name, or a path
    if hasattr(source, "frames") and hasattr(source, "name") and not isinstance(source, (str, os.PathLike)):
        return os.fspath(source.frames), (camera_name if camera_name is not None else source.name)
    return os.fspath(source), camera_name


def open_frames(source, *, camera_name: str | None = None,
                slots: tuple[int, tuple[int, ...]] | None = None) -> FrameSource:
    """Open a camera's frames for random access.

    Parameters
    ----------
    source : str, path-like or CameraSource
        An image sequence (printf pattern, glob pattern or folder), a multi-page TIFF or a
        video file; a :class:`~schlieren.storage.session.CameraSource` gives its ``frames``
        (split into fields when its ``interlaced`` is set).
    camera_name : str, optional
        Named in error messages (defaults to the CameraSource's name).
    slots : (int, tuple of int), optional
        A video's :meth:`VideoFrames.scan` result, known from an earlier scan (it is not
        decoded again).

    Returns
    -------
    FrameSource
        ``len(src)`` frames; ``src.read(i)`` -> float32 (H, W); ``src.size`` = (W, H);
        ``src.raw_dtype``.
    """
    path, name = _source_path_and_name(source, camera_name)
    kind = frames_kind(path)
    if kind == "sequence":
        src = ImageSequence(path, camera_name=name)
    elif kind in ("glob", "folder"):
        src = ImageFiles(path, camera_name=name)
    elif kind == "video":
        src = VideoFrames(path, camera_name=name, slots=slots)
    elif kind == "tiff":
        src = MultiPageTiff(path, camera_name=name)
    else:
        raise SessionError(
            "frames must be an image sequence (printf pattern cam00/frames/%05d.png, glob pattern "
            "cam00/frames/*.png or a folder), a multi-page TIFF or a video file "
            f"({', '.join(sorted(VIDEO_EXTENSIONS))})", file=path, camera=name)
    order = getattr(source, "interlaced", None)
    return InterlacedFields(src, order) if order else src


def read_reference(source, *, camera_name: str | None = None, parity: int | None = None) -> np.ndarray:
    """The reference (no-flow background) image of a camera, as float32 grey levels.

    Parameters
    ----------
    source : str, path-like or CameraSource
        One image file, or any frames specification of :func:`open_frames` (every frame is
        averaged); a CameraSource gives its ``reference`` (fields of interlaced cameras).
    parity : {0, 1}, optional
        For an interlaced camera: the reference of the fields of this row parity (every
        reference frame read as that field, :func:`bob_field`), so that a field is compared
        with a reference deinterlaced exactly as it is. None: both fields averaged.
    camera_name : str, optional

    Returns
    -------
    reference : ndarray, shape (H, W), float32
        Averages are accumulated in float64 and rounded to float32 once.
    """
    order = None
    if hasattr(source, "reference") and hasattr(source, "name") and not isinstance(source, (str, os.PathLike)):
        path = os.fspath(source.reference)
        name = camera_name if camera_name is not None else source.name
        order = getattr(source, "interlaced", None)
    else:
        path, name = os.fspath(source), camera_name
    kind = frames_kind(path)
    if order and parity is not None:
        if kind in ("sequence", "glob", "folder", "tiff", "video"):
            src = open_frames(path, camera_name=name)
            return _average((bob_field(src.read(i), parity) for i in src.present()), path, name)
        img, _ = read_image(path, camera_name=name, field="reference")
        return bob_field(img, parity)
    if kind == "video" and not order:
        vid = VideoFrames(path, camera_name=name)
        return _average(vid.iter_sequential(), path, name)
    if kind in ("sequence", "glob", "folder", "tiff", "video"):
        src = open_frames(path, camera_name=name)
        if order:  # the mean of both fields of every reference frame, like the frames
            src = InterlacedFields(src, order)
        return _average((src.read(i) for i in src.present()), path, name)
    img, _ = read_image(path, camera_name=name, field="reference")
    return img


def _average(frames, path: str, name: str | None) -> np.ndarray:
    acc = None
    n = 0
    for img in frames:
        if acc is None:
            acc = np.zeros(img.shape, dtype=np.float64)
        elif img.shape != acc.shape:
            raise SessionError(f"reference frame {n} has shape {img.shape}, frame 0 has {acc.shape}",
                               file=path, camera=name, field=f"reference[{n}]")
        acc += img
        n += 1
    if n == 0:
        raise SessionError("the reference holds no frames", file=path, camera=name, field="reference")
    return (acc / n).astype(np.float32)
