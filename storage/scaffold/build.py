"""Scaffold a session folder (:func:`scaffold_session`): check the frames against the
calibration, then write the references and a manifest that the session reader accepts."""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import yaml

from schlieren.pipeline.geometry import Camera, Grid, Medium, auto_voxel_size
from schlieren.storage.calibration_io import CalibrationFile, read_calibration
from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.readers.kinds import frames_kind
from schlieren.storage.readers.opening import open_frames
from schlieren.storage.scaffold.sources import VideoInfo, probe_source, source_kind, write_reference_frames
from schlieren.storage.session.checks import check_rig, frames_beside_strobe, strobe_overlap
from schlieren.storage.session.models import camera_name_problem

log = logging.getLogger(__name__)

SESSION_FORMAT = "schlieren-session/1"
MANIFEST_NAME = "session.yaml"
_FPS_RTOL = 1e-3


# long only for its docstring (every option of `schlieren init`); the body is the named steps below
def scaffold_session(session_dir: str | os.PathLike, videos: Mapping[str, str],
                     calibration: str | os.PathLike | CalibrationFile, *,
                     reference_frames: tuple[int, int], volume_min: Sequence[float],
                     volume_max: Sequence[float], voxel_size: float | None = None,
                     frame_rate: float | None = None, frames: tuple[int, int] | None = None,
                     strobe_frames: tuple[int, int] | None = None,
                     time_offsets: float | Mapping[str, float] | None = None,
                     line_times: float | Mapping[str, float] | None = None,
                     background_distance: float | Mapping[str, float] | None = None,
                     medium: Medium | None = None, name: str | None = None,
                     copy_videos: bool = False, count_frames: bool = False,
                     overwrite: bool = False, interlaced: str | Mapping[str, str] | None = None) -> Path:
    """Check the cameras' frames (videos or image sequences) against the calibration and
    write ``SESSION_DIR/session.yaml``.

    Parameters
    ----------
    session_dir : path
        Created if missing.
    videos : mapping of str to str
        Camera name -> frames specification (:func:`find_sources`: a video, an image
        sequence pattern, glob or folder, or a multi-page TIFF); every name must be in
        the calibration.
    calibration : path or CalibrationFile
    reference_frames : (int, int)
        Half-open range of frames without flow, averaged into each camera's reference.
    volume_min, volume_max : sequence of 3 floats
        Reconstruction box corners (world x, y, z), metres.
    voxel_size : float, optional
        Metres. Default: none in the manifest, so that the session reader chooses it from
        the cameras' pixel footprint (docs/session.md, ``volume.voxel_size``).
    frame_rate : float, optional
        Frames per second; default: the videos' (which must agree).
    frames : (int, int), optional
        Half-open range of frames to process; it may not overlap ``strobe_frames``.
        Default: every frame, or with ``strobe_frames`` the frames after the strobe window
        (before it, when it ends the recording).
    strobe_frames : (int, int), optional
        Frames where to look for the sync flash (``sync.strobe.search_frames``).
    time_offsets : float or mapping, optional
        Per-camera ``time_offset`` (seconds), or one value for all; needed without
        ``strobe_frames``.
    line_times : float or mapping, optional
        Rolling-shutter line time (seconds), one value or per camera; default 0 (global).
    background_distance : float or mapping, optional
        For cameras whose calibration has no background plane (metres along the axis).
    medium : Medium, optional
        Written as the ``medium`` block (defaults if None).
    name : str, optional
        Session name (default: the folder's name).
    copy_videos : bool
        Copy videos from outside the session folder into ``<camera>/``.
    count_frames : bool
        Count frames by decoding (exact) rather than trusting the containers.
    overwrite : bool
        Replace an existing ``session.yaml``.
    interlaced : str or mapping, optional
        ``"top_first"`` or ``"bottom_first"`` for every camera, or per camera: the frames
        are interlaced video whose two fields are processed as frames of their own
        (docs/session.md, "Interlaced video").

    Returns
    -------
    Path
        The manifest written.

    Raises
    ------
    SchlierenInputError
        One line naming the file, the camera and the field.
    """
    root = Path(session_dir)
    manifest_path = root / MANIFEST_NAME
    if manifest_path.exists() and not overwrite:
        raise SchlierenInputError("a session manifest already exists (use --force to replace it)",
                                  file=str(manifest_path))
    for n, spec in videos.items():
        why = camera_name_problem(n)
        if why is not None:
            raise SchlierenInputError(f"{why}; name the frames NAME=PATH", file=spec, field="name")
    calib, order = _calibrated_cameras(videos, calibration)
    infos = _probe_sources(videos, order, calib, count_frames)
    frame_rate = _frame_rate(infos, order, frame_rate)
    n_frames = infos[order[0]].frame_count
    reference_frames, frames, strobe_frames = _frame_ranges(n_frames, reference_frames, frames, strobe_frames)
    offsets, lines, fields = _timing(order, strobe_frames, time_offsets, line_times, interlaced)
    vmin, vmax = _volume(volume_min, volume_max, voxel_size)
    cameras, entries = _cameras(calib, order, vmin, vmax, background_distance)
    grid = _grid(vmin, vmax, voxel_size, cameras)
    plan = _Plan(root, manifest_path, calib, order, dict(videos), float(frame_rate), n_frames, reference_frames,
                 frames, strobe_frames, offsets, lines, fields, vmin, vmax,
                 None if voxel_size is None else float(voxel_size), grid, cameras, entries)
    _write_session(plan, copy_videos=copy_videos, medium=medium, name=name)
    log.info("wrote %s", manifest_path)
    return manifest_path


