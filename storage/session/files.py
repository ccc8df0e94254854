"""Checks of a session's frame and reference files, before any work is scheduled.

Every camera's frames are opened (frame 0 decoded and compared with ``image_size``),
the frames to process checked (headers and truncation, or decoded in full), the
reference checked the same way, and every file kept inside the session folder (symbolic
links resolved). A reader's error is re-raised with the manifest field in front
(``frames[3]`` -> ``cameras[1].frames[3]``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

from schlieren.pipeline.geometry import Camera
from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.readers import decoding
from schlieren.storage.readers.base import FrameSource
from schlieren.storage.readers.decoding import image_header, image_headers, images_incomplete, read_image
from schlieren.storage.readers.kinds import VIDEO_EXTENSIONS, frames_kind
from schlieren.storage.readers.opening import open_frames
from schlieren.storage.readers.sequence import ImageSequence
from schlieren.storage.readers.video import VideoFrames
from schlieren.storage.session.paths import check_contained
from schlieren.storage.session.types import CameraSource


class _qualified:
    """Re-raise a reader's SessionError with the manifest field of camera ``i`` in front.

    ``frames[3]`` becomes ``cameras[1].frames[3]``; no field becomes ``cameras[1].frames``.
    """

    def __init__(self, i: int, base: str, camera: str | None = None):
        self.prefix = f"cameras[{i}]"
        self.base = base
        self.camera = camera

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None or not issubclass(exc_type, SessionError):
            return False
        f = exc.field
        if f is None:
            f = f"{self.prefix}.{self.base}"
        elif not f.startswith("cameras["):
            f = f"{self.prefix}.{self.base}{f[len('frames'):]}" if f.startswith("frames[") else \
                f"{self.prefix}.{f}"
        raise SessionError(exc.message, file=exc.file, camera=exc.camera or self.camera, field=f) from None


def _per_camera(fn: Callable[[int], Any], n: int, concurrent: bool) -> list:
    """``[fn(i) for i in range(n)]``; with ``concurrent`` (files on an object store, or
    videos to decode) in threads, raising the error of the first camera that has one, as the
    loop would."""
    if not concurrent or n < 2:
        return [fn(i) for i in range(n)]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(8, n), thread_name_prefix="schlieren-session") as pool:
        return list(pool.map(fn, range(n)))


def _check_camera_files(i: int, cam: Camera, source: CameraSource, *, contained=None) -> FrameSource:
    """Open the frames, decode frame 0 and compare its size with ``image_size``.

    ``contained(fs)``, if given, checks the files before any is read (symlinks out of the
    session folder)."""
    W, H = cam.image_size
    fs = open_frames(source, camera_name=cam.name)  # fields of interlaced video
    if contained is not None:
        contained(fs)
    if len(fs) == 0:
        raise SessionError("the video holds no frames", file=source.frames, camera=cam.name,
                           field=f"cameras[{i}].frames")
    # a local file's header first: never decode a frame of an absurd size (from an object store
    # the frame is fetched whole once, and OpenCV's own pixel limit refuses an absurd one: a
    # ranged header read first would fetch frame 0 twice)
    if isinstance(fs, ImageSequence) and not location.is_url(os.fspath(fs.file_of(0))):
        size = image_header(fs.file_of(0))
        if size is not None and size != (W, H):
            raise SessionError(f"frame 0 is {size[0]}x{size[1]} pixels but image_size is [{W}, {H}]",
                               file=fs.file_of(0), camera=cam.name, field=f"cameras[{i}].image_size")
    first = fs.read(0)
    if (first.shape[1], first.shape[0]) != (W, H):
        raise SessionError(f"frame 0 is {first.shape[1]}x{first.shape[0]} pixels but image_size is "
                           f"[{W}, {H}]", file=fs.file_of(0), camera=cam.name, field=f"cameras[{i}].image_size")
    return fs


def _check_frames_content(i: int, cam: Camera, fs: FrameSource, indices: list[int], *,
                          decode_all: bool = False) -> None:
    W, H = cam.image_size
    gone = set(fs.dropped)
    indices = [k for k in indices if k not in gone]  # dropped by the camera: nothing to check
    if decode_all:
        wanted = set(indices)
        if not wanted:
            return
        frames = fs.iter_sequential() if isinstance(fs, VideoFrames) else (fs.read(k) for k in sorted(wanted))
        order = fs.present() if isinstance(fs, VideoFrames) else sorted(wanted)
        for k, img in zip(order, frames):
            if k in wanted and (img.shape[1], img.shape[0]) != (W, H):
                raise SessionError(f"frame {k} is {img.shape[1]}x{img.shape[0]} pixels but image_size is "
                                   f"[{W}, {H}]", file=fs.file_of(k), camera=cam.name,
                                   field=f"cameras[{i}].image_size")
            if isinstance(fs, VideoFrames) and k >= max(wanted):
                break
        return
    if isinstance(fs, ImageSequence):
        files = [fs.file_of(k) for k in indices]
        heads = fs.file_heads(indices) if files and location.is_url(files[0]) else None  # one batch serves both
        incomplete = images_incomplete(files, [fs.listed_size(k) for k in indices], heads)
        for k, size, why in zip(indices, image_headers(files, heads), incomplete):
            if size is None:  # a format Pillow does not know, or a corrupt file: decode it
                img, _ = read_image(fs.file_of(k), camera_name=cam.name, field=f"frames[{k}]")
                size = (img.shape[1], img.shape[0])
            if size != (W, H):
                raise SessionError(f"frame {k} is {size[0]}x{size[1]} pixels but image_size is [{W}, {H}]",
                                   file=fs.file_of(k), camera=cam.name, field=f"cameras[{i}].image_size")
            if why is not None:
                raise SessionError(f"frame {k} is truncated: {why}", file=fs.file_of(k), camera=cam.name,
                                   field=f"cameras[{i}].frames[{k}]")
    if indices:
        last = max(indices)
        img = fs.read(last)  # decodes fully; raises naming the frame index
        if (img.shape[1], img.shape[0]) != (W, H):
            raise SessionError(f"frame {last} is {img.shape[1]}x{img.shape[0]} pixels but image_size is "
                               f"[{W}, {H}]", file=fs.file_of(last), camera=cam.name,
                               field=f"cameras[{i}].image_size")


def _check_reference(i: int, cam: Camera, source: CameraSource) -> None:
    W, H = cam.image_size
    ref = source.reference
    fld = f"cameras[{i}].reference"
    head = None  # at a URL: its first bytes (the whole file if shorter), one request for the checks
    if source.reference_kind == "image":
        if location.is_url(ref):
            try:
                head = location.read_bytes(ref, 0, decoding.HEADER_BYTES)
            except (FileNotFoundError, IsADirectoryError):
                head = None
            if head is None or (len(head) == 0 and not location.isfile(ref)):
                raise SessionError("reference image not found", file=ref, camera=cam.name, field=fld)
        elif not location.isfile(ref):
            raise SessionError("reference image not found", file=ref, camera=cam.name, field=fld)
        size = image_header(ref, head)
        if size is None:
            img, _ = read_image(ref, camera_name=cam.name, field=fld)
            size = (img.shape[1], img.shape[0])
        files = [ref]
        sizes = [size]
    elif source.reference_kind == "video":
        vid = VideoFrames(ref, camera_name=cam.name)
        if (vid.header_count if vid.header_count > 0 else len(vid)) == 0:
            raise SessionError("the reference video holds no frames", file=ref, camera=cam.name, field=fld)
        files = [ref]
        sizes = [vid.size]
        vid.close()
    else:  # an image sequence (pattern, glob, folder) or a multi-page TIFF
        seq = open_frames(ref, camera_name=cam.name)
        if seq.dropped and source.reference_kind == "sequence":  # a printf pattern's lost file (a folder's
            # or glob's files are averaged as they are)
            k = seq.dropped[0]
            raise SessionError(f"reference file {seq.file_of(k)} is missing while later reference files exist",
                               file=seq.file_of(k), camera=cam.name, field=f"frames[{k}]")
        if isinstance(seq, ImageSequence):
            files = [seq.file_of(k) for k in seq.present()]
            sizes = []
            for f in files:
                size = image_header(f)
                if size is None:
                    img, _ = read_image(f, camera_name=cam.name, field=fld)
                    size = (img.shape[1], img.shape[0])
                sizes.append(size)
        else:
            files, sizes = [ref], [seq.size]
    for f, size in zip(files, sizes):
        if size != (W, H):
            raise SessionError(f"reference is {size[0]}x{size[1]} pixels but image_size is [{W}, {H}]",
                               file=f, camera=cam.name, field=fld)
        whole = head is not None and len(head) < decoding.HEADER_BYTES  # its size is known: no request for it
        why = images_incomplete([f], [len(head)] if whole else None, [head] if whole else None)[0] \
            if source.reference_kind != "video" else None
        if why is not None:
            raise SessionError(f"the reference is truncated: {why}", file=f, camera=cam.name, field=fld)


def _kind_of_frames(spec: str, file: str, camera: str, field: str) -> str:
    kind = frames_kind(spec)
    if kind in (None, "image"):
        raise SessionError(f"frames {spec!r} must be an image sequence (printf pattern cam00/frames/%05d.png, "
                           "glob pattern cam00/frames/*.png or a folder cam00/frames/), a multi-page TIFF or a "
                           f"video file ({', '.join(sorted(VIDEO_EXTENSIONS))})", file=file, camera=camera,
                           field=field)
    return kind


def _kind_of_reference(spec: str) -> str:
    return frames_kind(spec) or "image"


def _check_files_contained(i: int, cam: Camera, src: CameraSource, fs: FrameSource, indices, root: Path,
                           mfile: str) -> None:
    """Every frame and reference file a run will open, symlinks resolved, is in the session folder."""
    if location.is_url(str(root)):
        return  # object stores have no symbolic links
    if isinstance(fs, ImageSequence) and fs.dropped:
        gone = set(fs.dropped)
        indices = [k for k in indices if k not in gone]
    frames = [fs.file_of(k) for k in indices] if isinstance(fs, ImageSequence) else [fs.path]
    for k, f in zip(indices if isinstance(fs, ImageSequence) else [None], frames):
        check_contained(f, root, file=mfile, camera=cam.name,
                         field=f"cameras[{i}].frames" + (f"[{k}]" if k is not None else ""), what=f)
    refs = [src.reference]
    if src.reference_kind not in ("image", "video"):  # a sequence (pattern, glob, folder) or a TIFF
        with _qualified(i, "reference"):
            seq = open_frames(src.reference, camera_name=cam.name)
        if isinstance(seq, ImageSequence):
            refs = [seq.file_of(k) for k in seq.present()]
    for f in refs:
        check_contained(f, root, file=mfile, camera=cam.name, field=f"cameras[{i}].reference", what=f)
