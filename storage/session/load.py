"""Load and validate a capture session: :func:`load_session`, a short sequence of named steps.

Find the manifest, parse its YAML safely, validate the typed model, check the camera list,
the volume, the sync window and the frame range, resolve and contain the cameras' paths,
check the rig's geometry (units, cameras outside the volume and seeing it), check the files, and check that the cameras agree
on the image size. Each step is a function here or in a sibling module, and raises the
one-line :class:`~schlieren.storage.errors.SessionError` of the first problem it finds.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path


from pydantic import ValidationError

from schlieren.pipeline.geometry import Camera, Grid, Medium
from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.readers.base import FrameSource, format_ranges
from schlieren.storage.readers.sequence import ImageSequence
from schlieren.storage.readers.video import VideoFrames
from schlieren.storage.session.checks import (
    _camera_from_model,
    _check_background,
    _check_range,
    _check_volume,
    check_rig,
    frames_beside_strobe,
    parse_frame_range,
    strobe_overlap,
)
from schlieren.storage.session.files import (
    _check_camera_files,
    _check_files_contained,
    _check_frames_content,
    _check_reference,
    _kind_of_frames,
    _kind_of_reference,
    _per_camera,
    _qualified,
)
from schlieren.storage.session.models import ManifestModel, validation_error
from schlieren.storage.session.paths import resolve_path
from schlieren.storage.session.types import MANIFEST_NAME, SESSION_FORMAT, CameraSource, Session
from schlieren.storage.session.yaml_safe import check_plain, read_yaml

log = logging.getLogger(__name__)

#: Fewest frames in ``sync.strobe.search_frames`` (the flash detector compares each frame
#: with the others of the window: pipeline.sync.detect_flash needs at least 3).
MIN_STROBE_FRAMES = 3


def load_session(path: str | os.PathLike, *, frames: tuple[int, int] | None = None,
                 check_files: bool = True, decode_all_frames: bool = False) -> Session:
    """Load and validate a capture session.

    Parameters
    ----------
    path : path-like
        The session folder (holding ``session.yaml``) or the manifest file itself.
    frames : (int, int), optional
        Half-open range of frames to process; overrides the manifest's ``frames``.
    check_files : bool
        Open the frame and reference files and check them (existence, decodability,
        sizes, equal frame counts). ``False`` checks the manifest alone.
    decode_all_frames : bool
        Decode every frame in the range to process (and the strobe search range) before
        returning. By default every frame's header is decoded and its file checked for
        completeness (a truncated PNG, JPEG or TIFF is refused here), and the first and
        last frame are decoded in full: a frame corrupt inside its pixel data is then
        reported, with its index, when a task reads it.

    Returns
    -------
    Session

    Raises
    ------
    SessionError
        One line naming the file, the camera and the field.
    """
    manifest_path, mfile, root = _locate_manifest(path)
    raw = _parse_manifest(manifest_path, mfile)
    m = _validate_model(raw, mfile)
    interlaced = _check_camera_list(m, mfile)
    grid = _check_volume(m.volume, mfile) if m.volume.voxel_size is not None else None
    medium = Medium(**m.medium.model_dump())
    strobe = _strobe_window(m, mfile)
    rng, what = _frame_range(m, frames, mfile)
    if rng is not None and strobe is not None and strobe_overlap(rng, strobe, what) is not None:
        raise SessionError(strobe_overlap(rng, strobe, what), file=mfile, field="sync.strobe.search_frames")
    cameras, sources = _cameras_and_sources(m, root, mfile)
    if all(b > a for a, b in zip(m.volume.min, m.volume.max)):  # else _check_volume says why
        check_rig(cameras, m.volume.min, m.volume.max, file=mfile)  # units, placement, visibility
    if grid is None:   # no voxel_size in the manifest: from the cameras' pixel footprint
        grid = _check_volume(m.volume, mfile, cameras)
    found = _FileChecks(frames=rng)
    if check_files:
        found = _check_files(cameras, sources, root, mfile, rng=rng, what=what, strobe=strobe,
                             allow_external=m.allow_external_paths, decode_all=decode_all_frames)
    # after the file checks (which name the frame whose size differs from its camera's)
    _check_same_image_size(m, mfile)
    return Session(
        name=m.name if m.name is not None else location.basename(root),
        root=root,
        manifest=raw,
        format=m.format,
        frame_rate=float(m.frame_rate) * (2.0 if interlaced else 1.0),
        frames=found.frames,
        grid=grid,
        medium=medium,
        strobe_search=strobe,
        cameras=cameras,
        sources=sources,
        n_frames_available=found.n_available,
        manifest_path=manifest_path,
        allow_external_paths=m.allow_external_paths,
        dropped_frames=found.dropped,
        video_slots=found.video_slots,
        opened={i: fs for i, fs in enumerate(found.opened) if isinstance(fs, ImageSequence)},
    )


# --------------------------------------------------------------------------------------
# the manifest
# --------------------------------------------------------------------------------------
def _locate_manifest(path: str | os.PathLike) -> tuple[Path | str, str, Path | str]:
    """``(manifest path, its name in messages, session folder)`` of a folder, a manifest
    file or a URL of either."""
    if location.is_url(location.normalize(os.fspath(path))):
        manifest_path = root = None
        url = location.normalize(os.fspath(path))
        try:
            manifest_path = url if location.isfile(url) else location.join(url, MANIFEST_NAME)
            found = location.isfile(manifest_path)
        except (OSError, ValueError) as exc:  # no such bucket, no credentials, a bad endpoint...
            raise SessionError(f"cannot reach the session ({type(exc).__name__}: {exc})", file=url) from None
        if not found:
            raise SessionError("session manifest not found", file=manifest_path)
        mfile = manifest_path
        root = location.parent(manifest_path)
    else:
        p = Path(path).expanduser()
        manifest_path = p / MANIFEST_NAME if p.is_dir() else p
        mfile = str(manifest_path)
        if not manifest_path.is_file():
            where = f"no {MANIFEST_NAME} in the session folder" if p.is_dir() else "session manifest not found"
            raise SessionError(where, file=mfile)
        manifest_path = manifest_path.resolve()
        mfile = str(manifest_path)
        root = manifest_path.parent
    return manifest_path, mfile, root


def _parse_manifest(manifest_path: Path | str, mfile: str) -> dict:
    """The manifest as plain data: safe YAML, a mapping, of a format this version reads."""
    raw = read_yaml(manifest_path)
    if raw is None:
        raise SessionError("the manifest is empty", file=mfile)
    if not isinstance(raw, dict):
        raise SessionError(f"the manifest must be a mapping of fields, got {type(raw).__name__}", file=mfile)
    check_plain(raw, "", mfile)

    fmt = raw.get("format")
    if fmt is None:
        raise SessionError(f"required field is missing (expected format: {SESSION_FORMAT})", file=mfile,
                           field="format")
    if fmt != SESSION_FORMAT:
        raise SessionError(f"unknown format {fmt!r}; this version reads {SESSION_FORMAT!r}", file=mfile,
                           field="format")
    return raw


def _validate_model(raw: dict, mfile: str) -> ManifestModel:
    """The typed manifest (pydantic); its first problem as one line."""
    try:
        return ManifestModel.model_validate(raw)
    except ValidationError as exc:
        raise validation_error(exc, raw, mfile) from None


def _check_camera_list(m: ManifestModel, mfile: str) -> bool:
    """At least one camera, unique names, all interlaced or none; returns whether they are."""
    if not m.cameras:
        raise SessionError("no cameras: the session needs at least one", file=mfile, field="cameras")
    seen: dict[str, int] = {}
    for i, c in enumerate(m.cameras):
        if c.name in seen:
            raise SessionError(f"duplicate camera name (also cameras[{seen[c.name]}])", file=mfile,
                               camera=c.name, field=f"cameras[{i}].name")
        seen[c.name] = i

    laced = {c.interlaced is not None for c in m.cameras}
    if len(laced) > 1:
        i, c = next((i, c) for i, c in enumerate(m.cameras)
                    if (c.interlaced is None) != (m.cameras[0].interlaced is None))
        raise SessionError("some cameras are interlaced and some are not: every camera of a session needs the "
                           "same frame (or field) rate", file=mfile, camera=c.name, field=f"cameras[{i}].interlaced")
    return m.cameras[0].interlaced is not None


def _strobe_window(m: ManifestModel, mfile: str) -> tuple[int, int] | None:
    """``sync.strobe.search_frames`` (checked), or None: then every camera needs a time_offset."""
    strobe = None
    if m.sync is not None and m.sync.strobe is not None:
        strobe = tuple(m.sync.strobe.search_frames)
        _check_range(strobe, None, file=mfile, field="sync.strobe.search_frames", what="search_frames")
        if strobe[1] - strobe[0] < MIN_STROBE_FRAMES:
            raise SessionError(f"search_frames {list(strobe)} holds {strobe[1] - strobe[0]} frame(s); the flash is "
                               f"found against the frames around it, so give at least {MIN_STROBE_FRAMES}",
                               file=mfile, field="sync.strobe.search_frames")
    else:
        for i, c in enumerate(m.cameras):
            if c.time_offset is None:
                raise SessionError("no time_offset and no sync.strobe: give every camera a time_offset "
                                   "or add sync.strobe", file=mfile, camera=c.name,
                                   field=f"cameras[{i}].time_offset")
    return strobe


def _frame_range(m: ManifestModel, frames, mfile: str) -> tuple[tuple[int, int] | None, str]:
    """The frames to process (the caller's ``frames``, else the manifest's, else None: all)
    and how messages name them."""
    rng_field = what = "frames"
    rng: tuple[int, int] | None = None
    if frames is not None:
        try:
            rng = parse_frame_range(frames)
        except ValueError as exc:
            raise SessionError(f"requested {exc}", file=mfile, field="frames") from None
        what = "requested frames"
    elif m.frames is not None:
        rng = tuple(m.frames)
        what = "frames"
    if rng is not None:
        _check_range(rng, None, file=mfile, field=rng_field, what=what)
    return rng, what


def _cameras_and_sources(m: ManifestModel, root: Path | str, mfile: str) -> tuple[list[Camera], list[CameraSource]]:
    """Every camera's geometry (its background in front of it) and its paths, resolved
    and contained in the session folder."""
    cameras: list[Camera] = []
    sources: list[CameraSource] = []
    for i, c in enumerate(m.cameras):
        cam = _camera_from_model(i, c, mfile)
        _check_background(i, cam, mfile)
        fr = resolve_path(c.frames, root, allow_external=m.allow_external_paths, file=mfile, camera=c.name,
                          field=f"cameras[{i}].frames")
        ref = resolve_path(c.reference, root, allow_external=m.allow_external_paths, file=mfile,
                           camera=c.name, field=f"cameras[{i}].reference")
        kind = _kind_of_frames(c.frames, mfile, c.name, f"cameras[{i}].frames")
        cameras.append(cam)
        sources.append(CameraSource(c.name, fr, ref, kind, _kind_of_reference(c.reference), c.interlaced))
    return cameras, sources


def _check_same_image_size(m: ManifestModel, mfile: str) -> None:
    """Every camera has the image size of the first (a session's flow grid is one for all)."""
    sizes = {tuple(c.image_size) for c in m.cameras}
    if len(sizes) > 1:
        first = m.cameras[0]
        i, c = next((i, c) for i, c in enumerate(m.cameras) if tuple(c.image_size) != tuple(first.image_size))
        raise SessionError(f"image_size {list(c.image_size)} differs from camera {first.name}'s "
                           f"{list(first.image_size)}: every camera of a session needs the same image size "
                           "(resize or crop the frames of the odd cameras, and recalibrate them)", file=mfile,
                           camera=c.name, field=f"cameras[{i}].image_size")


# --------------------------------------------------------------------------------------
# the files
# --------------------------------------------------------------------------------------
@dataclass
class _FileChecks:
    """What the file checks found: the frame range (all frames when none was given), the
    frames every camera has, dropped frames and video timestamp scans by camera, and the
    opened readers by camera index (without file checks, only the range as given)."""

    frames: tuple[int, int] | None = None
    n_available: int | None = None
    dropped: dict[str, tuple[int, ...]] = field(default_factory=dict)
    video_slots: dict[str, tuple[int, tuple[int, ...]]] = field(default_factory=dict)
    opened: list[FrameSource] = field(default_factory=list)


def _check_files(cameras: list[Camera], sources: list[CameraSource], root: Path | str, mfile: str, *,
                 rng: tuple[int, int] | None, what: str, strobe: tuple[int, int] | None, allow_external: bool,
                 decode_all: bool) -> _FileChecks:
    """Open every camera's frames (equal frame counts), check the ranges against them, then
    check the frames to process and the references."""
    remote = location.is_url(root)  # each check waits for requests: the cameras' together
    opened = _open_cameras(cameras, sources, root, mfile, allow_external=allow_external, remote=remote)
    n_avail = len(opened[0])
    if strobe is not None:
        _check_range(strobe, n_avail, file=mfile, field="sync.strobe.search_frames",
                     what="search_frames")
    if rng is None:  # every frame, or those after (before) the strobe window
        rng = frames_beside_strobe(n_avail, strobe)
    _check_range(rng, n_avail, file=mfile, field="frames", what=what)
    wanted = set(range(*rng)) | (set(range(*strobe)) if strobe else set())
    found = _FileChecks(rng, n_avail, opened=opened)
    _check_contents(cameras, sources, found, sorted(wanted), decode_all=decode_all, remote=remote)
    return found


def _open_cameras(cameras: list[Camera], sources: list[CameraSource], root: Path | str, mfile: str, *,
                  allow_external: bool, remote: bool) -> list[FrameSource]:
    """Every camera's frames opened (frame 0 decoded, files contained); equal frame counts."""
    def open_camera(i: int) -> FrameSource:
        cam, src = cameras[i], sources[i]
        check = None if allow_external else (
            lambda fs: _check_files_contained(i, cam, src, fs, range(len(fs)), root, mfile))
        with _qualified(i, "frames", cam.name):
            return _check_camera_files(i, cam, src, contained=check)

    n_avail: int | None = None
    opened: list[FrameSource] = []
    for i, (cam, src, fs) in enumerate(zip(cameras, sources, _per_camera(open_camera, len(cameras), remote))):
        if n_avail is None:
            n_avail = len(fs)
        elif len(fs) != n_avail:
            raise SessionError(f"has {len(fs)} frames but camera {cameras[0].name} has {n_avail}: every "
                               "camera needs the same number of frames", file=src.frames, camera=cam.name,
                               field=f"cameras[{i}].frames")
        opened.append(fs)
    return opened


def _check_contents(cameras: list[Camera], sources: list[CameraSource], found: _FileChecks, wanted: list[int], *,
                    decode_all: bool, remote: bool) -> None:
    """Check the frames ``wanted`` and the reference of every camera; record in ``found``
    the frames each camera dropped and the timestamp scan of each video."""
    dropped, video_slots = found.dropped, found.video_slots

    def check_content(i: int) -> None:
        cam, src, fs = cameras[i], sources[i], found.opened[i]
        with _qualified(i, "frames", cam.name):
            _check_frames_content(i, cam, fs, wanted, decode_all=decode_all)
        with _qualified(i, "reference", cam.name):
            _check_reference(i, cam, src)
        inner = getattr(fs, "frames", fs)  # the video under interlaced fields
        if isinstance(inner, VideoFrames):
            video_slots[cam.name] = inner.scan()
        if fs.dropped:
            dropped[cam.name] = tuple(fs.dropped)
        if hasattr(fs, "close"):
            fs.close()
    # videos are decoded whole for their timestamps (dropped frames): the cameras together
    # (OpenCV's decoder releases the GIL; docs/tuning.md, "Speed")
    videos = any(src.frames_kind == "video" for src in sources)
    _per_camera(check_content, len(cameras), remote or videos)
    if dropped:
        found.dropped = {c.name: dropped[c.name] for c in cameras if c.name in dropped}  # camera order
        log.warning("frames dropped by the cameras (never used; the other frames keep their capture "
                    "times): %s", "; ".join(f"{c} frame(s) {format_ranges(v)}" for c, v in found.dropped.items()))
