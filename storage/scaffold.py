"""Scaffold a capture session (``schlieren init``): frames + calibration -> ``session.yaml``.

:func:`scaffold_session` checks every camera's frames (a video, an image sequence given
by a printf pattern, a glob pattern or a folder, or a multi-page TIFF: frame count, size,
frame rate must agree, and the size must be the calibration's ``image_size``), extracts
each camera's reference (no-flow) frames, and writes a ``schlieren-session/1`` manifest
(docs/session.md) that ``schlieren run`` accepts. The manifest is loaded back with the
session reader before it is put in place; if anything fails, whatever this call created
is removed again (a failed init leaves nothing behind, so the retry is not refused).

* ``frames:`` the source itself; relative to the session folder when it lies inside it,
  else copied into ``<camera>/`` (``copy_videos=True``) or referenced by absolute path
  with ``allow_external_paths: true``.
* ``reference:`` the frames ``[A, B)`` of the same source, written losslessly as
  ``<camera>/reference/%05d.png`` (the very pixels the decoder returns, renumbered from
  0; 16-bit stays 16-bit, float frames become ``.tif``); the session reader averages them. A printf pattern rather than one averaged
  image keeps the grey-level scale of the video frames exactly (an averaged 8-bit image
  would be re-quantised, a 16-bit one would be on another scale).
* camera geometry (``image_size, K, dist, R, t, background``) copied from the
  calibration file (``schlieren calibrate``); ``background: {distance: D}`` for cameras
  whose calibration has none when ``background_distance`` is given.
* ``volume``, ``frame_rate`` (from the videos unless given), ``frames``,
  ``sync.strobe.search_frames`` or per-camera ``time_offset``, ``rolling_shutter``.
"""

from __future__ import annotations

import glob
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np
import yaml

from schlieren.pipeline.geometry import Camera, Grid, Medium
from schlieren.storage.calibration_io import CalibrationFile, read_calibration
from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.frames import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, frames_kind, is_pattern, open_frames

__all__ = ["VideoInfo", "probe_video", "probe_source", "find_sources", "find_videos", "write_reference_frames",
           "scaffold_session", "SESSION_FORMAT", "MANIFEST_NAME"]

log = logging.getLogger(__name__)

SESSION_FORMAT = "schlieren-session/1"
MANIFEST_NAME = "session.yaml"
_FPS_RTOL = 1e-3


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
    are written as PNG, float frames as ``%05d.tif``. Stale numbered files of an earlier
    run in ``out_dir`` are removed first.

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
        for k in range(a, b):
            raw = src.read_raw(k)
            ext = ".png" if raw.dtype in (np.uint8, np.uint16) else ".tif"
            dest = out / f"{k - a:05d}{ext}"
            if not cv2.imwrite(str(dest), raw):
                raise SchlierenInputError("cannot write the reference frame", file=str(dest), camera=camera)
        return b - a
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


def _check_range(rng, n: int, what: str, *, file: str | None = None) -> tuple[int, int]:
    a, b = int(rng[0]), int(rng[1])
    if a < 0 or b <= a:
        raise SchlierenInputError(f"{what} [{a}, {b}) must be a non-empty range of frames from 0",
                                  file=file, field=what)
    if b > n:
        raise SchlierenInputError(f"{what} [{a}, {b}) goes beyond the {n} frames of the videos",
                                  file=file, field=what)
    return a, b


def _per_camera(value, names, what: str) -> dict:
    if value is None:
        return {}
    if isinstance(value, Mapping):
        unknown = [k for k in value if k not in names]
        if unknown:
            raise SchlierenInputError(f"{what} given for a camera without a video (cameras: "
                                      f"{', '.join(names)})", camera=unknown[0], field=what)
        return {k: float(v) for k, v in value.items()}
    return {n: float(value) for n in names}


def _rel_inside(path: str, root: Path) -> str | None:
    try:
        rel = Path(os.path.realpath(path)).relative_to(Path(os.path.realpath(root)))
    except ValueError:
        return None
    return rel.as_posix()


