"""The calibration file, ``format: schlieren-calibration/1`` (YAML): written, read and checked.

Its camera entries use the field names of the SPEC session manifest (``name, image_size,
K, dist, R, t, background``) so that ``schlieren init`` copies them as they are; extra
fields ``rms`` (pixels), ``n_views`` and ``n_points`` report the calibration's quality.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from schlieren.pipeline.calibration import BoardSpec, RigCalibration
from schlieren.pipeline.geometry import Camera
from schlieren.storage.errors import SchlierenInputError

CALIBRATION_FORMAT = "schlieren-calibration/1"

WORLD_CONVENTION = (
    "world origin at the centre of the board's chessboard area in view board_view; "
    "flat: x along the board columns, z out of the printed face (up), y = z cross x; "
    "upright: x along the board columns, z towards the printed top edge (up), y into the board")


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
