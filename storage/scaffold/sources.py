"""Capture sources for ``schlieren init``: finding them from its arguments, probing their
frame count, size and rate, and writing a range of their frames losslessly as references."""

from __future__ import annotations

import glob
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.readers.kinds import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, frames_kind, is_pattern
from schlieren.storage.readers.opening import open_frames

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoInfo:
    """What a video holds.

    Attributes
    ----------
    path : str
    frame_count : int
    width, height : int
        Pixels.
    fps : float
        Frames per second from the container (0 if unknown).
    """

    path: str
    frame_count: int
    width: int
    height: int
    fps: float

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height


def probe_video(path: str | os.PathLike, *, camera: str | None = None,
                count_frames: bool = False) -> VideoInfo:
    """Frame count, size and frame rate of a video.

    Parameters
    ----------
    path : path
    camera : str, optional
        For error messages.
    count_frames : bool
        Count the frames by decoding them all (exact, slow) instead of trusting the
        container's count; a container count of 0 is always counted.

    Raises
    ------
    SchlierenInputError
        Missing file, unopenable or empty video.
    """
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise SchlierenInputError("video file not found", file=p, camera=camera)
    cap = cv2.VideoCapture(p)
    try:
        if not cap.isOpened():
            raise SchlierenInputError("cannot open the video (corrupt or unsupported codec)", file=p,
                                      camera=camera)
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        n = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
        ok, img = cap.read()
        if not ok or img is None:
            raise SchlierenInputError("cannot decode the first frame of the video", file=p,
                                      camera=camera, field="frames[0]")
        h, w = img.shape[:2]
        if count_frames or n <= 0:
            n = 1
            while cap.grab():
                n += 1
    finally:
        cap.release()
    return VideoInfo(p, n, int(w), int(h), fps if np.isfinite(fps) else 0.0)


def probe_source(spec: str | os.PathLike, *, camera: str | None = None,
                 count_frames: bool = False) -> VideoInfo:
    """Frame count and size of a camera's frames (any kind :func:`find_sources` returns).

    Videos are probed with :func:`probe_video` (frame rate from the container); image
    sequences and multi-page TIFFs have no frame rate (``fps`` 0).
    """
    if frames_kind(spec) == "video":
        return probe_video(spec, camera=camera, count_frames=count_frames)
    fs = open_frames(os.fspath(spec), camera_name=camera)
    w, h = fs.size  # decodes frame 0
    return VideoInfo(os.fspath(spec), len(fs), int(w), int(h), 0.0)


def source_kind(spec: str | os.PathLike) -> str:
    """What a frames specification is, in words for messages: ``"video"``,
    ``"multi-page TIFF"`` or ``"image sequence"``."""
    kind = frames_kind(spec)
    return {"video": "video", "tiff": "multi-page TIFF"}.get(kind, "image sequence")


def _image_name(path: str) -> str:
    """Camera name of an image sequence: its folder (``cam00/frames/`` -> ``cam00``)."""
    folder = Path(os.path.abspath(path))
    if is_pattern(path) or frames_kind(path) == "glob" or folder.is_file():
        folder = folder.parent
    if folder.name in ("frames", "images", "img") and folder.parent.name:
        folder = folder.parent
    return folder.name