def scaffold_session(session_dir: str | os.PathLike, videos: Mapping[str, str],
                     calibration: str | os.PathLike | CalibrationFile, *,
                     reference_frames: tuple[int, int], volume_min: Sequence[float],
                     volume_max: Sequence[float], voxel_size: float,
                     frame_rate: float | None = None, frames: tuple[int, int] | None = None,
                     strobe_frames: tuple[int, int] | None = None,
                     time_offsets: float | Mapping[str, float] | None = None,
                     line_times: float | Mapping[str, float] | None = None,
                     background_distance: float | Mapping[str, float] | None = None,
                     medium: Medium | None = None, name: str | None = None,
                     copy_videos: bool = False, count_frames: bool = False,
                     overwrite: bool = False, interlaced: str | Mapping[str, str] | None = None) -> Path:
    """Check the videos against the calibration and write ``SESSION_DIR/session.yaml``.

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
    voxel_size : float
        Metres.
    frame_rate : float, optional
        Frames per second; default: the videos' (which must agree).
    frames : (int, int), optional
        Half-open range of frames to process.
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
    if not videos:
        raise SchlierenInputError("no videos given", field="videos")
    calib = calibration if isinstance(calibration, CalibrationFile) else read_calibration(calibration)
    names = list(videos)
    for n in names:
        if n not in calib.names:
            raise SchlierenInputError(f"no camera of that name in the calibration (it has "
                                      f"{', '.join(calib.names)}); name the video NAME=PATH",
                                      file=videos[n], camera=n)
    missing = [n for n in calib.names if n not in videos]
    if missing:
        log.warning("calibrated camera(s) without a video are left out: %s", ", ".join(missing))
    order = [n for n in calib.names if n in videos]  # calibration order

    # ---- the videos ------------------------------------------------------------------
    infos = {n: probe_source(videos[n], camera=n, count_frames=count_frames) for n in order}
    first = order[0]
    for n in order:
        info, entry = infos[n], calib.camera(n)
        if list(info.size) != list(entry["image_size"]):
            raise SchlierenInputError(
                f"video frames are {info.width}x{info.height} pixels but the calibration's image_size "
                f"is {entry['image_size'][0]}x{entry['image_size'][1]}", file=info.path, camera=n,
                field="image_size")
        if info.size != infos[first].size:
            raise SchlierenInputError(f"video frames are {info.width}x{info.height} pixels but camera "
                                      f"{first}'s are {infos[first].width}x{infos[first].height}; "
                                      "every camera needs the same size", file=info.path, camera=n,
                                      field="image_size")
        if info.frame_count != infos[first].frame_count:
            raise SchlierenInputError(f"the video has {info.frame_count} frames but camera {first}'s has "
                                      f"{infos[first].frame_count}; trim the videos to the same frames",
                                      file=info.path, camera=n, field="frames")
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
    n_frames = infos[first].frame_count
    reference_frames = _check_range(reference_frames, n_frames, "reference_frames")
    if frames is not None:
        frames = _check_range(frames, n_frames, "frames")
        if frames[0] < reference_frames[1] and reference_frames[0] < frames[1]:
            log.warning("the processed frames %s overlap the reference frames %s", list(frames),
                        list(reference_frames))
    if strobe_frames is not None:
        strobe_frames = _check_range(strobe_frames, n_frames, "sync.strobe.search_frames")

    # ---- timing ----------------------------------------------------------------------
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

    # ---- geometry --------------------------------------------------------------------
    vmin = np.asarray(volume_min, dtype=np.float64).ravel()
    vmax = np.asarray(volume_max, dtype=np.float64).ravel()
    if vmin.shape != (3,) or vmax.shape != (3,) or not np.all(vmax > vmin):
        raise SchlierenInputError("the volume needs min < max in x, y and z (metres)", field="volume")
    if not voxel_size > 0:
        raise SchlierenInputError("the voxel size must be positive (metres)", field="volume.voxel_size")
    grid = Grid(tuple(vmin), tuple(vmax), float(voxel_size))
    if min(grid.shape) < 1:
        raise SchlierenInputError(f"the voxel size {voxel_size} m is larger than the volume", field="volume")
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
    seeing = [c.name for c in cameras if _sees_point(c, grid.center)]
    if not seeing:
        raise SchlierenInputError("no camera sees the volume centre "
                                  f"{np.round(grid.center, 4).tolist()} (check --volume and the world frame "
                                  "of the calibration)", file=calib.path, field="volume")
    for c in cameras:
        if c.name not in seeing:
            log.warning("camera %s does not see the volume centre", c.name)

    # ---- files (everything created here is removed again if anything fails) --------------
    created: list[Path] = []  # paths this call created, removed on failure
    if not root.exists():
        created.append(root)
    tmp = manifest_path.with_name(MANIFEST_NAME + ".tmp")
    try:
        root.mkdir(parents=True, exist_ok=True)
        external = False
        cam_docs = []
        for (e, bg), cam in zip(entries, cameras):
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
        med = medium or Medium()
        manifest = {
            "format": SESSION_FORMAT,
            "name": name or root.resolve().name,
            "frame_rate": float(frame_rate),
        }
        if frames is not None:
            manifest["frames"] = [int(frames[0]), int(frames[1])]
        manifest["volume"] = {"min": [float(v) for v in vmin], "max": [float(v) for v in vmax],
                              "voxel_size": float(voxel_size)}
        manifest["medium"] = {"n_ambient": med.n_ambient, "T_ambient": med.T_ambient,
                              "p_ambient": med.p_ambient, "gladstone_dale": med.gladstone_dale}
        if strobe_frames is not None:
            manifest["sync"] = {"strobe": {"search_frames": [int(strobe_frames[0]), int(strobe_frames[1])]}}
        if external:
            manifest["allow_external_paths"] = True
        manifest["cameras"] = cam_docs

        header = [f"# Written by `schlieren init` from {os.path.abspath(calib.path)}",
                  f"# {len(order)} cameras, {n_frames} frames each at {frame_rate:.6g} fps; reference = frames "
                  f"[{reference_frames[0]}, {reference_frames[1]}) of each camera's frames",
                  f"# grid {grid.shape[2]} x {grid.shape[1]} x {grid.shape[0]} voxels (x, y, z)"]
        for n in order:
            e = calib.camera(n)
            if "rms" in e:
                header.append(f"# {n}: calibration RMS {float(e['rms']):.3f} px over "
                              f"{e.get('n_views', '?')} views")
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write("\n".join(header) + "\n")
            yaml.safe_dump(manifest, fh, sort_keys=False, default_flow_style=None, width=100)
        from schlieren.storage.session import load_session

        load_session(tmp)  # the reader `schlieren run` uses: fail here, before the manifest is in place
        os.replace(tmp, manifest_path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        for p in reversed(created):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            elif p.exists():
                p.unlink()
        raise
    log.info("wrote %s", manifest_path)
    return manifest_path


def _place_frames(spec: str, root: Path, camera: str, copy: bool, created: list) -> tuple[str, bool]:
    """The manifest's ``frames`` for a camera's source: relative inside ``root``, copied into
    ``root/<camera>/`` when ``copy``, else absolute (external). Returns ``(spec, external)``."""
    rel = _rel_inside(spec, root)
    if rel is not None:
        return rel, False
    if not copy:
        return os.path.abspath(spec), True
    kind = frames_kind(spec)
    if kind in ("video", "tiff"):
        dest = root / camera / Path(spec).name
        files, new_spec = [spec], dest
    else:  # an image sequence: its files into <camera>/frames/, same names
        src = open_frames(spec, camera_name=camera)
        files = [src.file_of(i) for i in range(len(src))]
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


def _sees_point(cam: Camera, X: np.ndarray) -> bool:
    Xc = cam.R @ np.asarray(X, dtype=np.float64) + cam.t
    if Xc[2] <= 0:
        return False
    uv = cam.project(np.asarray(X, dtype=np.float64)[None, :])[0]
    W, H = cam.image_size
    return bool(-0.5 <= uv[0] <= W - 0.5 and -0.5 <= uv[1] <= H - 0.5)
