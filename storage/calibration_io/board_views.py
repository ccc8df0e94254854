"""One camera's board views (a video, a folder of images or a glob of images), and board
images for printing."""

from __future__ import annotations

import glob
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.readers.kinds import IMAGE_EXTENSIONS as _FRAME_IMAGE_EXTENSIONS
from schlieren.storage.readers.kinds import VIDEO_EXTENSIONS as _FRAME_VIDEO_EXTENSIONS

# the one list of containers and image types every reader uses (storage/readers/kinds.py)
IMAGE_EXTENSIONS = tuple(sorted(_FRAME_IMAGE_EXTENSIONS))
VIDEO_EXTENSIONS = tuple(sorted(_FRAME_VIDEO_EXTENSIONS))


@dataclass(frozen=True)
class BoardSource:
    """One camera's board views.

    Attributes
    ----------
    name : str
        Camera name (``NAME=`` prefix, else the video's stem or the folder's name).
    kind : {"video", "images"}
    paths : tuple of str
        The video file, or the image files in name order.
    spec : str
        The argument as given (for messages).
    """

    name: str
    kind: str
    paths: tuple
    spec: str = ""

    @property
    def label(self) -> str:
        return self.paths[0] if self.kind == "video" else (self.spec or os.path.dirname(self.paths[0]))


def _split_name(arg: str) -> tuple[str | None, str]:
    if "=" in arg:
        name, path = arg.split("=", 1)
        if name and os.sep not in name and "/" not in name and not os.path.exists(arg):
            return name.strip(), path
    return None, arg


def resolve_source(arg: str, *, base: str | os.PathLike | None = None,
                   single_image: bool = False) -> BoardSource:
    """Interpret one camera's argument: ``[NAME=]VIDEO``, ``[NAME=]FOLDER`` or ``[NAME=]GLOB``.

    Parameters
    ----------
    arg : str
        A video file, a folder of images (sorted by name), or a quoted glob pattern of
        images, optionally prefixed by the camera's name and ``=``.
    base : path, optional
        Folder against which relative paths are resolved (default: current directory).
    single_image : bool
        Accept one image file (named by its stem), e.g. a board on the background.

    Returns
    -------
    BoardSource

    Raises
    ------
    SchlierenInputError
        Nothing matches, or a folder/pattern holds no images.
    """
    name, path = _split_name(arg)
    full = path if (base is None or os.path.isabs(path)) else os.path.join(os.fspath(base), path)
    if any(ch in path for ch in "*?["):
        files = sorted(f for f in glob.glob(full) if f.lower().endswith(IMAGE_EXTENSIONS))
        if not files:
            raise SchlierenInputError("the pattern matches no image files", file=full, camera=name)
        if name is None:
            parent = os.path.basename(os.path.dirname(os.path.abspath(files[0])))
            name = parent or Path(files[0]).stem
        return BoardSource(name, "images", tuple(files), path)
    if os.path.isdir(full):
        files = sorted(os.path.join(full, f) for f in os.listdir(full)
                       if f.lower().endswith(IMAGE_EXTENSIONS))
        if not files:
            raise SchlierenInputError("the folder holds no image files "
                                      f"({', '.join(IMAGE_EXTENSIONS)})", file=full, camera=name)
        return BoardSource(name or os.path.basename(os.path.normpath(full)), "images", tuple(files), full)
    if os.path.isfile(full):
        if full.lower().endswith(IMAGE_EXTENSIONS):
            if single_image:
                return BoardSource(name or Path(full).stem, "images", (full,), full)
            raise SchlierenInputError(
                "one image is not enough to calibrate a camera; give its folder or a quoted "
                "glob pattern (e.g. 'calib/cam00/*.png')", file=full, camera=name)
        return BoardSource(name or Path(full).stem, "video", (full,), full)
    raise SchlierenInputError("no such video, image folder or pattern", file=full, camera=name)


def read_image(path: str | os.PathLike, *, camera: str | None = None) -> np.ndarray:
    """Read one image as stored (8/16-bit, grey or BGR).

    Raises
    ------
    SchlierenInputError
        Missing or unreadable file.
    """
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise SchlierenInputError("file not found", file=p, camera=camera)
    img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SchlierenInputError("cannot read the image (corrupt or unsupported format)",
                                  file=p, camera=camera)
    return img


def iter_board_frames(source: BoardSource, *, step: int = 1,
                      max_views: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(view, image)`` for one camera's board views.

    View ``i`` is frame ``i * step`` of a video or image ``i * step`` (name order) of an
    image list, so the same ``step`` keeps synchronised cameras' views aligned. All
    images must share one size.

    Parameters
    ----------
    source : BoardSource
    step : int
        Use every ``step``-th frame or image.
    max_views : int, optional
        Stop after this many views.

    Raises
    ------
    SchlierenInputError
        Unreadable file or frame, or images of different sizes.
    """
    step = max(1, int(step))
    size = None
    n = 0

    def check(img, where):
        nonlocal size
        s = (img.shape[1], img.shape[0])
        if size is None:
            size = s
        elif s != size:
            raise SchlierenInputError(f"image size {s[0]}x{s[1]} differs from the first "
                                      f"image's {size[0]}x{size[1]}", file=where, camera=source.name)

    if source.kind == "images":
        for view, k in enumerate(range(0, len(source.paths), step)):
            if max_views is not None and n >= max_views:
                return
            img = read_image(source.paths[k], camera=source.name)
            check(img, source.paths[k])
            n += 1
            yield view, img
        return
    path = source.paths[0]
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        raise SchlierenInputError("cannot open the video", file=path, camera=source.name)
    try:
        while max_views is None or n < max_views:
            ok, img = cap.read()
            if not ok:
                break
            check(img, path)
            yield n, img
            n += 1
            for _ in range(step - 1):
                if not cap.grab():
                    return
    finally:
        cap.release()
    if n == 0:
        raise SchlierenInputError("the video holds no readable frame", file=path, camera=source.name)


def write_print_image(path: str | os.PathLike, image: np.ndarray, dpi: float) -> Path:
    """Write a grey image for printing: 8-bit PNG whose header states ``dpi`` (so printing
    "at 100 %" gives the physical size the pixels were computed for)."""
    from PIL import Image

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    img = np.clip(np.rint(np.asarray(image, dtype=np.float64)), 0, 255).astype(np.uint8)
    Image.fromarray(img).save(p, dpi=(float(dpi), float(dpi)))
    return p
