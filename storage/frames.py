"""Lazy random-access readers for camera frames and reference images (the public names).

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

The readers live in :mod:`schlieren.storage.readers` (one module per kind of source, a
shared base and the decoding helpers); this module re-exports their public names. The
tunables :data:`HEADER_BYTES` and :data:`FORWARD_GRAB_LIMIT` are read where they are
defined (``readers/decoding.py``, ``readers/video.py``): set them there.
"""

from __future__ import annotations

from schlieren.storage.readers.base import FrameSource, format_ranges
from schlieren.storage.readers.decoding import (
    HEADER_BYTES,
    image_header,
    image_headers,
    image_incomplete,
    images_incomplete,
    read_image,
)
from schlieren.storage.readers.files import ImageFiles
from schlieren.storage.readers.interlaced import InterlacedFields, bob_field
from schlieren.storage.readers.kinds import (
    IMAGE_EXTENSIONS,
    TIFF_EXTENSIONS,
    VIDEO_EXTENSIONS,
    frames_kind,
    is_glob,
    is_pattern,
    is_video,
)
from schlieren.storage.readers.opening import ReferenceMean, open_frames, read_reference, reference_frames
from schlieren.storage.readers.sequence import ImageSequence
from schlieren.storage.readers.tiff import MultiPageTiff
from schlieren.storage.readers.video import FORWARD_GRAB_LIMIT, VideoFrames, slots_of_timestamps


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
    "reference_frames",
    "ReferenceMean",
    "read_image",
    "is_pattern",
    "is_video",
    "image_header",
    "image_incomplete",
    "images_incomplete",
    "image_headers",
    "VIDEO_EXTENSIONS",
    "IMAGE_EXTENSIONS",
    "TIFF_EXTENSIONS",
    "HEADER_BYTES",
    "FORWARD_GRAB_LIMIT",
    "bob_field",
]