def find_sources(patterns: Sequence[str], *, base: str | os.PathLike | None = None) -> dict[str, str]:
    """Camera name -> frames specification from ``[NAME=]PATH`` arguments of ``schlieren init``.

    ``PATH`` may be

    * a video file, or a quoted glob matching several videos: one camera per video,
      named after its file stem;
    * an image sequence: a printf pattern (``cam00/frames/%05d.png``), a quoted glob of
      images (``'cam00/*.tif'``) or a folder of images: one camera, named after the
      folder (``cam00``; a folder named ``frames`` or ``images`` gives its parent's name);
    * a folder of videos: one camera per video;
    * a multi-page TIFF file: one camera, named after its stem.

    Relative paths are tried against the current directory, then ``base``.

    Raises
    ------
    SchlierenInputError
        A path matching nothing, or two sources with the same camera name.
    """
    out: dict[str, str] = {}

    def add(cam: str, spec: str) -> None:
        if cam in out and os.path.abspath(out[cam]) != os.path.abspath(spec):
            raise SchlierenInputError(f"two sources for the same camera ({out[cam]} and {spec}); "
                                      "name them with NAME=PATH", file=spec, camera=cam)
        out[cam] = spec

    for arg in patterns:
        name = None
        spec = arg
        if "=" in arg and not os.path.exists(arg):
            n, rest = arg.split("=", 1)
            if n and "/" not in n and os.sep not in n:
                name, spec = n, rest
        candidates = [spec]
        if base is not None and not os.path.isabs(spec):
            candidates.append(os.path.join(os.fspath(base), spec))
        found = None
        for c in candidates:
            if is_pattern(c):
                d = os.path.dirname(c) or "."
                if os.path.isdir(d):
                    found = ("sequence", [c])
            elif os.path.isdir(c):
                entries = sorted(os.path.join(c, f) for f in os.listdir(c))
                videos = [f for f in entries if Path(f).suffix.lower() in VIDEO_EXTENSIONS and os.path.isfile(f)]
                images = [f for f in entries if Path(f).suffix.lower() in IMAGE_EXTENSIONS and os.path.isfile(f)]
                if images:
                    found = ("folder", [c])
                elif videos:
                    found = ("videos", videos)
            else:
                files = sorted(f for f in glob.glob(c) if os.path.isfile(f))
                videos = [f for f in files if Path(f).suffix.lower() in VIDEO_EXTENSIONS]
                images = [f for f in files if Path(f).suffix.lower() in IMAGE_EXTENSIONS]
                if frames_kind(c) == "glob" and images and not videos:
                    found = ("glob", [c])
                elif len(files) == 1 and frames_kind(files[0]) == "tiff":
                    found = ("tiff", files)
                elif videos:
                    found = ("videos", videos)
            if found:
                break
        if not found:
            raise SchlierenInputError("no video, image sequence or multi-page TIFF matches", file=spec, camera=name)
        kind, items = found
        if kind == "videos":
            if name is not None and len(items) > 1:
                raise SchlierenInputError(f"NAME= needs exactly one video but the pattern matches {len(items)}",
                                          file=spec, camera=name)
            for f in items:
                add(name or Path(f).stem, f)
        elif kind == "tiff":
            add(name or Path(items[0]).stem, items[0])
        else:
            add(name or _image_name(items[0]), items[0])
    return out


#: The name of 0.1 (videos only); it now finds every kind of source.
find_videos = find_sources


def write_reference_frames(video: str | os.PathLike, frames: tuple[int, int], out_dir: str | os.PathLike,
                           *, camera: str | None = None) -> int:
    """Write frames ``[A, B)`` of a camera's frames losslessly as ``out_dir/%05d.png`` (from 00000).

    ``video`` is any frames specification (:func:`find_sources`); 8- and 16-bit frames
    are written as PNG, float frames as ``%05d.tif``. Frames the camera dropped (a gap in
    numbered files) are left out, the others numbered on without a gap. Stale numbered
    files of an earlier run in ``out_dir`` are removed first.

    Returns
    -------
    int
        The number of frames written.

    Raises
    ------
    SchlierenInputError
        A frame that cannot be decoded (named by its index).
    """
    a, b = int(frames[0]), int(frames[1])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for pattern in ("[0-9][0-9][0-9][0-9][0-9].png", "[0-9][0-9][0-9][0-9][0-9].tif"):
        for old in out.glob(pattern):
            old.unlink()
    p = os.fspath(video)
    if frames_kind(p) != "video":
        src = open_frames(p, camera_name=camera)
        present = [k for k in range(a, b) if k not in set(src.dropped)]
        if not present:
            raise SchlierenInputError(f"the camera dropped every reference frame {a}..{b - 1}", file=p,
                                      camera=camera, field="reference_frames")
        for j, k in enumerate(present):
            raw = src.read_raw(k)
            ext = ".png" if raw.dtype in (np.uint8, np.uint16) else ".tif"
            dest = out / f"{j:05d}{ext}"
            if not cv2.imwrite(str(dest), raw):
                raise SchlierenInputError("cannot write the reference frame", file=str(dest), camera=camera)
        return len(present)
    cap = cv2.VideoCapture(p)
    try:
        if not cap.isOpened():
            raise SchlierenInputError("cannot open the video", file=p, camera=camera)
        for k in range(b):
            if k < a:
                if not cap.grab():
                    raise SchlierenInputError(f"cannot decode frame {k} of the video", file=p,
                                              camera=camera, field=f"frames[{k}]")
                continue
            ok, img = cap.read()
            if not ok or img is None:
                raise SchlierenInputError(f"cannot decode frame {k} of the video", file=p,
                                          camera=camera, field=f"frames[{k}]")
            if not cv2.imwrite(str(out / f"{k - a:05d}.png"), img):
                raise SchlierenInputError("cannot write the reference frame",
                                          file=str(out / f"{k - a:05d}.png"), camera=camera)
    finally:
        cap.release()
    return b - a