@dataclass(frozen=True)
class _Plan:
    """What :func:`scaffold_session` checked, from which it writes the session folder."""

    root: Path
    manifest_path: Path
    calib: CalibrationFile
    order: list[str]  # camera names in calibration order
    videos: dict[str, str]
    frame_rate: float
    n_frames: int
    reference_frames: tuple[int, int]
    frames: tuple[int, int] | None
    strobe_frames: tuple[int, int] | None
    offsets: dict[str, float]
    lines: dict[str, float]
    fields: dict[str, str]
    vmin: np.ndarray
    vmax: np.ndarray
    voxel_size: float | None  # None: the session reader chooses it (the grid holds its choice)
    grid: Grid
    cameras: list[Camera]
    entries: list[tuple[dict, dict]]  # (calibration entry, background) per camera


# --------------------------------------------------------------------------------------
# checks
# --------------------------------------------------------------------------------------
def _calibrated_cameras(videos: Mapping[str, str], calibration) -> tuple[CalibrationFile, list[str]]:
    """The calibration, and the cameras with frames in calibration order (each in it)."""
    if not videos:
        raise SchlierenInputError("no camera frames given (videos or image sequences)", field="videos")
    calib = calibration if isinstance(calibration, CalibrationFile) else read_calibration(calibration)
    names = list(videos)
    for n in names:
        if n not in calib.names:
            raise SchlierenInputError(f"no camera of that name in the calibration (it has "
                                      f"{', '.join(calib.names)}); name the frames NAME=PATH",
                                      file=videos[n], camera=n)
    missing = [n for n in calib.names if n not in videos]
    if missing:
        log.warning("calibrated camera(s) without frames are left out: %s", ", ".join(missing))
    order = [n for n in calib.names if n in videos]  # calibration order
    return calib, order


def _probe_sources(videos: Mapping[str, str], order: list[str], calib: CalibrationFile,
                   count_frames: bool) -> dict[str, VideoInfo]:
    """Every camera's frames probed: the calibration's size, the same size and frame count for all."""
    infos = {n: probe_source(videos[n], camera=n, count_frames=count_frames) for n in order}
    first = order[0]
    for n in order:
        info, entry = infos[n], calib.camera(n)
        what = source_kind(info.path)
        if list(info.size) != list(entry["image_size"]):
            raise SchlierenInputError(
                f"the {what}'s frames are {info.width}x{info.height} pixels but the calibration's image_size "
                f"is {entry['image_size'][0]}x{entry['image_size'][1]}", file=info.path, camera=n,
                field="image_size")
        if info.size != infos[first].size:
            raise SchlierenInputError(f"the {what}'s frames are {info.width}x{info.height} pixels but camera "
                                      f"{first}'s are {infos[first].width}x{infos[first].height}; "
                                      "every camera needs the same size", file=info.path, camera=n,
                                      field="image_size")
        if info.frame_count != infos[first].frame_count:
            raise SchlierenInputError(_count_mismatch(what, info, first, infos[first]), file=info.path, camera=n,
                                      field="frames")
    return infos


