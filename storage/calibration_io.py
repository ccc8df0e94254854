"""Calibration files and board images: everything of the calibration that touches files.

* :func:`resolve_source` / :func:`iter_board_frames` read one camera's board views from a
  video file, a folder of images or a glob pattern of images (view ``i`` = frame
  ``i * step`` of a video, or the ``i * step``-th image in name order).
* :func:`write_calibration` / :func:`read_calibration` store a calibrated rig as YAML,
  ``format: schlieren-calibration/1``, whose camera entries use the field names of the
  SPEC session manifest (``name, image_size, K, dist, R, t, background``) so that
  ``schlieren init`` copies them as they are; extra fields ``rms`` (pixels),
  ``n_views`` and ``n_points`` report the calibration's quality.

Example::

    format: schlieren-calibration/1
    board: {type: charuco, squares: [10, 7], square_size: 0.03, marker_size: 0.022,
            dictionary: DICT_5X5_100, legacy_pattern: false}
    world: {board_view: 0, orientation: flat, convention: "..."}
    cameras:
    - name: cam00
      image_size: [1440, 1080]
      K: [[3300.0, 0.0, 720.0], [0.0, 3300.0, 540.0], [0.0, 0.0, 1.0]]
      dist: [-0.1, 0.05, 0.0, 0.0, 0.0]
      R: [[...], [...], [...]]
      t: [0.0, 0.0, 2.5]
      rms: 0.12
      n_views: 24
      background: {point: [0.0, -2.5, 0.15], normal: [0.0, 1.0, 0.0]}   # or {distance: 5.0}
"""

from __future__ import annotations

import glob
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import yaml

from schlieren.pipeline.calibration import BoardSpec, RigCalibration
from schlieren.pipeline.geometry import Camera
from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.frames import IMAGE_EXTENSIONS as _FRAME_IMAGE_EXTENSIONS
from schlieren.storage.frames import VIDEO_EXTENSIONS as _FRAME_VIDEO_EXTENSIONS

__all__ = [
    "CALIBRATION_FORMAT",
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "BoardSource",
    "CalibrationFile",
    "resolve_source",
    "iter_board_frames",
    "read_image",
    "write_calibration",
    "read_calibration",
    "validate_camera_entry",
    "import_calibration",
    "write_print_image",
    "read_opencv_camera",
    "read_kalibr_camchain",
]

log = logging.getLogger(__name__)

CALIBRATION_FORMAT = "schlieren-calibration/1"
# the one list of containers and image types every reader uses (storage/frames.py)
IMAGE_EXTENSIONS = tuple(sorted(_FRAME_IMAGE_EXTENSIONS))
VIDEO_EXTENSIONS = tuple(sorted(_FRAME_VIDEO_EXTENSIONS))

WORLD_CONVENTION = (
    "world origin at the centre of the board's chessboard area in view board_view; "
    "flat: x along the board columns, z out of the printed face (up), y = z cross x; "
    "upright: x along the board columns, z towards the printed top edge (up), y into the board")


# ----------------------------------------------------------------------------------
# Board views
# ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class BoardSource:
    """One camera's board views.

    Attributes
    ----------
    name : str
        Camera name (``NAME=`` prefix, else the video's stem or the folder's name).
    kind : {"video", "images"}
    paths : tuple of str
        The video file, or the image files in name order.
    spec : str
        The argument as given (for messages).
    """

    name: str
    kind: str
    paths: tuple
    spec: str = ""

    @property
    def label(self) -> str:
        return self.paths[0] if self.kind == "video" else (self.spec or os.path.dirname(self.paths[0]))


def _split_name(arg: str) -> tuple[str | None, str]:
    if "=" in arg:
        name, path = arg.split("=", 1)
        if name and os.sep not in name and "/" not in name and not os.path.exists(arg):
            return name.strip(), path
    return None, arg


