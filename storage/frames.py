"""Lazy random-access readers for camera frames and reference images.

A camera's frames are either an image sequence named by a printf pattern
(``cam00/frames/%05d.png``; 8/16-bit PNG or TIFF, colour converted to grey) or a video
file read with OpenCV. Frames are returned as ``float32`` grey levels of the raw values
(a 16-bit frame keeps its 0..65535 numbers; nothing is rescaled or quantised, since BOS
deflections are sub-pixel).

Readers open their files lazily and drop open handles when pickled, so a
:class:`FrameSource` can be built on the coordinator and shipped to a worker.

Errors are :class:`~schlieren.storage.errors.SessionError` naming the file, the camera
and the frame index (as ``frames[i]``, 0-based within the source).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import cv2
import numpy as np

from schlieren.storage.errors import SessionError

__all__ = [
    "FrameSource",
    "ImageSequence",
    "VideoFrames",
    "open_frames",
    "read_reference",
    "read_image",
    "is_pattern",
    "is_video",
    "image_header",
    "image_incomplete",
    "VIDEO_EXTENSIONS",
    "IMAGE_EXTENSIONS",
]

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg",
                              ".wmv", ".mj2", ".ogv"})
IMAGE_EXTENSIONS = frozenset({".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm",
                              ".exr"})

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
               field: str | None = None) -> tuple[np.ndarray, np.dtype]:
    """Read one image file as float32 grey levels.

    Parameters
    ----------
    path : path-like
        PNG/TIFF (8 or 16 bit, grey or colour) or any format OpenCV reads.
    camera_name, field : str, optional
        Named in the error message if the file is missing or cannot be decoded.

    Returns
    -------
    image : ndarray, shape (H, W), float32
        Grey levels of the raw values (16-bit values kept as numbers).
    raw_dtype : numpy dtype
        The file's sample type (uint8, uint16, float32, ...).
    """
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise SessionError("file not found", file=p, camera=camera_name, field=field)
    img = cv2.imread(p, cv2.IMREAD_UNCHANGED)  # any depth, any channels, as stored
    if img is None or img.size == 0:
        raise SessionError("cannot decode the image (corrupt or unsupported format)", file=p,
                           camera=camera_name, field=field)
    return _grey_of_raw(img, file=p, camera=camera_name, field=field), img.dtype


def image_header(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(width, height)`` from an image file's header without decoding it, or None.

    Uses Pillow's lazy opener (reads a few bytes). None means the file is not an image
    that Pillow recognises (missing, garbage, unsupported): callers decide whether to
    fall back to a full decode.
    """
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return None
    try:
        with Image.open(os.fspath(path)) as im:
            return int(im.size[0]), int(im.size[1])
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None