def _count_mismatch(what: str, info: VideoInfo, first: str, other: VideoInfo) -> str:
    """The frame counts of two cameras differ: how to make them agree without shifting
    the timing (frames missing between others are dropped frames, kept in their slots)."""
    text = f"the {what} has {info.frame_count} frames but camera {first}'s has {other.frame_count}"
    if what == "video":
        return text + "; cut the longer videos at their end so every camera has the same frames"
    return (text + " (counted to the last numbered file; a file missing between others is a dropped frame "
            "and keeps its slot); remove the extra files at the end of the longer sequences")


def _frame_rate(infos: dict[str, VideoInfo], order: list[str], frame_rate: float | None) -> float:
    """The given frame rate (positive), else the videos' (which must agree)."""
    first = order[0]
    rates = {n: infos[n].fps for n in order}
    if frame_rate is None:
        if any(r <= 0 for r in rates.values()):
            bad = next(n for n in order if rates[n] <= 0)
            raise SchlierenInputError("the frames do not state their frame rate (image sequences never do); "
                                      "give --frame-rate",
                                      file=infos[bad].path, camera=bad, field="frame_rate")
        for n in order:
            if abs(rates[n] - rates[first]) > _FPS_RTOL * rates[first]:
                raise SchlierenInputError(f"the video runs at {rates[n]:.4g} fps but camera {first}'s at "
                                          f"{rates[first]:.4g} fps (give --frame-rate if the containers "
                                          "are wrong)", file=infos[n].path, camera=n, field="frame_rate")
        frame_rate = float(np.mean(list(rates.values())))
    elif frame_rate <= 0:
        raise SchlierenInputError("the frame rate must be positive", field="frame_rate")
    else:
        for n in order:
            if rates[n] > 0 and abs(rates[n] - frame_rate) > _FPS_RTOL * frame_rate:
                log.warning("camera %s: the video says %.4g fps; using the given %.4g", n, rates[n],
                            frame_rate)
    return frame_rate


def _frame_ranges(n_frames: int, reference_frames, frames, strobe_frames):
    """The reference, processed and strobe frame ranges, each inside the ``n_frames``; the
    processed frames apart from the strobe window (by default the frames beside it)."""
    reference_frames = _check_range(reference_frames, n_frames, "reference_frames")
    if strobe_frames is not None:
        strobe_frames = _check_range(strobe_frames, n_frames, "sync.strobe.search_frames")
    if frames is not None:
        frames = _check_range(frames, n_frames, "frames")
        if strobe_frames is not None and strobe_overlap(frames, strobe_frames) is not None:
            raise SchlierenInputError(strobe_overlap(frames, strobe_frames).replace("sync.strobe.search_frames",
                                                                                    "the --strobe-frames"),
                                      field="sync.strobe.search_frames")
    elif strobe_frames is not None:
        frames = frames_beside_strobe(n_frames, strobe_frames)
        log.info("frames %s processed: those after (or before) the strobe window %s", list(frames),
                 list(strobe_frames))
    if frames is not None and frames[0] < reference_frames[1] and reference_frames[0] < frames[1]:
        log.warning("the processed frames %s overlap the reference frames %s", list(frames),
                    list(reference_frames))
    return reference_frames, frames, strobe_frames


def _timing(order: list[str], strobe_frames, time_offsets, line_times, interlaced):
    """Per camera: time offsets (every camera needs one without a strobe), line times, interlacing."""
    offsets = _per_camera(time_offsets, order, "time_offset")
    if strobe_frames is None:
        lacking = [n for n in order if n not in offsets]
        if lacking:
            raise SchlierenInputError("no time offset and no strobe: give --strobe-frames A:B (a flash seen "
                                      "by every camera) or --time-offset [NAME=]SECONDS",
                                      camera=lacking[0], field="time_offset")
    lines = _per_camera(line_times, order, "rolling_shutter.line_time")
    if isinstance(interlaced, str) or interlaced is None:
        fields = {n: interlaced for n in order} if interlaced else {}
    else:
        fields = dict(interlaced)
    for n, v in fields.items():
        if n not in order:
            raise SchlierenInputError("interlacing given for a camera without frames", camera=n, field="interlaced")
        if v not in ("top_first", "bottom_first"):
            raise SchlierenInputError(f"interlaced must be top_first or bottom_first, got {v!r}", camera=n,
                                      field="interlaced")
    for n, v in lines.items():
        if v < 0:
            raise SchlierenInputError("the line time must be >= 0 seconds", camera=n,
                                      field="rolling_shutter.line_time")
    return offsets, lines, fields


