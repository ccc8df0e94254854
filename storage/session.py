"""Load and validate a capture session (``session.yaml``, SPEC section 1).

:func:`load_session` reads the manifest with ``yaml.safe_load`` semantics (plain data
only: a tag that would construct a Python object is refused), validates it with typed
pydantic models that forbid unknown fields (a misspelled field is reported with its
dotted path and a "did you mean" suggestion), resolves paths inside the session folder,
checks the geometry (orthonormal rotations, background planes in front of the cameras, a
volume that the cameras see and that fits in memory) and, unless ``check_files=False``,
the frame and reference files (existence, decodability, sizes, equal frame counts).

Every problem raises :class:`~schlieren.storage.errors.SessionError` with a one-line
message naming the file, the camera and the field (``cameras[2].R``), before any work
is scheduled.
"""

from __future__ import annotations

import difflib
import logging
import math
import numbers
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schlieren.pipeline import resources as _resources
from schlieren.pipeline.geometry import Camera, Grid, Medium, auto_voxel_size, rodrigues
from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.frames import (
    HEADER_BYTES,
    FrameSource,
    ImageSequence,
    InterlacedFields,
    VIDEO_EXTENSIONS,
    VideoFrames,
    format_ranges,
    frames_kind,
    image_header,
    image_headers,
    images_incomplete,
    open_frames,
    read_image,
)

__all__ = [
    "SESSION_FORMAT",
    "MANIFEST_NAME",
    "BYTES_PER_VOXEL",
    "CameraSource",
    "Session",
    "load_session",
    "parse_frame_range",
]

log = logging.getLogger(__name__)

SESSION_FORMAT = "schlieren-session/1"
MANIFEST_NAME = "session.yaml"
#: Working set of the 3-D stages per voxel and frame (the largest per-voxel coefficient
#: measured by benchmarks/memory.py, pipeline/resources.py), a first gate refusing grids
#: that cannot fit in the machine's memory whatever the cameras; the run's preflight
#: (workers/preflight.py) then checks the whole model times the workers.
BYTES_PER_VOXEL = _resources.BYTES_PER_VOXEL
DIST_LENGTHS = (4, 5, 8, 12, 14)
#: Fewest frames in ``sync.strobe.search_frames`` (the flash detector compares each frame
#: with the others of the window: pipeline.sync.detect_flash needs at least 3).
MIN_STROBE_FRAMES = 3
ORTHONORMAL_TOL = 1e-6


# --------------------------------------------------------------------------------------
# YAML: plain data only
# --------------------------------------------------------------------------------------
class _ManifestLoader(yaml.SafeLoader):
    """SafeLoader that keeps dates as strings and refuses duplicate keys."""


_ManifestLoader.yaml_implicit_resolvers = {
    ch: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:timestamp"]
    for ch, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}


