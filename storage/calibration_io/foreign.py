"""Calibrations made by other tools, read into the ``schlieren-calibration/1`` form:
OpenCV FileStorage files (YAML or XML, one camera each) and Kalibr ``camchain.yaml``."""

from __future__ import annotations

import glob
import os
import re
from pathlib import Path

import cv2
import numpy as np
import yaml

from schlieren.storage.calibration_io.board_views import _split_name
from schlieren.storage.calibration_io.calibration_file import (
    CALIBRATION_FORMAT,
    CalibrationFile,
    read_calibration,
    validate_camera_entry,
)
from schlieren.storage.errors import SchlierenInputError

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
