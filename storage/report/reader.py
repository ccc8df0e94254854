"""What the report (and the exports) read from a result store.

:class:`ReportReader` hands :mod:`schlieren.workers.report.build` plain data: arrays,
attributes, completion markers, the :class:`~schlieren.pipeline.geometry.Grid`, the
cameras and the medium. It tolerates a partial run: a missing array, a frame whose
completion marker ``status/<stage>`` is unset, or a chunk left at its NaN fill value
reads as ``None``. :func:`open_result`, :func:`volume_grid`, :func:`frame_range` and
:func:`first_frame` serve the exports too.
"""


from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from schlieren.pipeline.geometry import Camera, Grid, Medium, rodrigues
from schlieren.storage import location
from schlieren.storage.errors import SchlierenInputError, StoreError
from schlieren.storage.layout import STORE_FORMAT
from schlieren.storage.store.attrs import decode_attrs

log = logging.getLogger(__name__)

EXPECTED_ARRAYS = ("time", "flow", "mask", "potential", "hull", "gradient", "refractivity", "density",
                   "temperature")
VOLUME_ARRAYS = ("hull", "gradient", "refractivity", "density", "temperature")
#: Arrays read when present and never listed as missing: the optional stages' (``uncertainty``),
#: and those stores of older versions lack (the capture corrections of issue 33 and the flow's
#: per-camera pre-smoothing, the raw frames' coordinate).
OPTIONAL_ARRAYS = ("refractivity_sigma", "density_sigma", "temperature_sigma", "background_motion",
                   "photometric", "capture_fit", "defective_pixels", "presmooth", "row_knot", "raw_frame")


# ---------------------------------------------------------------------------------------
# Reading the store
# ---------------------------------------------------------------------------------------


def open_result(store_path: str | os.PathLike):
    """Open a result store read-only, every chunk read checked (storage/integrity.py).

    Raises
    ------
    StoreError
        The path does not exist, is not a Zarr group, or has another ``format``.
    """
    import zarr

    from schlieren.storage.integrity import checked

    path = location.normalize(store_path)
    if not location.exists(path):
        raise StoreError("result store not found", file=path)
    try:  # reads are checked: a corrupt chunk, or one lost under a set marker, raises ChunkError
        group = zarr.open_group(checked(path, read_only=True), mode="r")
    except Exception as exc:  # zarr raises several types for "not a group"
        raise StoreError(f"not a Zarr group ({type(exc).__name__}: {exc})", file=path) from None
    fmt = group.attrs.get("format")
    if fmt is not None and fmt != STORE_FORMAT:
        raise StoreError(f"unknown store format {fmt!r} (expected {STORE_FORMAT})", file=path,
                         field="format")
    return group


def volume_grid(array) -> Grid:
    """The :class:`Grid` of a volume array from its ``origin`` / ``voxel_size`` attributes.

    Parameters
    ----------
    array : zarr.Array
        Dims ``(frame, z, y, x[, component])``.

    Raises
    ------
    StoreError
        Missing or inconsistent attributes, or anisotropic voxels (``Grid`` is isotropic).
    """
    attrs = dict(array.attrs)
    name = array.basename if hasattr(array, "basename") else str(array)
    try:
        origin = np.asarray(attrs["origin"], dtype=np.float64).reshape(3)
        vs = np.asarray(attrs["voxel_size"], dtype=np.float64).ravel()
    except (KeyError, ValueError, TypeError):
        raise StoreError("volume array lacks origin (x, y, z) / voxel_size attributes",
                         field=f"{name}.attrs") from None
    if vs.size == 1:
        vs = np.repeat(vs, 3)
    if vs.size != 3 or np.any(vs <= 0):
        raise StoreError(f"voxel_size must be 3 positive numbers, got {vs.tolist()}", field=f"{name}.attrs")
    if not np.allclose(vs, vs[0], rtol=1e-9):
        raise StoreError(f"anisotropic voxels {vs.tolist()} are not supported", field=f"{name}.attrs")
    nz, ny, nx = (int(v) for v in array.shape[1:4])
    h = float(vs[0])
    vmin = origin - 0.5 * h
    vmax = vmin + h * np.array([nx, ny, nz], dtype=np.float64)
    grid = Grid(tuple(vmin), tuple(vmax), h)
    if grid.shape != (nz, ny, nx):  # round-off in (vmax - vmin) / h
        raise StoreError(f"grid from attributes has shape {grid.shape}, array has {(nz, ny, nx)}",
                         field=f"{name}.attrs")
    return grid