def _volume(volume_min, volume_max, voxel_size) -> tuple[np.ndarray, np.ndarray]:
    """The box corners (``min < max``), a given voxel positive and no larger than the box."""
    vmin = np.asarray(volume_min, dtype=np.float64).ravel()
    vmax = np.asarray(volume_max, dtype=np.float64).ravel()
    if vmin.shape != (3,) or vmax.shape != (3,) or not np.all(vmax > vmin):
        raise SchlierenInputError("the volume needs min < max in x, y and z (metres)", field="volume")
    if voxel_size is not None:
        if not voxel_size > 0:
            raise SchlierenInputError("the voxel size must be positive (metres)", field="volume.voxel_size")
        if min(Grid(tuple(vmin), tuple(vmax), float(voxel_size)).shape) < 1:
            raise SchlierenInputError(f"the voxel size {voxel_size} m is larger than the volume", field="volume")
    return vmin, vmax


def _grid(vmin: np.ndarray, vmax: np.ndarray, voxel_size: float | None, cameras: list[Camera]) -> Grid:
    """The grid of the given voxel, or of the one the session reader will choose from the
    cameras' pixel footprint (:func:`~schlieren.pipeline.geometry.auto_voxel_size`)."""
    if voxel_size is None:
        voxel_size, info = auto_voxel_size(cameras, vmin, vmax)
        log.info("voxel %.2f mm chosen from the cameras' pixel footprint (%.2f px per voxel, limited by %s)",
                 1e3 * voxel_size, info["px_per_voxel"], info["limited_by"])
    return Grid(tuple(vmin), tuple(vmax), float(voxel_size))


def _cameras(calib: CalibrationFile, order: list[str], vmin: np.ndarray, vmax: np.ndarray, background_distance):
    """Every camera with its background plane (from the calibration or ``background_distance``,
    in front of it), and a sane rig (:func:`~schlieren.storage.session.checks.check_rig`)."""
    bg_dist = _per_camera(background_distance, order, "background.distance")
    entries, cameras = [], []
    for n in order:
        e = calib.camera(n)
        bg = e.get("background")
        if bg is None:
            if n not in bg_dist:
                raise SchlierenInputError("the calibration has no background plane for this camera; give "
                                          "--background-distance [NAME=]METRES (or calibrate with "
                                          "--background-board)", file=calib.path, camera=n,
                                          field="background")
            if not bg_dist[n] > 0:
                raise SchlierenInputError("the background distance must be positive", camera=n,
                                          field="background.distance")
            bg = {"distance": bg_dist[n]}
        if "distance" in bg:
            point, normal = Camera.background_from_distance(e["R"], e["t"], bg["distance"])
        else:
            point, normal = bg["point"], bg["normal"]
        cam = Camera(n, e["K"], e["dist"], e["R"], e["t"], tuple(e["image_size"]), point, normal)
        if cam.background_distance() <= 0:
            raise SchlierenInputError("the background plane is behind the camera", file=calib.path,
                                      camera=n, field="background")
        cameras.append(cam)
        entries.append((e, bg))
    # units, placement, visibility: before the grid (a voxel from a millimetre rig's footprint is absurd)
    check_rig(cameras, vmin, vmax, file=calib.path, error=SchlierenInputError,
              fields={n: f"cameras[{calib.names.index(n)}]" for n in order})
    return cameras, entries