def _construct_mapping(loader, node, deep=False):
    loader.flatten_mapping(node)
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first at line {seen[key] + 1})", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_ManifestLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _read_yaml(path: Path | str) -> Any:
    try:
        text = location.read_bytes(path).decode("utf-8")
    except UnicodeDecodeError:
        raise SessionError("the manifest is not UTF-8 text", file=str(path)) from None
    except OSError as exc:
        raise SessionError(f"cannot read the manifest ({exc.strerror or exc})", file=str(path)) from None
    try:
        return yaml.load(text, Loader=_ManifestLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.constructor.ConstructorError as exc:
        line = f" at line {exc.problem_mark.line + 1}" if exc.problem_mark else ""
        problem = str(exc.problem or exc)
        m = re.search(r"tag '([^']+)'", problem)
        if m and "constructor" in problem:
            tag = m.group(1).replace("tag:yaml.org,2002:", "!!")
            raise SessionError(
                f"YAML tag {tag}{line} is not allowed: the manifest must be plain data "
                "(mappings, lists, strings, numbers), not Python objects", file=str(path)) from None
        raise SessionError(f"invalid YAML{line}: {problem}", file=str(path)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise SessionError(f"not valid YAML{line}: {problem}", file=str(path)) from None


def _check_plain(obj: Any, where: str, file: str) -> None:
    """Refuse values that JSON cannot hold (the manifest is saved in the store attrs)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str):
                raise SessionError(f"field names must be text, got {k!r}", file=file, field=where or None)
            _check_plain(v, f"{where}.{k}" if where else k, file)
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _check_plain(v, f"{where}[{i}]", file)
    elif not (obj is None or isinstance(obj, (str, bool, int, float))):
        raise SessionError(f"value of type {type(obj).__name__} is not plain data", file=file,
                           field=where or None)


# --------------------------------------------------------------------------------------
# typed manifest models
# --------------------------------------------------------------------------------------
def _as_array(v: Any, shapes: tuple[tuple[int, ...], ...], what: str) -> list:
    if v is None:
        raise ValueError(f"must be {what}, got nothing")
    if isinstance(v, (str, bytes, dict)):
        raise ValueError(f"must be {what}, got {type(v).__name__}")
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"must be {what} of numbers") from None
    if a.shape not in shapes:
        raise ValueError(f"must be {what}, got shape {a.shape}")
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        idx = "".join(f"[{int(k)}]" for k in bad[0])
        raise ValueError(f"value{idx} is {a[tuple(bad[0])]}; only finite numbers are allowed")
    return a.tolist()


def _as_range(v: Any, what: str) -> list[int]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise ValueError(f"{what} must be [first, end) as two integers")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, numbers.Real) or not float(x).is_integer():
            raise ValueError(f"{what} must be [first, end) as two integers, got {list(v)!r}")
        out.append(int(x))
    return out


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, coerce_numbers_to_str=True,
                              frozen=True)


class VolumeModel(_Model):
    min: list[float]
    max: list[float]
    voxel_size: float | None = None   # None: chosen from the cameras' pixel footprint

    @field_validator("min", "max", mode="before")
    @classmethod
    def _vec3(cls, v):
        return _as_array(v, ((3,),), "a point [x, y, z] in metres")

    @field_validator("voxel_size")
    @classmethod
    def _positive(cls, v):
        if v is not None and v <= 0:
            raise ValueError(f"must be positive (metres), got {v}")
        return v


class MediumModel(_Model):
    n_ambient: float = Field(1.00029, gt=0)
    T_ambient: float = Field(293.15, gt=0)
    p_ambient: float = Field(101325.0, gt=0)
    gladstone_dale: float = Field(2.26e-4, gt=0)


class StrobeModel(_Model):
    search_frames: list[int]

    @field_validator("search_frames", mode="before")
    @classmethod
    def _range(cls, v):
        return _as_range(v, "search_frames")


class SyncModel(_Model):
    strobe: StrobeModel | None = None


class BackgroundModel(_Model):
    point: list[float] | None = None
    normal: list[float] | None = None
    distance: float | None = None

    @field_validator("point", "normal", mode="before")
    @classmethod
    def _vec3(cls, v):
        return None if v is None else _as_array(v, ((3,),), "a vector [x, y, z]")

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v):
        if v is not None and np.linalg.norm(v) == 0:
            raise ValueError("must not be the zero vector")
        return v

    @field_validator("distance")
    @classmethod
    def _positive(cls, v):
        if v is not None and v <= 0:
            raise ValueError(f"must be positive (metres in front of the camera), got {v}")
        return v

    @model_validator(mode="after")
    def _one_form(self):
        plane = self.point is not None or self.normal is not None
        if plane and self.distance is not None:
            raise ValueError("give either point + normal or distance, not both")
        if not plane and self.distance is None:
            raise ValueError("give point + normal, or distance")
        if plane and (self.point is None or self.normal is None):
            raise ValueError("a background plane needs both point and normal")
        return self


class RollingShutterModel(_Model):
    line_time: float = 0.0

    @field_validator("line_time")
    @classmethod
    def _non_negative(cls, v):
        if v < 0:
            raise ValueError(f"must be >= 0 seconds (0 = global shutter), got {v}")
        return v


class CameraModel(_Model):
    name: str = Field(min_length=1)
    frames: str = Field(min_length=1)
    reference: str = Field(min_length=1)
    image_size: list[int]
    K: list[list[float]]
    dist: list[float]
    R: list[list[float]] | None = None
    rvec: list[float] | None = None
    t: list[float]
    background: BackgroundModel
    rolling_shutter: RollingShutterModel = RollingShutterModel()
    time_offset: float | None = None
    interlaced: typing.Literal["top_first", "bottom_first"] | None = None

    @field_validator("image_size", mode="before")
    @classmethod
    def _size(cls, v):
        a = _as_array(v, ((2,),), "[width, height] in pixels")
        if any(x <= 0 or not float(x).is_integer() for x in a):
            raise ValueError(f"must be two positive integers [width, height], got {v!r}")
        return [int(x) for x in a]

    @field_validator("K", mode="before")
    @classmethod
    def _k(cls, v):
        a = np.asarray(_as_array(v, ((3, 3),), "a 3x3 matrix"))
        if not np.allclose(a[2], [0.0, 0.0, 1.0]):
            raise ValueError(f"last row must be [0, 0, 1], got {a[2].tolist()}")
        if a[0, 0] <= 0 or a[1, 1] <= 0:
            raise ValueError("focal lengths K[0][0] and K[1][1] must be positive")
        return a.tolist()

    @field_validator("dist", mode="before")
    @classmethod
    def _dist(cls, v):
        return _as_array(v, tuple((n,) for n in DIST_LENGTHS),
                         "a list of 4, 5, 8, 12 or 14 OpenCV distortion coefficients")

    @field_validator("R", mode="before")
    @classmethod
    def _rotation(cls, v):
        if v is None:
            return None
        a = np.asarray(_as_array(v, ((3, 3),), "a 3x3 rotation matrix"))
        err = float(np.max(np.abs(a @ a.T - np.eye(3))))
        if err > ORTHONORMAL_TOL:
            raise ValueError(f"is not orthonormal: max |R R^T - I| = {err:.3g} (tolerance {ORTHONORMAL_TOL:g})")
        det = float(np.linalg.det(a))
        if det < 0:
            raise ValueError(f"is a reflection (det = {det:.6g}), not a rotation (det = +1)")
        return a.tolist()

    @field_validator("rvec", mode="before")
    @classmethod
    def _rvec(cls, v):
        return None if v is None else _as_array(v, ((3,),), "a rotation vector [rx, ry, rz] in radians")

    @field_validator("t", mode="before")
    @classmethod
    def _t(cls, v):
        return _as_array(v, ((3,),), "a translation [tx, ty, tz] in metres")


class ManifestModel(_Model):
    format: str
    name: str | None = None
    frame_rate: float
    frames: list[int] | None = None
    volume: VolumeModel
    medium: MediumModel = MediumModel()
    sync: SyncModel | None = None
    cameras: list[CameraModel]
    allow_external_paths: bool = False

    @field_validator("frame_rate")
    @classmethod
    def _rate(cls, v):
        if v <= 0:
            raise ValueError(f"must be positive (frames per second), got {v}")
        return v

    @field_validator("frames", mode="before")
    @classmethod
    def _frames(cls, v):
        return None if v is None else _as_range(v, "frames")


# --------------------------------------------------------------------------------------
# pydantic errors -> one line naming file, camera and field
# --------------------------------------------------------------------------------------
def _dotted(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _model_of(annotation) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        m = _model_of(arg)
        if m is not None:
            return m
    return None


def _model_at(loc: tuple) -> type[BaseModel] | None:
    cls: type[BaseModel] | None = ManifestModel
    for part in loc:
        if isinstance(part, int):
            continue
        if cls is None or part not in cls.model_fields:
            return None
        cls = _model_of(cls.model_fields[part].annotation)
    return cls


def _suggest(word: str, options) -> str:
    close = difflib.get_close_matches(str(word), list(options), n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else ""


def _camera_name_at(raw: dict, loc: tuple) -> str | None:
    if len(loc) >= 2 and loc[0] == "cameras" and isinstance(loc[1], int):
        cams = raw.get("cameras")
        if isinstance(cams, list) and loc[1] < len(cams) and isinstance(cams[loc[1]], dict):
            name = cams[loc[1]].get("name")
            return str(name) if name is not None else f"#{loc[1]}"
    return None


def _validation_error(exc: ValidationError, raw: dict, file: str) -> SessionError:
    errors = exc.errors(include_url=False)
    # a misspelled field also makes the right one "missing": report the unknown one first
    errors.sort(key=lambda err: 0 if err["type"] == "extra_forbidden" else 1)
    e = errors[0]
    loc = tuple(e["loc"])
    kind = e["type"]
    if kind == "extra_forbidden":
        parent = _model_at(loc[:-1])
        options = list(parent.model_fields) if parent is not None else []
        msg = f"unknown field '{loc[-1]}'{_suggest(loc[-1], options)}"
    elif kind == "missing":
        msg = "required field is missing"
    elif kind == "value_error":
        msg = str(e["msg"]).removeprefix("Value error, ")
    else:
        got = repr(e.get("input"))
        if len(got) > 60:
            got = got[:57] + "..."
        msg = f"{e['msg']} (got {got})"
    if len(errors) > 1:
        msg += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return SessionError(msg, file=file, camera=_camera_name_at(raw, loc), field=_dotted(loc) or None)


# --------------------------------------------------------------------------------------
# the loaded session
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CameraSource:
    """Where a camera's frames and reference live (absolute paths, resolved).

    Attributes
    ----------
    name : str
    frames : str
        printf pattern of an image sequence or a video file.
    reference : str
        One image, a printf pattern or a video (averaged).
    frames_kind : {"sequence", "glob", "folder", "tiff", "video"}
    reference_kind : {"image", "sequence", "glob", "folder", "tiff", "video"}
    interlaced : {"top_first", "bottom_first"} or None
        Interlaced video: each frame is split into its two fields, read as frames of
        their own (:class:`~schlieren.storage.frames.InterlacedFields`).
    """

    name: str
    frames: str
    reference: str
    frames_kind: str
    reference_kind: str
    interlaced: str | None = None

    def open_frames(self) -> FrameSource:
        """Random-access reader of this camera's frames (see :func:`storage.frames.open_frames`)."""
        return open_frames(self, camera_name=self.name)


@dataclass(frozen=True, eq=False)
class Session:
    """A validated capture session.

    Attributes
    ----------
    name : str
    root : Path or str
        The session folder (absolute; a URL string for a session on object storage);
        manifest paths are relative to it.
    manifest : dict
        The manifest as loaded (plain JSON-compatible data).
    format : str
    frame_rate : float
        Frames per second of every camera (fields per second for interlaced cameras:
        twice the manifest's ``frame_rate``).
    frames : tuple of int or None
        Half-open range ``(A, B)`` of frames to process. None only when loaded with
        ``check_files=False`` and neither the manifest nor the caller gave a range.
    grid : Grid
    medium : Medium
    strobe_search : tuple of int or None
        Half-open frame range in which to look for the sync flash (None without
        ``sync.strobe``).
    cameras : list of Camera
        In manifest order, ``time_offset`` from the manifest (or None).
    sources : list of CameraSource
        Same order as ``cameras``.
    n_frames_available : int or None
        Frames every camera has (None with ``check_files=False``).
    manifest_path : Path
    allow_external_paths : bool
    dropped_frames : dict of str to tuple of int
        Frames (time slots) each camera dropped, by camera name (cameras with none are
        left out; empty with ``check_files=False``). They are excluded from the
        reconstruction; every other frame keeps its index = its capture time.
    video_slots : dict of str to (int, tuple of int)
        The timestamp scan (:meth:`~schlieren.storage.frames.VideoFrames.scan`) of each
        camera whose frames are a video, handed to the run's workers.
    opened : dict of int to ImageSequence
        The image-sequence readers the file checks opened, by camera index (with their
        listing and the frames they fetched from a URL): a run in this process reads
        through them instead of listing and fetching again. Not compared, not pickled.
    """

    name: str
    root: Path | str
    manifest: dict
    format: str
    frame_rate: float
    frames: tuple[int, int] | None
    grid: Grid
    medium: Medium
    strobe_search: tuple[int, int] | None
    cameras: list[Camera]
    sources: list[CameraSource]
    n_frames_available: int | None
    manifest_path: Path | str = field(default=Path(MANIFEST_NAME))
    allow_external_paths: bool = False
    dropped_frames: dict = field(default_factory=dict)
    video_slots: dict = field(default_factory=dict)
    opened: dict = field(default_factory=dict, compare=False, repr=False)

    def __getstate__(self):
        return {**self.__dict__, "opened": {}}

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def n_frames(self) -> int:
        """Number of frames to process, ``B - A``."""
        if self.frames is None:
            raise SessionError("the frame range is unknown (session loaded without file checks)",
                               file=str(self.manifest_path), field="frames")
        return self.frames[1] - self.frames[0]

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def source(self, name: str) -> CameraSource:
        for s in self.sources:
            if s.name == name:
                return s
        raise KeyError(name)


# --------------------------------------------------------------------------------------
# checks
# --------------------------------------------------------------------------------------
def parse_frame_range(value, *, what: str = "frames") -> tuple[int, int]:
    """``(A, B)`` from a pair or an ``"A:B"`` string (the CLI's ``--frames``)."""
    if isinstance(value, str):
        parts = value.split(":")
        if len(parts) != 2:
            raise ValueError(f"{what} must be A:B, got {value!r}")
        try:
            return int(parts[0]), int(parts[1])
        except ValueError:
            raise ValueError(f"{what} must be A:B with integers, got {value!r}") from None
    a, b = _as_range(list(value) if isinstance(value, tuple) else value, what)
    return a, b


def _check_range(rng: tuple[int, int], n: int | None, *, file: str, field: str, what: str) -> None:
    a, b = rng
    if a < 0 or b < 0:
        raise SessionError(f"{what} [{a}, {b}) has a negative frame index", file=file, field=field)
    if b <= a:
        raise SessionError(f"{what} [{a}, {b}) is empty (the end must be greater than the start)",
                           file=file, field=field)
    if n is not None and b > n:
        raise SessionError(f"{what} [{a}, {b}) goes beyond the {n} frames available",
                           file=file, field=field)


def _resolve(spec: str, root: Path | str, *, allow_external: bool, file: str, camera: str, field: str) -> str:
    if location.is_url(spec):
        if not allow_external:
            raise SessionError(f"URL {spec!r} is not allowed (paths are relative to the session folder "
                               "unless allow_external_paths: true)", file=file, camera=camera, field=field)
        return location.normalize(spec)
    remote = location.is_url(str(root))  # a session on object storage: "/"-separated paths below it
    if not allow_external:
        if spec.startswith("~") or os.path.isabs(spec) or re.match(r"^[A-Za-z]:[\\/]", spec):
            raise SessionError(f"absolute path {spec!r} is not allowed (paths are relative to the "
                               "session folder unless allow_external_paths: true)",
                               file=file, camera=camera, field=field)
        norm = os.path.normpath(spec)
        if norm == ".." or norm.startswith(".." + os.sep) or norm.startswith("../"):
            raise SessionError(f"path {spec!r} escapes the session folder (set allow_external_paths: "
                               "true to allow it)", file=file, camera=camera, field=field)
        if remote:
            return location.join(str(root), norm.replace(os.sep, "/"))
        out = str(root / norm)
        # folders on the way (a pattern's folder) may be symbolic links out of the session
        existing = out
        while not os.path.lexists(existing) and os.path.dirname(existing) != existing:
            existing = os.path.dirname(existing)
        _check_contained(existing, root, file=file, camera=camera, field=field, what=spec)
        return out
    spec = os.path.expanduser(spec)
    if os.path.isabs(spec):
        return spec
    return location.join(str(root), spec) if remote else os.path.normpath(str(root / spec))


def _check_contained(path: str, root: Path, *, file: str, camera: str | None, field: str | None,
                     what: str | None = None) -> None:
    """Refuse ``path`` if, with every symbolic link resolved, it is not inside ``root``."""
    if location.is_url(str(path)) or location.is_url(str(root)):
        return  # object stores have no symbolic links
    real = os.path.realpath(path)
    base = os.path.realpath(root)
    if real != base and not real.startswith(base.rstrip(os.sep) + os.sep):
        raise SessionError(f"path {what or path!r} leads outside the session folder through a symbolic link "
                           f"(to {real}); set allow_external_paths: true to allow it", file=file, camera=camera,
                           field=field)


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
        _check_contained(f, root, file=mfile, camera=cam.name,
                         field=f"cameras[{i}].frames" + (f"[{k}]" if k is not None else ""), what=f)
    refs = [src.reference]
    if src.reference_kind not in ("image", "video"):  # a sequence (pattern, glob, folder) or a TIFF
        with _qualified(i, "reference"):
            seq = open_frames(src.reference, camera_name=cam.name)
        if isinstance(seq, ImageSequence):
            refs = [seq.file_of(k) for k in seq.present()]
    for f in refs:
        _check_contained(f, root, file=mfile, camera=cam.name, field=f"cameras[{i}].reference", what=f)


def _human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover


def _total_memory() -> int:
    import psutil

    return int(psutil.virtual_memory().total)


def _check_volume(v: VolumeModel, file: str, cameras=None) -> Grid:
    lo, hi = np.asarray(v.min), np.asarray(v.max)
    for k, ax in enumerate("xyz"):
        if hi[k] <= lo[k]:
            raise SessionError(f"empty or inverted volume: max.{ax} = {hi[k]:g} is not greater than "
                               f"min.{ax} = {lo[k]:g}", file=file, field="volume.max")
    if v.voxel_size is None:
        if not cameras:
            raise SessionError("voxel_size is missing and there are no cameras to choose it from",
                               file=file, field="volume.voxel_size")
        voxel, info = auto_voxel_size(cameras, lo, hi)
        log.info("volume.voxel_size not given: %.2f mm chosen (%.2f px per voxel at a footprint of %.3f mm/px, "
                 "limited by %s)", 1e3 * voxel, info["px_per_voxel"], 1e3 * info["footprint"], info["limited_by"])
        v = v.model_copy(update={"voxel_size": voxel})
    grid = Grid(tuple(lo), tuple(hi), v.voxel_size)
    if min(grid.shape) < 1:
        raise SessionError(f"voxel_size {v.voxel_size:g} m gives an empty grid {grid.shape_xyz} (x, y, z) "
                           f"for a box of {tuple(float(e) for e in hi - lo)} m",
                           file=file, field="volume.voxel_size")
    n_vox = math.prod(grid.shape)
    need = BYTES_PER_VOXEL * n_vox
    total = _total_memory()
    if need > total:
        nx, ny, nz = grid.shape_xyz
        raise SessionError(
            f"voxel_size {v.voxel_size:g} m gives {nx}x{ny}x{nz} = {n_vox:.3g} voxels; the 3-D stage "
            f"needs about {_human_bytes(need)} per frame ({BYTES_PER_VOXEL:.0f} bytes/voxel, measured), more than this "
            f"machine's {_human_bytes(total)}: use a larger voxel_size", file=file, field="volume.voxel_size")
    return grid


def _camera_from_model(i: int, c: CameraModel, file: str) -> Camera:
    fld = f"cameras[{i}]"
    if c.R is not None and c.rvec is not None:
        raise SessionError("give either R or rvec, not both", file=file, camera=c.name, field=f"{fld}.R")
    if c.R is None and c.rvec is None:
        raise SessionError("required field is missing (give R, or rvec)", file=file, camera=c.name,
                           field=f"{fld}.R")
    R = np.asarray(c.R) if c.R is not None else rodrigues(c.rvec)
    t = np.asarray(c.t)
    if c.background.distance is not None:
        point, normal = Camera.background_from_distance(R, t, c.background.distance)
    else:
        point, normal = np.asarray(c.background.point), np.asarray(c.background.normal)
    # interlaced: each field is read at full height (missing rows interpolated), its rows one
    # field line apart; in the image's row numbering that is half the field line time per row
    line_time = c.rolling_shutter.line_time / (2.0 if c.interlaced else 1.0)
    return Camera(c.name, np.asarray(c.K), np.asarray(c.dist), R, t, tuple(c.image_size), point, normal,
                  line_time=line_time, time_offset=c.time_offset)


def _check_background(i: int, cam: Camera, file: str) -> None:
    fld = f"cameras[{i}].background"
    C, axis, n = cam.center, cam.optical_axis, cam.bg_normal
    denom = float(axis @ n)
    if abs(denom) < 1e-9:
        raise SessionError("the background plane is parallel to the camera's optical axis",
                           file=file, camera=cam.name, field=fld)
    s = float((cam.bg_point - C) @ n) / denom
    if s <= 0:
        raise SessionError(f"the background plane is behind the camera (it meets the optical axis "
                           f"{-s:.4g} m behind the camera centre)", file=file, camera=cam.name, field=fld)


def _check_background_beyond_volume(i: int, cam: Camera, grid: Grid, file: str) -> None:
    fld = f"cameras[{i}].background"
    C, axis, n = cam.center, cam.optical_axis, cam.bg_normal
    s = float((cam.bg_point - C) @ n) / float(axis @ n)
    depth = float((grid.center - C) @ axis)
    if depth > 0 and s <= depth:
        raise SessionError(f"the background plane ({s:.4g} m along the optical axis) is not behind the "
                           f"volume centre ({depth:.4g} m)", file=file, camera=cam.name, field=fld)


def _sees_volume(cam: Camera, grid: Grid) -> bool:
    """Conservative test: False only if no part of the box can be in the image."""
    pts = np.vstack([grid.corners(), grid.center[None, :]])
    Xc = pts @ cam.R.T + cam.t
    front = Xc[:, 2] > 0
    if not front.any():
        return False
    if not front.all():  # the box straddles the camera plane: the camera is next to or in it
        return True
    uv = cam.project(pts)
    W, H = cam.image_size
    lo, hi = -0.5, np.array([W - 0.5, H - 0.5])
    if np.any(np.all((uv >= lo) & (uv <= hi), axis=1)):
        return True
    # the projected box may still cover the image without a corner inside it
    umin, umax = uv.min(axis=0), uv.max(axis=0)
    return bool(np.all(umin <= hi) and np.all(umax >= lo))


class _qualified:
    """Re-raise a reader's SessionError with the manifest field of camera ``i`` in front.

    ``frames[3]`` becomes ``cameras[1].frames[3]``; no field becomes ``cameras[1].frames``.
    """

    def __init__(self, i: int, base: str):
        self.prefix = f"cameras[{i}]"
        self.base = base

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
        raise SessionError(exc.message, file=exc.file, camera=exc.camera, field=f) from None


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
                head = location.read_bytes(ref, 0, HEADER_BYTES)
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
        if seq.dropped:  # references are not a capture with drops: a lost file
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
        whole = head is not None and len(head) < HEADER_BYTES  # its size is known: no request for it
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


# --------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------
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

    raw = _read_yaml(manifest_path)
    if raw is None:
        raise SessionError("the manifest is empty", file=mfile)
    if not isinstance(raw, dict):
        raise SessionError(f"the manifest must be a mapping of fields, got {type(raw).__name__}", file=mfile)
    _check_plain(raw, "", mfile)

    fmt = raw.get("format")
    if fmt is None:
        raise SessionError(f"required field is missing (expected format: {SESSION_FORMAT})", file=mfile,
                           field="format")
    if fmt != SESSION_FORMAT:
        raise SessionError(f"unknown format {fmt!r}; this version reads {SESSION_FORMAT!r}", file=mfile,
                           field="format")

    try:
        m = ManifestModel.model_validate(raw)
    except ValidationError as exc:
        raise _validation_error(exc, raw, mfile) from None

    # ---- manifest-level checks --------------------------------------------------
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
    interlaced = m.cameras[0].interlaced is not None if m.cameras else False
    grid = _check_volume(m.volume, mfile) if m.volume.voxel_size is not None else None
    medium = Medium(**m.medium.model_dump())

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

    cameras: list[Camera] = []
    sources: list[CameraSource] = []
    for i, c in enumerate(m.cameras):
        cam = _camera_from_model(i, c, mfile)
        _check_background(i, cam, mfile)
        fr = _resolve(c.frames, root, allow_external=m.allow_external_paths, file=mfile, camera=c.name,
                      field=f"cameras[{i}].frames")
        ref = _resolve(c.reference, root, allow_external=m.allow_external_paths, file=mfile,
                       camera=c.name, field=f"cameras[{i}].reference")
        kind = _kind_of_frames(c.frames, mfile, c.name, f"cameras[{i}].frames")
        cameras.append(cam)
        sources.append(CameraSource(c.name, fr, ref, kind, _kind_of_reference(c.reference), c.interlaced))
    if grid is None:   # no voxel_size in the manifest: from the cameras' pixel footprint
        grid = _check_volume(m.volume, mfile, cameras)

    seeing = [cam.name for cam in cameras if _sees_volume(cam, grid)]
    if not seeing:
        raise SessionError("no camera sees any part of the volume (check volume, R and t)", file=mfile,
                           field="volume")
    for i, cam in enumerate(cameras):
        if cam.name not in seeing:
            log.warning("camera %s does not see the volume; it will contribute nothing", cam.name)
        _check_background_beyond_volume(i, cam, grid, mfile)

    # ---- files --------------------------------------------------------------------
    n_avail: int | None = None
    dropped: dict[str, tuple[int, ...]] = {}
    video_slots: dict[str, tuple[int, tuple[int, ...]]] = {}
    opened: list[FrameSource] = []
    if check_files:
        def open_camera(i: int) -> FrameSource:
            cam, src = cameras[i], sources[i]
            check = None if m.allow_external_paths else (
                lambda fs: _check_files_contained(i, cam, src, fs, range(len(fs)), root, mfile))
            with _qualified(i, "frames"):
                return _check_camera_files(i, cam, src, contained=check)

        remote = location.is_url(root)  # each check waits for requests: the cameras' together
        for i, (cam, src, fs) in enumerate(zip(cameras, sources, _per_camera(open_camera, len(cameras), remote))):
            if n_avail is None:
                n_avail = len(fs)
            elif len(fs) != n_avail:
                raise SessionError(f"has {len(fs)} frames but camera {cameras[0].name} has {n_avail}: every "
                                   "camera needs the same number of frames", file=src.frames, camera=cam.name,
                                   field=f"cameras[{i}].frames")
            opened.append(fs)
        if rng is None:
            rng = (0, n_avail)
        _check_range(rng, n_avail, file=mfile, field=rng_field, what=what)
        if strobe is not None:
            _check_range(strobe, n_avail, file=mfile, field="sync.strobe.search_frames",
                         what="search_frames")
        wanted = set(range(*rng)) | (set(range(*strobe)) if strobe else set())

        def check_content(i: int) -> None:
            cam, src, fs = cameras[i], sources[i], opened[i]
            with _qualified(i, "frames"):
                _check_frames_content(i, cam, fs, sorted(wanted), decode_all=decode_all_frames)
            with _qualified(i, "reference"):
                _check_reference(i, cam, src)
            inner = getattr(fs, "frames", fs)  # the video under interlaced fields
            if isinstance(inner, VideoFrames):
                video_slots[cam.name] = inner.scan()
            if fs.dropped:
                dropped[cam.name] = tuple(fs.dropped)
            if hasattr(fs, "close"):
                fs.close()
        # videos are decoded whole for their timestamps (dropped frames): the cameras together
        # (OpenCV's decoder releases the GIL; 1.4x on 2 cores for 1440x1080 H.264)
        videos = any(src.frames_kind == "video" for src in sources)
        _per_camera(check_content, len(cameras), remote or videos)
        if dropped:
            dropped = {c.name: dropped[c.name] for c in cameras if c.name in dropped}  # camera order
            log.warning("frames dropped by the cameras (never used; the other frames keep their capture "
                        "times): %s", "; ".join(f"{c} frame(s) {format_ranges(v)}" for c, v in dropped.items()))

    # after the file checks (which name the frame whose size differs from its camera's)
    sizes = {tuple(c.image_size) for c in m.cameras}
    if len(sizes) > 1:
        first = m.cameras[0]
        i, c = next((i, c) for i, c in enumerate(m.cameras) if tuple(c.image_size) != tuple(first.image_size))
        raise SessionError(f"image_size {list(c.image_size)} differs from camera {first.name}'s "
                           f"{list(first.image_size)}: every camera of a session needs the same image size "
                           "(resize or crop the frames of the odd cameras, and recalibrate them)", file=mfile,
                           camera=c.name, field=f"cameras[{i}].image_size")

    return Session(
        name=m.name if m.name is not None else location.basename(root),
        root=root,
        manifest=raw,
        format=m.format,
        frame_rate=float(m.frame_rate) * (2.0 if interlaced else 1.0),
        frames=rng,
        grid=grid,
        medium=medium,
        strobe_search=strobe,
        cameras=cameras,
        sources=sources,
        n_frames_available=n_avail,
        manifest_path=manifest_path,
        allow_external_paths=m.allow_external_paths,
        dropped_frames=dropped,
        video_slots=video_slots,
        opened={i: fs for i, fs in enumerate(opened) if isinstance(fs, ImageSequence)},
    )