def frame_range(frames, n_frames: int, first: int = 0) -> range:
    """Store indices of a validated half-open range of capture frames ``[a, b)``.

    Parameters
    ----------
    frames : None, (a, b) or range
        Capture frame indices (the store's ``frame`` coordinate, the numbers every command
        shows); ``None`` = every frame; ``b`` may be None (to the end) and is clipped.
    n_frames : int
        Frames in the store.
    first : int
        Capture index of store frame 0 (``frame[0]``).

    Returns
    -------
    range
        Store indices ``a - first .. b - first``.
    """
    if frames is None:
        return range(n_frames)
    if isinstance(frames, range):
        a, b = frames.start, frames.stop
    else:
        a, b = frames
    a = first if a is None else int(a)
    want = f"{a}:{'' if b is None else int(b)}"
    b = first + n_frames if b is None else min(int(b), first + n_frames)
    if a < first or a >= b:
        raise StoreError(f"frame range {want} is empty or outside the store's frames "
                         f"{first}:{first + n_frames}", field="frames")
    return range(a - first, b - first)


def first_frame(group) -> int:
    """Capture index of a store's frame 0 (its ``frame`` coordinate; 0 without one)."""
    try:
        return int(np.asarray(group["frame"][0]))
    except (KeyError, IndexError, ValueError, TypeError):
        return 0


def _get(d: dict, key: str, default=None):
    return d.get(key, default) if isinstance(d, dict) else default


def medium_from_session(session: dict | None) -> Medium:
    """The session's ``medium`` block (SPEC defaults for what is missing)."""
    m = _get(session, "medium") or {}
    base = Medium()
    kw = {}
    for k in ("n_ambient", "T_ambient", "p_ambient", "gladstone_dale"):
        if k in m and m[k] is not None:
            kw[k] = float(m[k])
    return Medium(**{**base.__dict__, **kw})


def cameras_from_session(session: dict, time_offsets=None) -> list[Camera]:
    """Cameras of a stored session manifest (SPEC section 1 fields).

    Parameters
    ----------
    session : dict
        The manifest as stored in the root attribute ``session``.
    time_offsets : sequence of float, optional
        Per-camera session-clock offsets (the store's ``time_offset``).

    Raises
    ------
    StoreError
        A camera entry lacks a field the geometry needs (named as ``cameras[i].field``).
    """
    cams = _get(session, "cameras")
    if not isinstance(cams, list) or not cams:
        raise StoreError("the stored session has no cameras", field="session.cameras")
    out = []
    for i, c in enumerate(cams):
        name = str(c.get("name", f"cam{i:02d}"))
        where = f"session.cameras[{i}]"
        try:
            K = np.asarray(c["K"], dtype=np.float64)
            dist = np.asarray(c.get("dist") or [0.0] * 5, dtype=np.float64)
            if c.get("R") is not None:
                R = np.asarray(c["R"], dtype=np.float64)
            elif c.get("rvec") is not None:
                R = rodrigues(c["rvec"])
            else:
                raise KeyError("R")
            t = np.asarray(c["t"], dtype=np.float64)
            size = tuple(int(v) for v in c["image_size"])
            bg = c.get("background") or {}
            if bg.get("point") is not None and bg.get("normal") is not None:
                point, normal = bg["point"], bg["normal"]
            elif bg.get("distance") is not None:
                point, normal = Camera.background_from_distance(R, t, float(bg["distance"]))
            else:
                raise KeyError("background")
            rs = c.get("rolling_shutter") or {}
            line_time = float(rs.get("line_time", 0.0) or 0.0)
        except KeyError as exc:
            raise StoreError("camera entry lacks a field", camera=name, field=f"{where}.{exc.args[0]}") from None
        except (TypeError, ValueError) as exc:
            raise StoreError(f"malformed camera entry ({exc})", camera=name, field=where) from None
        offset = c.get("time_offset")
        if time_offsets is not None and i < len(time_offsets) and np.isfinite(time_offsets[i]):
            offset = float(time_offsets[i])
        out.append(Camera(name, K, dist, R, t, size, point, normal, line_time,
                          None if offset is None else float(offset)))
    return out


def _session_root(attrs: dict) -> str | None:
    p = attrs.get("session_path")
    if not p:
        return None
    if location.is_url(p):
        return location.parent(p) if p.lower().endswith((".yaml", ".yml", ".json")) else p
    p = Path(p)
    return str(p.parent if p.suffix.lower() in (".yaml", ".yml", ".json") or p.is_file() else p)


def _first_session_frame(attrs: dict) -> int:
    for src in (attrs, _get(attrs, "params") or {}, _get(attrs, "session") or {}):
        fr = _get(src, "frames")
        if isinstance(fr, (list, tuple)) and fr and fr[0] is not None:
            try:
                return int(fr[0])
            except (TypeError, ValueError):
                continue
    return 0