_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


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
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return None if tail.endswith(_PNG_END) else "the PNG ends before its IEND chunk"
    if head.startswith(b"\xff\xd8"):
        return None if b"\xff\xd9" in tail else "the JPEG has no end-of-image marker"
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        try:
            from PIL import Image

            with Image.open(p) as im:
                tags = im.tag_v2
                offsets = tags.get(273) or tags.get(324)
                counts = tags.get(279) or tags.get(325)
        except Exception as exc:  # noqa: BLE001 - Pillow raises many types for broken files
            return f"the TIFF header does not parse ({type(exc).__name__})"
        if offsets and counts:
            end = max(int(o) + int(c) for o, c in zip(offsets, counts))
            if end > size:
                return f"the TIFF's image data ends at byte {end}, past the file's {size} bytes"
    return None


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

    def _ensure_info(self) -> None:
        if getattr(self, "_size", None) is None:
            self.read(0)

    def _check_index(self, i: int) -> int:
        i = int(i)
        n = len(self)
        if not 0 <= i < n:
            raise SessionError(f"frame index {i} is outside the {n} frames available",
                               file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        return i

    def __iter__(self):
        for i in range(len(self)):
            yield self.read(i)


class ImageSequence(FrameSource):
    """Frames stored one file each, named by a printf pattern.

    The first file index is detected: ``0`` if that file exists, else ``1``. Frame ``i``
    of the source is file ``pattern % (first + i)``. The frame count is the number of
    consecutive files from the first; a gap followed by more files is an error naming
    the missing index.
    """

    def __init__(self, pattern: str | os.PathLike, *, camera_name: str | None = None):
        self.path = os.fspath(pattern)
        self.camera_name = camera_name
        if not is_pattern(self.path):
            raise SessionError("not a printf pattern with one integer directive such as %05d",
                               file=self.path, camera=camera_name)
        self.first, self._count = self._scan()
        self._size = None
        self._raw_dtype = None

    def _scan(self) -> tuple[int, int]:
        directory, base = os.path.split(self.path)
        directory = directory or "."
        if _DIRECTIVE.search(directory):
            return self._scan_by_stat()
        try:
            names = os.listdir(directory)
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
        n = 0
        while first + n in indices:
            n += 1
        later = [k for k in indices if k > first + n]
        if later:
            raise SessionError(
                f"frame file {self.path % (first + n)} is missing while {len(later)} later "
                f"frame file(s) exist", file=self.path % (first + n), camera=self.camera_name,
                field=f"frames[{n}]")
        return first, n

    def _scan_by_stat(self) -> tuple[int, int]:
        if os.path.isfile(self.path % 0):
            first = 0
        elif os.path.isfile(self.path % 1):
            first = 1
        else:
            raise SessionError(
                f"no frame file found: neither {self.path % 0} nor {self.path % 1} exists",
                file=self.path, camera=self.camera_name, field="frames[0]")
        n = 0
        while os.path.isfile(self.path % (first + n)):
            n += 1
        return first, n

    def __len__(self) -> int:
        return self._count

    def file_of(self, i: int) -> str:
        return self.path % (self.first + int(i))

    def read(self, i: int) -> np.ndarray:
        i = self._check_index(i)
        img, raw = read_image(self.file_of(i), camera_name=self.camera_name, field=f"frames[{i}]")
        self._remember(img, raw, i)
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

    def __repr__(self) -> str:
        return f"ImageSequence({self.path!r}, first={self.first}, n={self._count})"


class VideoFrames(FrameSource):
    """Frames of a video file, decoded with ``cv2.VideoCapture``.

    Random access seeks with ``CAP_PROP_POS_FRAMES``; reads in increasing order (or short
    jumps ahead, up to ``FORWARD_GRAB_LIMIT`` frames) reuse the open decoder. If a seek is
    refused or lands elsewhere, the reader reopens the file and decodes sequentially up to
    the frame. A frame that cannot be decoded raises
    :class:`SessionError` naming the file, the camera and the frame index.
    """

    def __init__(self, path: str | os.PathLike, *, camera_name: str | None = None):
        self.path = os.fspath(path)
        self.camera_name = camera_name
        if not os.path.isfile(self.path):
            raise SessionError("video file not found", file=self.path, camera=camera_name)
        self._cap = None
        self._next = 0  # index of the frame the open decoder returns next
        self._size = None
        self._raw_dtype = None
        cap = self._open()
        n = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        if n <= 0:
            n = self._count_sequentially()
        self._count = n

    # -- handle management ------------------------------------------------------
    def _open(self) -> cv2.VideoCapture:
        if self._cap is None:
            cap = cv2.VideoCapture(self.path)
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

    def _count_sequentially(self) -> int:
        self.close()
        cap = self._open()
        n = 0
        while cap.grab():
            n += 1
        self.close()
        return n

    def __len__(self) -> int:
        return self._count

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
        self._seek(i)
        ok, img = self._cap.read()
        if not ok or img is None or img.size == 0:
            raise self._decode_error(i)
        self._next = i + 1
        grey = _grey_of_raw(img, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        size = (grey.shape[1], grey.shape[0])
        if self._size is None:
            self._size, self._raw_dtype = size, np.dtype(img.dtype)
        return grey

    def iter_sequential(self):
        """Decode every frame in order (faster than random access), as float32 grey."""
        self.close()
        cap = self._open()
        for i in range(len(self)):
            ok, img = cap.read()
            if not ok or img is None:
                raise self._decode_error(i)
            self._next = i + 1
            yield _grey_of_raw(img, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        self.close()

    def __repr__(self) -> str:
        return f"VideoFrames({self.path!r}, n={self._count})"


def _source_path_and_name(source, camera_name):
    # a CameraSource (storage.session) or anything with .frames/.name, or a path
    if hasattr(source, "frames") and hasattr(source, "name") and not isinstance(source, (str, os.PathLike)):
        return os.fspath(source.frames), (camera_name if camera_name is not None else source.name)
    return os.fspath(source), camera_name


def open_frames(source, *, camera_name: str | None = None) -> FrameSource:
    """Open a camera's frames for random access.

    Parameters
    ----------
    source : str, path-like or CameraSource
        A printf pattern of an image sequence (``cam00/frames/%05d.png``) or a video file;
        a :class:`~schlieren.storage.session.CameraSource` gives its ``frames``.
    camera_name : str, optional
        Named in error messages (defaults to the CameraSource's name).

    Returns
    -------
    FrameSource
        ``len(src)`` frames; ``src.read(i)`` -> float32 (H, W); ``src.size`` = (W, H);
        ``src.raw_dtype``.
    """
    path, name = _source_path_and_name(source, camera_name)
    if is_pattern(path):
        return ImageSequence(path, camera_name=name)
    if is_video(path):
        return VideoFrames(path, camera_name=name)
    raise SessionError(
        "frames must be a printf pattern of an image sequence (e.g. cam00/frames/%05d.png) "
        f"or a video file ({', '.join(sorted(VIDEO_EXTENSIONS))})", file=path, camera=name)


def read_reference(source, *, camera_name: str | None = None) -> np.ndarray:
    """The reference (no-flow background) image of a camera, as float32 grey levels.

    Parameters
    ----------
    source : str, path-like or CameraSource
        One image file, a printf pattern (every frame is averaged) or a video (every frame
        is averaged); a CameraSource gives its ``reference``.
    camera_name : str, optional

    Returns
    -------
    reference : ndarray, shape (H, W), float32
        Averages are accumulated in float64 and rounded to float32 once.
    """
    if hasattr(source, "reference") and hasattr(source, "name") and not isinstance(source, (str, os.PathLike)):
        path = os.fspath(source.reference)
        name = camera_name if camera_name is not None else source.name
    else:
        path, name = os.fspath(source), camera_name
    if is_pattern(path):
        seq = ImageSequence(path, camera_name=name)
        return _average((seq.read(i) for i in range(len(seq))), path, name)
    if is_video(path):
        vid = VideoFrames(path, camera_name=name)
        return _average(vid.iter_sequential(), path, name)
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