def resolve_source(arg: str, *, base: str | os.PathLike | None = None,
                   single_image: bool = False) -> BoardSource:
    """Interpret one camera's argument: ``[NAME=]VIDEO``, ``[NAME=]FOLDER`` or ``[NAME=]GLOB``.

    Parameters
    ----------
    arg : str
        A video file, a folder of images (sorted by name), or a quoted glob pattern of
        images, optionally prefixed by the camera's name and ``=``.
    base : path, optional
        Folder against which relative paths are resolved (default: current directory).
    single_image : bool
        Accept one image file (named by its stem), e.g. a board on the background.

    Returns
    -------
    BoardSource

    Raises
    ------
    SchlierenInputError
        Nothing matches, or a folder/pattern holds no images.
    """
    name, path = _split_name(arg)
    full = path if (base is None or os.path.isabs(path)) else os.path.join(os.fspath(base), path)
    if any(ch in path for ch in "*?["):
        files = sorted(f for f in glob.glob(full) if f.lower().endswith(IMAGE_EXTENSIONS))
        if not files:
            raise SchlierenInputError("the pattern matches no image files", file=full, camera=name)
        if name is None:
            parent = os.path.basename(os.path.dirname(os.path.abspath(files[0])))
            name = parent or Path(files[0]).stem
        return BoardSource(name, "images", tuple(files), path)
    if os.path.isdir(full):
        files = sorted(os.path.join(full, f) for f in os.listdir(full)
                       if f.lower().endswith(IMAGE_EXTENSIONS))
        if not files:
            raise SchlierenInputError("the folder holds no image files "
                                      f"({', '.join(IMAGE_EXTENSIONS)})", file=full, camera=name)
        return BoardSource(name or os.path.basename(os.path.normpath(full)), "images", tuple(files), full)
    if os.path.isfile(full):
        if full.lower().endswith(IMAGE_EXTENSIONS):
            if single_image:
                return BoardSource(name or Path(full).stem, "images", (full,), full)
            raise SchlierenInputError(
                "one image is not enough to calibrate a camera; give its folder or a quoted "
                "glob pattern (e.g. 'calib/cam00/*.png')", file=full, camera=name)
        return BoardSource(name or Path(full).stem, "video", (full,), full)
    raise SchlierenInputError("no such video, image folder or pattern", file=full, camera=name)


def read_image(path: str | os.PathLike, *, camera: str | None = None) -> np.ndarray:
    """Read one image as stored (8/16-bit, grey or BGR).

    Raises
    ------
    SchlierenInputError
        Missing or unreadable file.
    """
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise SchlierenInputError("file not found", file=p, camera=camera)
    img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SchlierenInputError("cannot read the image (corrupt or unsupported format)",
                                  file=p, camera=camera)
    return img