class ReportReader:
    """What the report reads from a result store, as plain data (numpy arrays, dicts, geometry types).

    Tolerant of missing arrays and unfinished chunks: completion comes from the
    ``status/<stage>`` markers when the store has them; a frame that is marked incomplete,
    or whose values are all NaN (the arrays' fill value), reads as ``None``. Volumes are
    read one frame at a time, so callers can stream over frames.

    Parameters
    ----------
    store_path : path
        The Zarr result store, opened read-only.

    Raises
    ------
    StoreError
        See :func:`open_result`.
    """

    STAGE_OF = {"flow": "resample", "mask": "mask", "potential": "potential", "hull": "hull",
                "gradient": "tomography", "refractivity": "integrate", "density": "integrate",
                "temperature": "integrate", "refractivity_sigma": "uncertainty", "density_sigma": "uncertainty",
                "temperature_sigma": "uncertainty"}

    def __init__(self, store_path: str | os.PathLike):
        self.path = location.normalize(store_path)
        self._group = open_result(store_path)
        #: root attributes of the store (``session``, ``params``, ``stage_times``, ``run``, ...)
        self.attrs: dict = decode_attrs(self._group.attrs)
        self._arrays = {k: self._group[k] for k in EXPECTED_ARRAYS + OPTIONAL_ARRAYS if k in self._group}
        self._done: dict[str, np.ndarray | None] = {}

    # --- what exists -------------------------------------------------------------------
    def has(self, name: str) -> bool:
        """Is the expected array ``name`` (one of ``EXPECTED_ARRAYS``) in the store?"""
        return name in self._arrays

    def shape(self, name: str) -> tuple[int, ...]:
        """Shape of a present expected array."""
        return tuple(int(s) for s in self._arrays[name].shape)

    def array_attrs(self, name: str) -> dict:
        """Attributes of a present expected array (empty if absent)."""
        return dict(self._arrays[name].attrs) if name in self._arrays else {}

    @property
    def missing_arrays(self) -> list[str]:
        """Expected arrays the store lacks, in ``EXPECTED_ARRAYS`` order."""
        return [k for k in EXPECTED_ARRAYS if k not in self._arrays]

    @property
    def session(self) -> dict:
        """The stored session manifest (empty dict if none)."""
        return _get(self.attrs, "session") or {}

    @property
    def params(self) -> dict:
        """The stored run parameters (empty dict if none)."""
        return _get(self.attrs, "params") or {}

    @property
    def name(self) -> str:
        """Session name, else the store's file name."""
        return str(self.attrs.get("session_name") or _get(self.session, "name") or location.basename(self.path))

    @property
    def n_frames(self) -> int:
        """Store frames (from ``time``, else any volume or per-camera array; 0 if none)."""
        if "time" in self._arrays:
            return int(self._arrays["time"].shape[0])
        for k in VOLUME_ARRAYS:
            if k in self._arrays:
                return int(self._arrays[k].shape[0])
        for k in ("flow", "mask", "potential"):
            if k in self._arrays:
                return int(self._arrays[k].shape[1])
        return 0

    # --- plain data --------------------------------------------------------------------
    def times(self) -> np.ndarray | None:
        """Per store frame: time on the session clock (s), float64; None if absent or all NaN."""
        if "time" not in self._arrays:
            return None
        t = np.asarray(self._arrays["time"][:], dtype=np.float64)
        return t if np.isfinite(t).any() else None

    def grid(self) -> Grid | None:
        """The volume :class:`Grid` of the first present volume array, or None."""
        for k in VOLUME_ARRAYS:
            if k in self._arrays:
                return volume_grid(self._arrays[k])
        return None

    def medium(self) -> Medium:
        """The session's ambient medium (SPEC defaults for what is missing)."""
        return medium_from_session(self.session)

    def cameras(self) -> tuple[list[Camera] | None, str]:
        """The calibrated cameras with the store's ``time_offset``, or (None, why not)."""
        if not self.session:
            return None, ""
        try:
            offs = np.asarray(self._group["time_offset"][:]) if "time_offset" in self._group else None
            return cameras_from_session(self.session, offs), ""
        except StoreError as exc:
            return None, str(exc)

    def mask_threshold(self) -> float | None:
        """The stored deflection-magnitude threshold of the masks (px), or None."""
        if "mask_threshold" not in self._group:
            return None
        thr = np.asarray(self._group["mask_threshold"][...], dtype=np.float64).ravel()
        return float(thr[0]) if thr.size and np.isfinite(thr[0]) else None

    def completion(self) -> list[tuple[str, int, int]]:
        """``(stage, done, total)`` of every completion marker ``status/<stage>``, by stage name."""
        try:
            status = self._group["status"]
        except KeyError:
            return []
        rows = []
        for stage, arr in sorted(status.arrays(), key=lambda kv: kv[0]):
            done = np.asarray(arr[...]) == 1
            rows.append((stage, int(done.sum()), int(done.size)))
        return rows

    def marker(self, stage: str) -> np.ndarray | None:
        """The completion marker of ``stage`` as bool, or None if the store has none."""
        if stage not in self._done:
            try:
                self._done[stage] = np.asarray(self._group[f"status/{stage}"][...]) == 1
            except KeyError:
                self._done[stage] = None
        return self._done[stage]

    def frame_done(self, name: str, n_frames: int) -> np.ndarray:
        """Per store frame: is ``name`` complete (for every camera)? Unknown -> True."""
        if name not in self._arrays:
            return np.zeros(n_frames, bool)
        m = self.marker(self.STAGE_OF.get(name, ""))
        if m is None:
            return np.ones(n_frames, bool)
        if m.ndim == 2:  # (camera, frame)
            m = m.all(axis=0)
        return m.reshape(-1)[:n_frames] if m.size >= n_frames else np.ones(n_frames, bool)

    def volume(self, name: str, f: int) -> np.ndarray | None:
        """Frame ``f`` of a volume array (float64 if floating), or None if missing, unfinished or all NaN."""
        if name not in self._arrays:
            return None
        m = self.marker(self.STAGE_OF.get(name, ""))
        if m is not None and m.ndim == 1 and f < m.size and not m[f]:
            return None
        v = np.asarray(self._arrays[name][f])
        if v.dtype.kind == "f":
            if not np.isfinite(v).any():
                return None
            v = v.astype(np.float64)
        return v

    def whole(self, name: str) -> np.ndarray | None:
        """All of a present (small) array, e.g. ``background_motion`` (camera, raw_frame, 8);
        None if absent."""
        return np.asarray(self._arrays[name][...]) if name in self._arrays else None

    def camera_frame(self, name: str, c: int, f: int) -> np.ndarray | None:
        """``name[c, f]`` of a per-camera array (float64 if floating), or None if missing or unfinished."""
        if name not in self._arrays:
            return None
        m = self.marker(self.STAGE_OF.get(name, ""))
        if m is not None and m.ndim == 2 and c < m.shape[0] and f < m.shape[1] and not m[c, f]:
            return None
        v = np.asarray(self._arrays[name][c, f])
        if v.dtype.kind == "f":
            if not np.isfinite(v).any():
                return None
            v = v.astype(np.float64)
        return v

    def capture_index(self, f: int) -> int:
        """Capture frame index of store frame ``f`` (the ``frame`` coordinate)."""
        if "frame" in self._group:
            try:
                return int(np.asarray(self._group["frame"][f]))
            except (IndexError, ValueError, TypeError):
                pass
        run = _get(self.attrs, "run") or {}
        fr = _get(run, "frames")
        if isinstance(fr, (list, tuple)) and fr:
            return int(fr[0]) + f
        return _first_session_frame(self.attrs) + f

    def camera_names(self, n: int) -> list[str]:
        """Names of the ``n`` cameras from the stored session (``camXX`` if it does not list ``n``)."""
        cams = _get(self.session, "cameras") or []
        names = [str(c.get("name", f"cam{i:02d}")) for i, c in enumerate(cams)]
        return names if len(names) == n else [f"cam{i:02d}" for i in range(n)]

    def camera_image(self, cam_index: int, capture_index: int) -> tuple[np.ndarray | None, str]:
        """Input frame ``capture_index`` of a camera (from the session folder), or None and why not.

        Returns
        -------
        image : ndarray, shape (H, W), float32, or None
        source : str
            Where it came from (file pattern and frame), or why it could not be read.
        """
        from schlieren.storage.frames import open_frames

        root = _session_root(self.attrs)
        cams = _get(self.session, "cameras") or []
        if root is None or cam_index >= len(cams) or not cams[cam_index].get("frames"):
            return None, "the store does not name the session's frames"
        spec = location.join(root, str(cams[cam_index]["frames"]))
        try:
            src = open_frames(spec, camera_name=cams[cam_index].get("name"))
            idx = min(max(capture_index, 0), len(src) - 1)
            return src.read(idx), f"{location.basename(spec)}, capture frame {idx}"
        except (SchlierenInputError, OSError, ValueError) as exc:
            return None, f"camera frame not readable: {exc}"
