"""Checks of the manifest's numbers: frame ranges, the volume, and the camera geometry.

The volume must be a non-empty box whose grid fits in the machine's memory (its voxel
size chosen from the cameras' pixel footprint when the manifest gives none); every
camera's rotation, background plane and view of the volume are checked before any file
is opened.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict

import numpy as np

from schlieren.pipeline import resources as _resources
from schlieren.pipeline.calibration.sanity import RigSanityParams, centre_inside, rig_problems, sees_box
from schlieren.pipeline.geometry import Camera, Grid, auto_voxel_size, rodrigues
from schlieren.storage.errors import SchlierenInputError, SessionError
from schlieren.storage.session.models import CameraModel, VolumeModel, _as_range

log = logging.getLogger(__name__)

#: Working set of the 3-D stages per voxel and frame (the largest per-voxel coefficient
#: measured by benchmarks/memory.py, pipeline/resources.py), a first gate refusing grids
#: that cannot fit in the machine's memory whatever the cameras; the run's preflight
#: (workers/preflight.py) then checks the whole model times the workers.
BYTES_PER_VOXEL = _resources.BYTES_PER_VOXEL


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


def strobe_overlap(rng: tuple[int, int], strobe: tuple[int, int], what: str = "frames") -> str | None:
    """Why the frames to process ``rng`` may not meet the strobe window ``strobe`` (both
    half-open), or None when they are apart: a frame the flash lit cannot be reconstructed
    (the sync excludes it from the resampling)."""
    (a, b), (s0, s1) = rng, strobe
    if a >= s1 or s0 >= b:
        return None
    if b > s1:
        fix = f"[{s1}, {b})"
    elif a < s0:
        fix = f"[{a}, {s0})"
    else:
        fix = f"frames from {s1} on" + (f" or before {s0}" if s0 > 0 else "")
    return (f"the {what} [{a}, {b}) overlap sync.strobe.search_frames [{s0}, {s1}): a frame the flash "
            f"lit cannot be reconstructed; process frames outside the strobe window (e.g. {fix})")


def frames_beside_strobe(n: int, strobe: tuple[int, int] | None) -> tuple[int, int]:
    """The default frames to process of ``n`` frames: all of them without a strobe window,
    else the frames after it (before it, when it ends the recording)."""
    if strobe is None:
        return 0, n
    s0, s1 = strobe
    return (s1, n) if s1 < n else (0, s0)


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


def _sees_volume(cam: Camera, grid: Grid) -> bool:
    """Conservative test: False only if no part of the box can be in the image."""
    return sees_box(cam, grid.vmin, grid.vmax)


def check_rig(cameras, vmin, vmax, *, file: str, fields: dict[str, str] | None = None,
              error: type[SchlierenInputError] = SessionError,
              params: RigSanityParams = RigSanityParams()) -> None:
    """Calibration sanity (:func:`~schlieren.pipeline.calibration.sanity.rig_problems`)
    before any work: raise the first fatal problem as ``error`` naming ``file`` (the
    manifest or calibration file the user gave), the camera and its field
    (``fields[name] + "." + field``, default ``cameras[i].field``); log the warnings."""
    prefix = fields or {c.name: f"cameras[{i}]" for i, c in enumerate(cameras)}
    problems = rig_problems(cameras, vmin, vmax, **asdict(params))
    for p in problems:
        if p.fatal:
            fld = "volume" if p.camera is None else f"{prefix[p.camera]}.{p.field}"
            raise error(p.message, file=file, camera=p.camera, field=fld)
    for p in problems:
        log.warning("camera %s %s (file %s)", p.camera, p.message, file)
