"""What a frames specification is: printf pattern, glob, folder, video, multi-page TIFF or image.

The one list of video containers and image types every reader uses (session, init,
calibrate), and the predicates that classify a specification without opening it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from schlieren.storage import location

#: Video containers read with OpenCV/FFmpeg, for every reader (session, init, calibrate):
#: camcorder AVCHD (.mts, .m2ts), broadcast MXF and the common desktop containers.
VIDEO_EXTENSIONS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg",
                              ".wmv", ".mj2", ".ogv", ".mts", ".m2ts", ".mxf"})
IMAGE_EXTENSIONS = frozenset({".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm",
                              ".exr"})
TIFF_EXTENSIONS = frozenset({".tif", ".tiff"})

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


def _natural_key(path: str):
    """Name order with numbers compared as numbers (``img2`` before ``img10``)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", os.path.basename(path))]
