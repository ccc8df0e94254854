"""Open a camera's frames for random access (:func:`open_frames`) and read its reference
(no-flow background) image, averaging several frames (:func:`read_reference`; the frames
one by one, :func:`reference_frames`, and their average, :class:`ReferenceMean`, for a
caller that reads them anyway)."""

from __future__ import annotations

import os

import numpy as np

from schlieren.storage.errors import SessionError
from schlieren.storage.readers.base import FrameSource
from schlieren.storage.readers.decoding import read_image
from schlieren.storage.readers.files import ImageFiles
from schlieren.storage.readers.interlaced import InterlacedFields, bob_field
from schlieren.storage.readers.kinds import VIDEO_EXTENSIONS, frames_kind
from schlieren.storage.readers.sequence import ImageSequence
from schlieren.storage.readers.tiff import MultiPageTiff
from schlieren.storage.readers.video import VideoFrames


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
    path, name, order = _reference_path(source, camera_name)
    kind = frames_kind(path)
    if order and parity is not None:
        if kind in ("sequence", "glob", "folder", "tiff", "video"):
            src = open_frames(path, camera_name=name)
            return _average((bob_field(src.read(i), parity) for i in src.present()), path, name)
        img, _ = read_image(path, camera_name=name, field="reference")
        return bob_field(img, parity)
    if kind in _MULTI_FRAME:
        return _average(reference_frames(source, camera_name=camera_name), path, name)
    img, _ = read_image(path, camera_name=name, field="reference")
    return img


#: Kinds of reference specification that :func:`read_reference` averages frame by frame.
_MULTI_FRAME = ("sequence", "glob", "folder", "tiff", "video")


def _reference_path(source, camera_name):
    """``(path, name, interlaced order)`` of a camera's reference specification."""
    if hasattr(source, "reference") and hasattr(source, "name") and not isinstance(source, (str, os.PathLike)):
        return (os.fspath(source.reference), camera_name if camera_name is not None else source.name,
                getattr(source, "interlaced", None))
    return os.fspath(source), camera_name, None


def reference_frames(source, *, camera_name: str | None = None):
    """The frames of a camera's reference one by one, read as :func:`read_reference` (without
    ``parity``) reads them: their :class:`ReferenceMean` is its reference, bit for bit (one
    image: that image)."""
    path, name, order = _reference_path(source, camera_name)
    kind = frames_kind(path)
    if kind == "video" and not order:
        yield from VideoFrames(path, camera_name=name).iter_sequential()
    elif kind in _MULTI_FRAME:
        src = open_frames(path, camera_name=name)
        if order:  # the mean of both fields of every reference frame, like the frames
            src = InterlacedFields(src, order)
        for i in src.present():
            yield src.read(i)
    else:
        yield read_image(path, camera_name=name, field="reference")[0]


class ReferenceMean:
    """The average of a reference's frames, added one at a time: float64 sums, rounded to
    float32 once (:func:`read_reference`)."""

    def __init__(self, path: str = "", name: str | None = None):
        self.path, self.name = path, name
        self.acc: np.ndarray | None = None
        self.n = 0

    def add(self, img: np.ndarray) -> None:
        if self.acc is None:
            self.acc = np.zeros(img.shape, dtype=np.float64)
        elif img.shape != self.acc.shape:
            raise SessionError(f"reference frame {self.n} has shape {img.shape}, frame 0 has {self.acc.shape}",
                               file=self.path, camera=self.name, field=f"reference[{self.n}]")
        self.acc += img
        self.n += 1

    def result(self) -> np.ndarray:
        if self.n == 0:
            raise SessionError("the reference holds no frames", file=self.path, camera=self.name, field="reference")
        return (self.acc / self.n).astype(np.float32)


def _average(frames, path: str, name: str | None) -> np.ndarray:
    mean = ReferenceMean(path, name)
    for img in frames:
        mean.add(img)
    return mean.result()
