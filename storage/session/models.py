"""The typed manifest models (pydantic), and their validation errors as one line.

The models forbid unknown fields and non-finite numbers; a validation error becomes a
:class:`~schlieren.storage.errors.SessionError` naming the file, the camera and the dotted
field (``cameras[2].R``), with a "did you mean" suggestion for a misspelled field.
"""

from __future__ import annotations

import difflib
import numbers
import re
import typing
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schlieren.storage.errors import SessionError

DIST_LENGTHS = (4, 5, 8, 12, 14)
ORTHONORMAL_TOL = 1e-6

#: A camera name: 1 to 64 ASCII letters, digits, ``_``, ``.`` or ``-``, starting with a
#: letter or digit. Names label the store's ``camera`` coordinate, messages and file names.
CAMERA_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}\Z")
CAMERA_NAME_RULE = ("1 to 64 letters, digits, '_', '.' or '-', starting with a letter or digit "
                    "(it names files and the store's camera coordinate)")


def camera_name_problem(name: object) -> str | None:
    """Why ``name`` is not a valid camera name (:data:`CAMERA_NAME`), or None."""
    if not isinstance(name, str):
        return f"a camera name must be text, got {type(name).__name__}"
    if CAMERA_NAME.match(name):
        return None
    return f"camera name {short_name(name)} is not allowed: use {CAMERA_NAME_RULE}"


def short_name(name: str, limit: int = 24) -> str:
    """``name`` quoted for a message, cut to ``limit`` characters (with its length if cut)."""
    shown = repr(name[:limit])
    return shown if len(name) <= limit else f"{shown[:-1]}...{shown[-1]} ({len(name)} characters)"


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

    @field_validator("name", mode="before")
    @classmethod
    def _name(cls, v):
        if isinstance(v, int) and not isinstance(v, bool):  # `name: 7` in YAML
            v = str(v)
        why = camera_name_problem(v)
        if why is not None:
            raise ValueError(why)
        return v

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
            return str(name) if camera_name_problem(name) is None else f"#{loc[1]}"
    return None


def validation_error(exc: ValidationError, raw: dict, file: str) -> SessionError:
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