# --------------------------------------------------------------------------------------
# the files
# --------------------------------------------------------------------------------------
def _write_session(plan: _Plan, *, copy_videos: bool, medium: Medium | None, name: str | None) -> None:
    """Place the frames, write the references and the manifest, and load it back with the
    session reader before it is put in place; everything created here is removed again if
    anything fails."""
    root, manifest_path = plan.root, plan.manifest_path
    created: list[Path] = []  # paths this call created, removed on failure
    if not root.exists():
        created.append(root)
    tmp = manifest_path.with_name(MANIFEST_NAME + ".tmp")
    try:
        root.mkdir(parents=True, exist_ok=True)
        cam_docs, external = _camera_docs(plan, copy_videos, created)
        manifest = _manifest(plan, cam_docs, external, medium, name)
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write("\n".join(_header(plan)) + "\n")
            yaml.safe_dump(manifest, fh, sort_keys=False, default_flow_style=None, width=100)
        from schlieren.storage.session import load_session

        try:  # the reader `schlieren run` uses: fail here, before the manifest is in place
            load_session(tmp)
        except SchlierenInputError as exc:
            raise _named_for_user(exc, tmp, plan) from None
        os.replace(tmp, manifest_path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        for p in reversed(created):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            elif p.exists():
                p.unlink()
        raise


def _named_for_user(exc: SchlierenInputError, tmp: Path, plan: _Plan) -> SchlierenInputError:
    """The session reader's error on the temporary manifest, naming instead the file the
    user gave: the calibration for a camera's geometry, else the manifest to be written."""
    if exc.file is None or Path(exc.file).resolve() != tmp.resolve():
        return exc
    geometry = exc.camera is not None and exc.field is not None and \
        exc.field.split(".")[-1].split("[")[0] in ("K", "dist", "R", "rvec", "t", "background", "distance")
    if geometry and exc.camera in plan.calib.names:
        field = exc.field.replace(exc.field.split(".")[0], f"cameras[{plan.calib.names.index(exc.camera)}]", 1)
        return type(exc)(exc.message, file=plan.calib.path, camera=exc.camera, field=field)
    return type(exc)(exc.message, file=str(plan.manifest_path), camera=exc.camera, field=exc.field)


def _camera_docs(plan: _Plan, copy_videos: bool, created: list[Path]) -> tuple[list[dict], bool]:
    """Each camera's manifest entry, its frames placed and its reference frames written;
    and whether some frames stay outside the session folder."""
    root, videos, reference_frames = plan.root, plan.videos, plan.reference_frames
    lines, fields, offsets = plan.lines, plan.fields, plan.offsets
    external = False
    cam_docs = []
    for (e, bg), cam in zip(plan.entries, plan.cameras):
        n = cam.name
        video = videos[n]
        frames_spec, is_external = _place_frames(video, root, n, copy_videos, created)
        external = external or is_external
        ref_dir = root / n / "reference"
        for p in (root / n, ref_dir):
            if not p.exists():
                created.append(p)
        write_reference_frames(video, reference_frames, ref_dir, camera=n)
        ext = ".png" if any(ref_dir.glob("00000.png")) else ".tif"
        doc = {
            "name": n,
            "frames": frames_spec,
            "reference": f"{n}/reference/%05d{ext}",
            "image_size": list(e["image_size"]),
            "K": e["K"],
            "dist": e["dist"],
            "R": e["R"],
            "t": e["t"],
            "background": bg,
            "rolling_shutter": {"line_time": float(lines.get(n, 0.0))},
        }
        if n in fields:
            doc["interlaced"] = fields[n]
        if n in offsets:
            doc["time_offset"] = offsets[n]
        cam_docs.append(doc)
    return cam_docs, external


def _manifest(plan: _Plan, cam_docs: list[dict], external: bool, medium: Medium | None, name: str | None) -> dict:
    """The ``schlieren-session/1`` manifest."""
    root, frames, strobe_frames = plan.root, plan.frames, plan.strobe_frames
    med = medium or Medium()
    manifest = {
        "format": SESSION_FORMAT,
        "name": name or root.resolve().name,
        "frame_rate": plan.frame_rate,
    }
    if frames is not None:
        manifest["frames"] = [int(frames[0]), int(frames[1])]
    manifest["volume"] = {"min": [float(v) for v in plan.vmin], "max": [float(v) for v in plan.vmax]}
    if plan.voxel_size is not None:  # else the session reader chooses it from the cameras
        manifest["volume"]["voxel_size"] = plan.voxel_size
    manifest["medium"] = {"n_ambient": med.n_ambient, "T_ambient": med.T_ambient,
                          "p_ambient": med.p_ambient, "gladstone_dale": med.gladstone_dale}
    if strobe_frames is not None:
        manifest["sync"] = {"strobe": {"search_frames": [int(strobe_frames[0]), int(strobe_frames[1])]}}
    if external:
        manifest["allow_external_paths"] = True
    manifest["cameras"] = cam_docs
    return manifest


def _header(plan: _Plan) -> list[str]:
    """The manifest's comment lines: where it came from, the frames, the grid, the calibration's RMS."""
    calib, order, grid, reference_frames = plan.calib, plan.order, plan.grid, plan.reference_frames
    n_frames, frame_rate = plan.n_frames, plan.frame_rate
    header = [f"# Written by `schlieren init` from {os.path.abspath(calib.path)}",
              f"# {len(order)} cameras, {n_frames} frames each at {frame_rate:.6g} fps; reference = frames "
              f"[{reference_frames[0]}, {reference_frames[1]}) of each camera's frames",
              f"# grid {grid.shape[2]} x {grid.shape[1]} x {grid.shape[0]} voxels (x, y, z)"
              + ("" if plan.voxel_size is not None else
                 f" of {1e3 * grid.voxel_size:.2f} mm, chosen by the session reader from the cameras' "
                 "pixel footprint (no voxel_size)")]
    for n in order:
        e = calib.camera(n)
        if "rms" in e:
            header.append(f"# {n}: calibration RMS {float(e['rms']):.3f} px over "
                          f"{e.get('n_views', '?')} views")
    return header


def _check_range(rng, n: int, what: str, *, file: str | None = None) -> tuple[int, int]:
    a, b = int(rng[0]), int(rng[1])
    if a < 0 or b <= a:
        raise SchlierenInputError(f"{what} [{a}, {b}) must be a non-empty range of frames from 0",
                                  file=file, field=what)
    if b > n:
        raise SchlierenInputError(f"{what} [{a}, {b}) goes beyond the {n} frames of the cameras",
                                  file=file, field=what)
    return a, b


def _per_camera(value, names, what: str) -> dict:
    if value is None:
        return {}
    if isinstance(value, Mapping):
        unknown = [k for k in value if k not in names]
        if unknown:
            raise SchlierenInputError(f"{what} given for a camera without frames (cameras: "
                                      f"{', '.join(names)})", camera=unknown[0], field=what)
        return {k: float(v) for k, v in value.items()}
    return {n: float(value) for n in names}


def _rel_inside(path: str, root: Path) -> str | None:
    try:
        rel = Path(os.path.realpath(path)).relative_to(Path(os.path.realpath(root)))
    except ValueError:
        return None
    return rel.as_posix()


def _place_frames(spec: str, root: Path, camera: str, copy: bool, created: list) -> tuple[str, bool]:
    """The manifest's ``frames`` for a camera's source: relative inside ``root``, copied into
    ``root/<camera>/`` when ``copy``, else absolute (external). Returns ``(spec, external)``."""
    kind = frames_kind(spec)
    folder = "/" if kind == "folder" else ""  # a folder stays one in the manifest (relative to it)
    rel = _rel_inside(spec, root)
    if rel is not None:
        return rel.rstrip("/") + folder, False
    if not copy:
        return os.path.abspath(spec).rstrip("/") + folder, True
    if kind in ("video", "tiff"):
        dest = root / camera / Path(spec).name
        files, new_spec = [spec], dest
    else:  # an image sequence: its files into <camera>/frames/, same names
        src = open_frames(spec, camera_name=camera)
        files = [src.file_of(i) for i in src.present()]  # not the frames the camera dropped
        dest = root / camera / "frames"
        new_spec = dest / ("" if kind == "folder" else Path(spec).name)
    for p in (root / camera, dest if kind not in ("video", "tiff") else None):
        if p is not None and not p.exists():
            created.append(p)
    folder = dest.parent if kind in ("video", "tiff") else dest
    folder.mkdir(parents=True, exist_ok=True)
    log.info("copying %d file(s) of camera %s into %s", len(files), camera, folder)
    for f in files:
        target = folder / Path(f).name
        if not target.exists():
            created.append(target)
        shutil.copy2(f, target)
    rel = _rel_inside(str(new_spec), root)
    return (rel + "/" if kind == "folder" else rel), False
