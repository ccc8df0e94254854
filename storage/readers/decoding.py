"""Decoding image files to grey levels, and their headers and completeness without decoding.

Frames are returned as ``float32`` grey levels of the raw values (a 16-bit frame keeps its
0..65535 numbers; nothing is rescaled or quantised, since BOS deflections are sub-pixel);
colour is converted with OpenCV's luma weights. Files at an fsspec URL are fetched and
decoded from memory with the same decoder. :func:`image_header` and
:func:`image_incomplete` read a few bytes of a file (its size from the header; a PNG, JPEG
or TIFF cut short), so the session checks need not decode every frame.
"""

from __future__ import annotations

import io
import logging
import os

import cv2
import numpy as np

from schlieren.storage import location
from schlieren.storage.errors import SessionError

log = logging.getLogger(__name__)

#: Leading bytes of an image file fetched from an object store to read its header.
HEADER_BYTES = 1 << 16


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
        try:
            img = cv2.imdecode(np.frombuffer(blob, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if blob else None
        except cv2.error:  # e.g. a header declaring more pixels than OpenCV's limit
            img = None
    elif not os.path.isfile(p):
        raise SessionError("file not found", file=p, camera=camera_name, field=field)
    else:
        try:
            img = cv2.imread(p, cv2.IMREAD_UNCHANGED)  # any depth, any channels, as stored
        except cv2.error:  # e.g. a header declaring more pixels than OpenCV's limit
            size = image_header(p)
            what = f" its header declares {size[0]}x{size[1]} pixels;" if size else ""
            raise SessionError(f"cannot decode the image:{what} corrupt, or larger than any camera frame", file=p,
                               camera=camera_name, field=field) from None
    if img is None or img.size == 0:
        raise SessionError("cannot decode the image (corrupt or unsupported format)", file=p,
                           camera=camera_name, field=field)
    return img


def image_header(path: str | os.PathLike, head: bytes | None = None) -> tuple[int, int] | None:
    """``(width, height)`` from an image file's header without decoding it, or None.

    Uses Pillow's lazy opener (reads a few bytes). None means the file is not an image
    that Pillow recognises (missing, garbage, unsupported): callers decide whether to
    fall back to a full decode. A header declaring more pixels than Pillow's
    decompression-bomb limit still gives its size (a PNG's, read from its ``IHDR``), so
    that the caller refuses it as any other wrong size, or raises :class:`SessionError`
    naming the file.
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
    except Image.DecompressionBombError:
        size = _png_size(head if head is not None else _read_head(p))
        if size is None:
            raise SessionError("the image header declares more pixels than any camera frame has (Pillow's "
                               "decompression-bomb limit): a corrupt or hostile file", file=p) from None
        return size
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError):
        return None


def _read_head(path: str, n: int = 32) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def _png_size(head: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG's ``IHDR`` chunk (its first 24 bytes), or None."""
    if len(head) >= 24 and head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
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


def image_headers(paths: list[str], heads: list[bytes | None] | None = None) -> list[tuple[int, int] | None]:
    """:func:`image_header` of each file; from an object store in one concurrent batch
    (``heads``: their first :data:`HEADER_BYTES`, if already fetched)."""
    if not paths or not location.is_url(os.fspath(paths[0])):
        return [image_header(p) for p in paths]
    if heads is None:
        heads = location.read_many([os.fspath(p) for p in paths], 0, HEADER_BYTES)
    return [image_header(p, h) if h is not None else None for p, h in zip(paths, heads)]