def iter_board_frames(source: BoardSource, *, step: int = 1,
                      max_views: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(view, image)`` for one camera's board views.

    View ``i`` is frame ``i * step`` of a video or image ``i * step`` (name order) of an
    image list, so the same ``step`` keeps synchronised cameras' views aligned. All
    images must share one size.

    Parameters
    ----------
    source : BoardSource
    step : int
        Use every ``step``-th frame or image.
    max_views : int, optional
        Stop after this many views.

    Raises
    ------
    SchlierenInputError
        Unreadable file or frame, or images of different sizes.
    """
    step = max(1, int(step))
    size = None
    n = 0

    def check(img, where):
        nonlocal size
        s = (img.shape[1], img.shape[0])
        if size is None:
            size = s
        elif s != size:
            raise SchlierenInputError(f"image size {s[0]}x{s[1]} differs from the first "
                                      f"image's {size[0]}x{size[1]}", file=where, camera=source.name)

    if source.kind == "images":
        for view, k in enumerate(range(0, len(source.paths), step)):
            if max_views is not None and n >= max_views:
                return
            img = read_image(source.paths[k], camera=source.name)
            check(img, source.paths[k])
            n += 1
            yield view, img
        return
    path = source.paths[0]
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        raise SchlierenInputError("cannot open the video", file=path, camera=source.name)
    try:
        while max_views is None or n < max_views:
            ok, img = cap.read()
            if not ok:
                break
            check(img, path)
            yield n, img
            n += 1
            for _ in range(step - 1):
                if not cap.grab():
                    return
    finally:
        cap.release()
    if n == 0:
        raise SchlierenInputError("the video holds no readable frame", file=path, camera=source.name)


# ----------------------------------------------------------------------------------
# The calibration file
# ----------------------------------------------------------------------------------
def _floats(a) -> list:
    arr = np.asarray(a, dtype=np.float64)
    return [float(v) for v in arr] if arr.ndim == 1 else [_floats(r) for r in arr]


def _background_entry(bg: dict | None) -> dict | None:
    if bg is None:
        return None
    if "distance" in bg:
        return {"distance": float(bg["distance"])}
    return {"point": _floats(bg["point"]), "normal": _floats(bg["normal"])}


def write_calibration(path: str | os.PathLike, rig: RigCalibration, *, board: BoardSpec,
                      sources: dict | None = None) -> Path:
    """Write a calibrated rig as ``format: schlieren-calibration/1`` YAML.

    Parameters
    ----------
    path : path
        Output file (its folder is created).
    rig : RigCalibration
    board : BoardSpec
    sources : dict of str to str, optional
        Camera name -> the board views it was calibrated from (recorded for provenance).

    Returns
    -------
    Path
    """
    cams = []
    for c in rig.cameras:
        entry = {
            "name": c.name,
            "image_size": [int(c.image_size[0]), int(c.image_size[1])],
            "K": _floats(c.K),
            "dist": _floats(c.dist),
            "R": _floats(c.R),
            "t": _floats(c.t),
            "rms": round(float(c.rms), 5),
            "n_views": int(c.n_views),
            "n_points": int(c.n_points),
        }
        if np.isfinite(c.rms_intrinsic):
            entry["rms_intrinsic"] = round(float(c.rms_intrinsic), 5)
        bg = _background_entry(c.background)
        if bg is not None:
            entry["background"] = bg
        if sources and c.name in sources:
            entry["source"] = str(sources[c.name])
        cams.append(entry)
    doc = {
        "format": CALIBRATION_FORMAT,
        "board": {"type": "charuco", "squares": list(board.squares), "square_size": board.square_size,
                  "marker_size": board.marker_size, "dictionary": board.dictionary,
                  "legacy_pattern": bool(board.legacy_pattern)},
        "world": {"board_view": int(rig.world_board_view), "orientation": rig.world_board_orientation,
                  "convention": WORLD_CONVENTION},
        "rms": round(float(rig.rms), 5),
        "cameras": cams,
    }
    p = Path(path)
    if p.parent and not p.parent.exists():
        p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write("# Written by `schlieren calibrate`; camera entries use the session manifest's fields.\n")
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None, width=100)
    os.replace(tmp, p)
    return p


@dataclass(frozen=True)
class CalibrationFile:
    """A calibration file as read and validated.

    Attributes
    ----------
    path : str
    cameras : list of dict
        SPEC camera entries (``name, image_size, K, dist, R, t`` and, if known,
        ``background``), plus ``rms, n_views`` when present; plain Python lists.
    board : dict
    world : dict
    """

    path: str
    cameras: list = field(default_factory=list)
    board: dict = field(default_factory=dict)
    world: dict = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return [c["name"] for c in self.cameras]

    def camera(self, name: str) -> dict:
        for c in self.cameras:
            if c["name"] == name:
                return c
        raise SchlierenInputError(f"no camera {name!r} in the calibration (it has "
                                  f"{', '.join(self.names)})", file=self.path, camera=name)

    def camera_object(self, name: str) -> Camera:
        """The camera as a :class:`~schlieren.pipeline.geometry.Camera` (needs a background)."""
        c = self.camera(name)
        bg = c.get("background")
        if bg is None:
            raise SchlierenInputError("no background plane in the calibration", file=self.path,
                                      camera=name, field="background")
        if "distance" in bg:
            point, normal = Camera.background_from_distance(c["R"], c["t"], bg["distance"])
        else:
            point, normal = bg["point"], bg["normal"]
        return Camera(name, c["K"], c["dist"], c["R"], c["t"], tuple(c["image_size"]), point, normal)


def _matrix(value, shape, *, file, camera, fld) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SchlierenInputError(f"expected numbers of shape {shape}", file=file, camera=camera,
                                  field=fld) from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise SchlierenInputError(f"expected finite numbers of shape {shape}, got shape "
                                  f"{arr.shape}", file=file, camera=camera, field=fld)
    return arr


def validate_camera_entry(entry, *, file: str, index: int, prefix: str = "cameras") -> dict:
    """Check one camera entry (SPEC field names) and return it with plain lists.

    Accepts ``rvec`` instead of ``R``; checks shapes, ``R`` orthonormal with det +1,
    ``K`` with positive focal lengths, ``dist`` of 4, 5, 8, 12 or 14 values, and a
    background plane in front of the camera.

    Raises
    ------
    SchlierenInputError
        Naming the file, the camera and the field.
    """
    where = f"{prefix}[{index}]"
    if not isinstance(entry, dict):
        raise SchlierenInputError("a camera entry must be a mapping", file=file, field=where)
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise SchlierenInputError("missing camera name", file=file, field=f"{where}.name")
    for key in ("image_size", "K", "dist", "t"):
        if key not in entry:
            raise SchlierenInputError("missing field", file=file, camera=name, field=f"{where}.{key}")
    size = entry["image_size"]
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(isinstance(s, int) and s > 0 for s in size)):
        raise SchlierenInputError("expected [width, height], positive integers", file=file,
                                  camera=name, field=f"{where}.image_size")
    K = _matrix(entry["K"], (3, 3), file=file, camera=name, fld=f"{where}.K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise SchlierenInputError("K must have positive focal lengths and last row [0, 0, 1]",
                                  file=file, camera=name, field=f"{where}.K")
    dist = np.asarray(entry["dist"], dtype=np.float64).ravel()
    if len(dist) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise SchlierenInputError(f"expected 4, 5, 8, 12 or 14 distortion coefficients, got "
                                  f"{len(dist)}", file=file, camera=name, field=f"{where}.dist")
    if "R" in entry:
        R = _matrix(entry["R"], (3, 3), file=file, camera=name, fld=f"{where}.R")
    elif "rvec" in entry:
        rv = _matrix(entry["rvec"], (3,), file=file, camera=name, fld=f"{where}.rvec")
        R, _ = cv2.Rodrigues(rv.reshape(3, 1))
    else:
        raise SchlierenInputError("missing field (or rvec)", file=file, camera=name, field=f"{where}.R")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise SchlierenInputError("R is not a rotation (orthonormal with determinant +1)",
                                  file=file, camera=name, field=f"{where}.R")
    t = _matrix(entry["t"], (3,), file=file, camera=name, fld=f"{where}.t")
    out = dict(entry)
    out.pop("rvec", None)
    out.update(name=name, image_size=[int(size[0]), int(size[1])], K=_floats(K),
               dist=_floats(dist), R=_floats(R), t=_floats(t))
    bg = entry.get("background")
    if bg is not None:
        centre = -R.T @ t
        if not isinstance(bg, dict):
            raise SchlierenInputError("expected {point, normal} or {distance}", file=file,
                                      camera=name, field=f"{where}.background")
        if "distance" in bg:
            d = bg["distance"]
            if not isinstance(d, (int, float)) or not d > 0:
                raise SchlierenInputError("the background distance must be a positive number "
                                          "of metres", file=file, camera=name,
                                          field=f"{where}.background.distance")
            out["background"] = {"distance": float(d)}
        else:
            p = _matrix(bg.get("point"), (3,), file=file, camera=name, fld=f"{where}.background.point")
            n = _matrix(bg.get("normal"), (3,), file=file, camera=name, fld=f"{where}.background.normal")
            if np.linalg.norm(n) == 0:
                raise SchlierenInputError("zero normal", file=file, camera=name,
                                          field=f"{where}.background.normal")
            n = n / np.linalg.norm(n)
            denom = float(R[2] @ n)
            s = float((p - centre) @ n) / denom if abs(denom) > 1e-9 else -1.0
            if s <= 0:
                raise SchlierenInputError("the background plane is behind the camera (or parallel to "
                                          "its optical axis)", file=file, camera=name,
                                          field=f"{where}.background")
            out["background"] = {"point": _floats(p), "normal": _floats(n)}
    return out


def read_calibration(path: str | os.PathLike) -> CalibrationFile:
    """Read and validate a ``schlieren-calibration/1`` file.

    Raises
    ------
    SchlierenInputError
        Missing/unparsable file, unknown format, or a bad camera entry (named).
    """
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise SchlierenInputError("calibration file not found", file=p)
    try:
        with open(p, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        where = f" at line {line + 1}" if line is not None else ""
        raise SchlierenInputError(f"not valid YAML{where}", file=p) from None
    if not isinstance(doc, dict):
        raise SchlierenInputError("expected a mapping at the top level", file=p)
    fmt = doc.get("format")
    if fmt != CALIBRATION_FORMAT:
        raise SchlierenInputError(f"unknown format {fmt!r} (expected {CALIBRATION_FORMAT})",
                                  file=p, field="format")
    cams = doc.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise SchlierenInputError("expected a non-empty list of cameras", file=p, field="cameras")
    entries = [validate_camera_entry(c, file=p, index=i) for i, c in enumerate(cams)]
    names = [c["name"] for c in entries]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SchlierenInputError("duplicate camera name", file=p, camera=dup[0], field="cameras")
    return CalibrationFile(p, entries, dict(doc.get("board") or {}), dict(doc.get("world") or {}))


# ----------------------------------------------------------------------------------
# Importing calibrations made by other tools
# ----------------------------------------------------------------------------------
#: Names under which OpenCV FileStorage files (the OpenCV samples, ROS camera_info
#: conversions, hand-written ``cv::FileStorage`` output) hold each quantity (any case).
_OPENCV_KEYS = {
    "K": ("camera_matrix", "cameramatrix", "k", "m", "intrinsic_matrix", "intrinsics", "mtx"),
    "dist": ("distortion_coefficients", "dist_coeffs", "distcoeffs", "dist", "d", "distortion"),
    "R": ("r", "rotation", "rotation_matrix", "rmat"),
    "rvec": ("rvec", "rotation_vector", "rvecs"),
    "t": ("t", "tvec", "translation", "translation_vector", "tvecs"),
    "width": ("image_width", "width", "imagewidth"),
    "height": ("image_height", "height", "imageheight"),
    "size": ("image_size", "imagesize", "resolution", "size"),
}


def _node_value(node):
    """A FileStorage node as a numpy array, number or None."""
    if node is None or node.empty():
        return None
    if node.isMap() and node.mat() is not None:
        return np.asarray(node.mat(), dtype=np.float64)
    if node.isSeq():
        return np.asarray([node.at(i).real() for i in range(node.size())], dtype=np.float64)
    if node.isReal() or node.isInt():
        return float(node.real())
    m = node.mat()
    return None if m is None else np.asarray(m, dtype=np.float64)


def read_opencv_camera(path: str | os.PathLike, name: str) -> dict:
    """One camera from an OpenCV FileStorage file (YAML ``%YAML:1.0`` or XML).

    Reads the intrinsic matrix (``camera_matrix``/``K``), the distortion coefficients
    (``distortion_coefficients``/``D``), the image size (``image_width`` and
    ``image_height``, or ``image_size``) and the camera's pose in the rig's world frame
    (``R`` or ``rvec``, and ``T``/``t``/``tvec``: ``x_cam = R x_world + t``, metres).

    Raises
    ------
    SchlierenInputError
        Naming the file, the camera and the missing or malformed quantity.
    """
    p = os.fspath(path)
    fs = cv2.FileStorage(p, cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise SchlierenInputError("cannot read the OpenCV FileStorage file", file=p, camera=name)
    try:
        keys = {k.lower(): k for k in fs.root().keys()}

        def get(what):
            for alias in _OPENCV_KEYS[what]:
                if alias in keys:
                    return _node_value(fs.getNode(keys[alias])), keys[alias]
            return None, None

        K, k_name = get("K")
        if K is None:
            raise SchlierenInputError("no camera matrix (camera_matrix or K)", file=p, camera=name, field="K")
        dist, d_name = get("dist")
        dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).ravel()
        size, _ = get("size")
        w, _ = get("width")
        h, _ = get("height")
        if size is not None and np.asarray(size).size == 2:
            w, h = (float(v) for v in np.asarray(size).ravel())
        if w is None or h is None:
            raise SchlierenInputError("no image size (image_width and image_height, or image_size)", file=p,
                                      camera=name, field="image_size")
        entry = {"name": name, "image_size": [int(round(float(w))), int(round(float(h)))],
                 "K": np.asarray(K, dtype=np.float64).reshape(3, 3).tolist(), "dist": dist.tolist()}
        R, _ = get("R")
        rvec, _ = get("rvec")
        t, t_name = get("t")
        if (R is None and rvec is None) or t is None:
            raise SchlierenInputError("no camera pose: give R (or rvec) and T (or tvec), the world -> camera "
                                      "transform x_cam = R x_world + t in metres", file=p, camera=name, field="R")
        if R is not None and np.asarray(R).size == 9:
            entry["R"] = np.asarray(R, dtype=np.float64).reshape(3, 3).tolist()
        else:
            entry["rvec"] = np.asarray(R if rvec is None else rvec, dtype=np.float64).ravel()[:3].tolist()
        entry["t"] = np.asarray(t, dtype=np.float64).ravel()[:3].tolist()
        bg, _ = (fs.getNode("background_distance").real(), None) if "background_distance" in keys else (None, None)
        if bg is not None:
            entry["background"] = {"distance": float(bg)}
        return entry
    finally:
        fs.release()


def read_kalibr_camchain(path: str | os.PathLike, doc: dict) -> list[dict]:
    """Cameras of a Kalibr ``camchain.yaml`` (``cam0``, ``cam1``, ...).

    Pinhole cameras with ``radtan`` distortion (``k1 k2 r1 r2`` = OpenCV ``k1 k2 p1 p2``)
    or ``none``. ``T_cn_cnm1`` chains each camera to the previous one; the world frame is
    ``cam0``'s camera frame (x right, y down, z along its optical axis), so give the
    volume in those coordinates (docs/calibration.md).
    """
    p = os.fspath(path)
    names = sorted((k for k in doc if re.fullmatch(r"cam\d+", str(k))), key=lambda k: int(k[3:]))
    out = []
    pose = np.eye(4)
    for i, n in enumerate(names):
        c = doc[n]
        if not isinstance(c, dict):
            raise SchlierenInputError("expected a mapping", file=p, camera=n, field=n)
        model = c.get("camera_model", "pinhole")
        if model != "pinhole":
            raise SchlierenInputError(f"camera_model {model!r} is not supported (pinhole only)", file=p,
                                      camera=n, field=f"{n}.camera_model")
        dm = c.get("distortion_model", "radtan")
        if dm not in ("radtan", "none"):
            raise SchlierenInputError(f"distortion_model {dm!r} is not supported (radtan or none; equidistant "
                                      "fisheye lenses need another model)", file=p, camera=n,
                                      field=f"{n}.distortion_model")
        try:
            fu, fv, pu, pv = (float(v) for v in c["intrinsics"])
            w, h = (int(v) for v in c["resolution"])
            d = [float(v) for v in c.get("distortion_coeffs", [0, 0, 0, 0])] if dm == "radtan" else [0.0] * 4
        except (KeyError, TypeError, ValueError) as exc:
            raise SchlierenInputError(f"needs intrinsics [fu, fv, pu, pv] and resolution [w, h] ({exc})",
                                      file=p, camera=n, field=n) from None
        if i > 0:
            if "T_cn_cnm1" not in c:
                raise SchlierenInputError("no T_cn_cnm1 (the transform from the previous camera)", file=p,
                                          camera=n, field=f"{n}.T_cn_cnm1")
            T = np.asarray(c["T_cn_cnm1"], dtype=np.float64)
            if T.shape != (4, 4):
                raise SchlierenInputError("T_cn_cnm1 must be a 4x4 matrix", file=p, camera=n,
                                          field=f"{n}.T_cn_cnm1")
            pose = T @ pose
        out.append({"name": n, "image_size": [w, h], "K": [[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]],
                    "dist": (d + [0.0] * 4)[:4], "R": pose[:3, :3].tolist(), "t": pose[:3, 3].tolist()})
    if not out:
        raise SchlierenInputError("no cam0, cam1, ... entries (not a Kalibr camchain)", file=p)
    return out


def _opencv_storage(path: str) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(256).lstrip()
    return head.startswith(b"%YAML") or b"<opencv_storage>" in head or path.lower().endswith(".xml")


def import_calibration(args: list[str] | str) -> CalibrationFile:
    """A rig's calibration from one or more files: ``[NAME=]PATH`` (quoted globs allowed).

    Recognised by content:

    * ``format: schlieren-calibration/1`` (YAML or the same as JSON: docs/calibration.md);
    * OpenCV FileStorage YAML (``%YAML:1.0``) or XML, one camera per file, named after
      ``NAME=`` or the file stem (:func:`read_opencv_camera`);
    * a Kalibr ``camchain.yaml`` (:func:`read_kalibr_camchain`).

    Raises
    ------
    SchlierenInputError
        Naming the file, the camera and the field.
    """
    if isinstance(args, (str, os.PathLike)):
        args = [os.fspath(args)]
    entries: list[dict] = []
    source = None
    for arg in args:
        name, spec = _split_name(arg)
        files = sorted(glob.glob(spec)) if any(ch in spec for ch in "*?[") else [spec]
        if not files:
            raise SchlierenInputError("no calibration file matches", file=spec, camera=name)
        for f in files:
            if not os.path.isfile(f):
                raise SchlierenInputError("calibration file not found", file=f, camera=name)
            source = source or f
            if _opencv_storage(f):
                raw = read_opencv_camera(f, name or Path(f).stem)
                entries.append(validate_camera_entry(raw, file=f, index=len(entries)))
                continue
            try:
                with open(f, encoding="utf-8") as fh:
                    doc = yaml.safe_load(fh)
            except yaml.YAMLError:
                raise SchlierenInputError("not valid YAML or JSON", file=f) from None
            if isinstance(doc, dict) and doc.get("format") == CALIBRATION_FORMAT:
                entries.extend(read_calibration(f).cameras)
            elif isinstance(doc, dict) and "cam0" in doc:
                for i, raw in enumerate(read_kalibr_camchain(f, doc)):
                    entries.append(validate_camera_entry(raw, file=f, index=i, prefix="cams"))
            else:
                raise SchlierenInputError(f"not a calibration this version reads ({CALIBRATION_FORMAT} YAML/JSON, "
                                          "OpenCV FileStorage YAML/XML, Kalibr camchain.yaml)", file=f)
    names = [e["name"] for e in entries]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SchlierenInputError("two calibrations for the same camera; name them NAME=PATH", camera=dup[0])
    return CalibrationFile(", ".join(args) if len(args) > 1 else (source or ""), entries)


def write_print_image(path: str | os.PathLike, image: np.ndarray, dpi: float) -> Path:
    """Write a grey image for printing: 8-bit PNG whose header states ``dpi`` (so printing
    "at 100 %" gives the physical size the pixels were computed for)."""
    from PIL import Image

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    img = np.clip(np.rint(np.asarray(image, dtype=np.float64)), 0, 255).astype(np.uint8)
    Image.fromarray(img).save(p, dpi=(float(dpi), float(dpi)))
    return p
