"""The loaded session: :class:`Session` and each camera's :class:`CameraSource`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from schlieren.pipeline.geometry import Camera, Grid, Medium
from schlieren.storage.errors import SessionError
from schlieren.storage.readers.base import FrameSource
from schlieren.storage.readers.opening import open_frames

SESSION_FORMAT = "schlieren-session/1"
MANIFEST_NAME = "session.yaml"


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
