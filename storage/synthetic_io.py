"""Files of synthetic captures: the session (SPEC section 1), its ground truth, backgrounds.

* :func:`write_manifest` writes ``session.yaml`` in the SPEC form, paths relative to it;
  :func:`write_frame` / :func:`write_reference` write PNG frames (8 or 16 bit), and
  :class:`VideoSink` optionally encodes a camera's frames losslessly (FFV1 in Matroska).
* :class:`TruthWriter` writes the ground truth as a Zarr v3 group (``truth.zarr``), every
  array created up front with ``dimension_names``; :func:`read_truth` reads it back.

Truth layout (``docs/design.md`` conventions; volumes on the phantom's fine grid, attrs
``origin`` / ``voxel_size`` as :meth:`Grid.to_attrs`):

=================  ===================================  ==========================================
array              dims                                 meaning
=================  ===================================  ==========================================
``time``           (frame,)                             output instants (session seconds)
``refractivity``   (frame, z, y, x) float32             ``n - 1`` at the output instants
``knot_time``      (knot,)                              times at which the phantom is defined
``knot_refractivity`` (knot, z, y, x) float32           ``n - 1`` at those knots; the phantom is
                                                        linear in time between knots, so this
                                                        gives the truth at any time in the span
``time_offset``    (camera,)                            hidden per-camera offsets (seconds)
``d_in``, ``d_out`` (camera, frame, v, u, 3) float32    unit directions of the rays through the
                                                        flow-cell centres at ``time`` (exact)
``deflection``     (camera, frame, v, u, 2) float32     image-plane deflection (pixels) at
                                                        ``time``, area mean over each flow cell
``deflection_rs``  (camera, frame, v, u, 2) float32     the rolling-shutter deflection of raw
                                                        frame ``A + frame`` (area mean per cell)
=================  ===================================  ==========================================

A capture rendered with lab effects (:mod:`schlieren.pipeline.synthetic.lab`) also has
``lab.json`` beside ``truth.zarr`` (:func:`write_lab_truth`, :func:`read_lab_truth`): the
effects' parameters and, per camera, what was drawn, indexed by raw frame (0 = the
capture's first frame, as the frame files are numbered) and by reference frame:

================  ==================  =========================================================
key               shape               meaning
================  ==================  =========================================================
``shift``         (raw, 2)            image displacement of the principal point against the
                                      reference (u, v pixels)
``roll``          (raw,)              rotation about the optical axis (radians, +u towards +v)
``homography``    (raw, 3, 3)         reference pixel -> frame pixel, undistorted coordinates
``gain``          (raw,)              lamp gain of the frame
``offset``        (raw,)              grey levels (8-bit scale) added to the frame
``phase``         (raw,)              row banding phase at row 0 (radians): rows times
                                      ``1 + banding sin(2 pi f v line_time + phase)``
``ref_gain``,     (ref,)              the same for each reference frame
``ref_offset``,
``ref_phase``
``hot``, ``dead`` (k, 2)              (row, column) of pixels stuck at full scale / at 0
``stuck``         (k, 2)              (row, column) of pixels stuck at ``stuck_value`` (8-bit)
================  ==================  =========================================================
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
import zarr

from schlieren.pipeline.geometry import Camera, Grid, Medium
from schlieren.storage import location
from schlieren.storage.errors import StoreError

__all__ = [
    "read_store_frames",
    "frame_pattern",
    "write_manifest",
    "write_frame",
    "write_reference",
    "write_reference_frames",
    "manifest_with_voxel",
    "VideoSink",
    "TruthWriter",
    "Truth",
    "read_truth",
    "read_store_refractivity",
    "write_json",
    "export_background",
    "write_lab_truth",
    "read_lab_truth",
    "LAB_FORMAT",
]

log = logging.getLogger(__name__)

TRUTH_FORMAT = "schlieren-truth/1"
LAB_FORMAT = "schlieren-lab/1"


def frame_pattern(camera_name: str) -> str:
    """Relative printf pattern of a camera's frames."""
    return f"{camera_name}/frames/%05d.png"


def _camera_entry(cam: Camera, *, frames: str, reference: str, write_offset: bool) -> dict:
    e: dict[str, Any] = {
        "name": cam.name,
        "frames": frames,
        "reference": reference,
        "image_size": [int(cam.width), int(cam.height)],
        "K": cam.K.tolist(),
        "dist": cam.dist.tolist(),
        "R": cam.R.tolist(),
        "t": cam.t.tolist(),
        "background": {"point": cam.bg_point.tolist(), "normal": cam.bg_normal.tolist()},
        "rolling_shutter": {"line_time": float(cam.line_time)},
    }
    if write_offset:
        e["time_offset"] = float(cam.time_offset)
    return e


def write_manifest(out_dir: str | os.PathLike, *, name: str, frame_rate: float, frames: tuple[int, int],
                   grid: Grid, medium: Medium, cameras: list[Camera], camera_files: dict[str, tuple[str, str]],
                   strobe_search: tuple[int, int] | None, voxel_size: bool = True) -> Path:
    """Write ``session.yaml`` (SPEC section 1).

    Parameters
    ----------
    out_dir : path
    name : str
    frame_rate : float
    frames : (int, int)
        Half-open range of frames to process.
    grid : Grid
        The reconstruction volume (``volume`` block).
    medium : Medium
    cameras : list of Camera
        With ``time_offset`` set; offsets are written only when ``strobe_search`` is None.
    camera_files : dict
        ``name -> (frames spec, reference spec)``, relative to ``out_dir``.
    strobe_search : (int, int) or None
        With a range, the manifest gets ``sync.strobe.search_frames`` and no offsets.
    voxel_size : bool
        Write ``volume.voxel_size`` (False leaves the choice to the pipeline: the
        cameras' pixel footprint).

    Returns
    -------
    Path of the manifest.
    """
    out = Path(out_dir)
    doc: dict[str, Any] = {
        "format": "schlieren-session/1",
        "name": name,
        "frame_rate": float(frame_rate),
        "frames": [int(frames[0]), int(frames[1])],
        "volume": {"min": list(grid.vmin), "max": list(grid.vmax)},
        "medium": {"n_ambient": medium.n_ambient, "T_ambient": medium.T_ambient,
                   "p_ambient": medium.p_ambient, "gladstone_dale": medium.gladstone_dale},
    }
    if voxel_size:
        doc["volume"]["voxel_size"] = float(grid.voxel_size)
    if strobe_search is not None:
        doc["sync"] = {"strobe": {"search_frames": [int(strobe_search[0]), int(strobe_search[1])]}}
    doc["cameras"] = [_camera_entry(c, frames=camera_files[c.name][0], reference=camera_files[c.name][1],
                                    write_offset=strobe_search is None) for c in cameras]
    path = out / "session.yaml"
    out.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None, width=120)
    return path


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError("frames must be uint8 or uint16")
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def manifest_with_voxel(session_path: str | os.PathLike, voxel: float) -> Path:
    """A copy of ``session.yaml`` beside it (``session-voxel<V>.yaml``) that sets ``volume.voxel_size``."""
    src = Path(session_path)
    doc = yaml.safe_load(src.read_text())
    doc.setdefault("volume", {})["voxel_size"] = float(voxel)
    out = src.with_name(f"{src.stem}-voxel{1e3 * float(voxel):g}mm.yaml")
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out


def write_frame(out_dir: str | os.PathLike, camera_name: str, index: int, image: np.ndarray) -> Path:
    """Write frame ``index`` of a camera as PNG under ``camera_name/frames/``."""
    path = Path(out_dir) / (frame_pattern(camera_name) % index)
    _write_png(path, image)
    return path


def write_reference(out_dir: str | os.PathLike, camera_name: str, image: np.ndarray) -> str:
    """Write the reference image; returns its path relative to ``out_dir``."""
    rel = f"{camera_name}/reference.png"
    _write_png(Path(out_dir) / rel, image)
    return rel


class VideoSink:
    """Video of one camera (8-bit grey), written frame by frame.

    ``codec="ffv1"``: lossless FFV1 in Matroska through OpenCV (``capture.mkv``).
    ``codec="h264"``: lossy H.264 (yuv420p, constant bitrate of ``bits_per_pixel`` per
    pixel and frame, like a camcorder's AVCHD stream: about 0.16 at 1440x1080 and
    15 Mbit/s, 60 fields/s) in MP4 through the ``ffmpeg`` binary of ``imageio-ffmpeg``
    (optional, extra ``bench``). ``name`` is the file's stem.
    """

    def __init__(self, out_dir: str | os.PathLike, camera_name: str, frame_rate: float, size: tuple[int, int],
                 *, codec: str = "ffv1", bits_per_pixel: float = 0.16, name: str = "capture"):
        self.codec = codec
        self._size = (int(size[0]), int(size[1]))
        if codec == "ffv1":
            self.rel = f"{camera_name}/{name}.mkv"
            path = Path(out_dir) / self.rel
            path.parent.mkdir(parents=True, exist_ok=True)
            self._w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), float(frame_rate),
                                      self._size, False)
            if not self._w.isOpened():
                raise OSError(f"cannot open a FFV1 video writer for {path}")
        elif codec == "h264":
            try:
                import imageio_ffmpeg
            except ImportError as exc:
                raise ImportError("lossy video needs imageio-ffmpeg: pip install 'schlieren[bench]'") from exc
            self.rel = f"{camera_name}/{name}.mp4"
            path = Path(out_dir) / self.rel
            path.parent.mkdir(parents=True, exist_ok=True)
            kbps = max(int(round(bits_per_pixel * self._size[0] * self._size[1] * frame_rate / 1000.0)), 16)
            self._w = imageio_ffmpeg.write_frames(
                str(path), self._size, fps=float(frame_rate), codec="libx264", pix_fmt_in="gray",
                pix_fmt_out="yuv420p", bitrate=f"{kbps}k", macro_block_size=1,
                output_params=["-maxrate", f"{kbps}k", "-bufsize", f"{2 * kbps}k", "-g", "15", "-bf", "2"],
                ffmpeg_log_level="error")
            self._w.send(None)
        else:
            raise ValueError(f"video codec must be 'ffv1' or 'h264', not {codec!r}")

    def write(self, image: np.ndarray) -> None:
        if image.dtype != np.uint8:
            raise ValueError("video frames must be 8-bit")
        if self.codec == "ffv1":
            self._w.write(image)
        else:
            self._w.send(np.ascontiguousarray(image))

    def close(self) -> None:
        if self.codec == "ffv1":
            self._w.release()
        else:
            self._w.close()


def write_reference_frames(out_dir: str | os.PathLike, camera_name: str, images) -> str:
    """Write several reference images (no flow) as a PNG sequence; returns the relative printf pattern."""
    rel = f"{camera_name}/reference/%03d.png"
    for i, img in enumerate(images):
        _write_png(Path(out_dir) / (rel % i), img)
    return rel


# --------------------------------------------------------------------------------------
# ground truth
# --------------------------------------------------------------------------------------

def _vol_chunks(shape: tuple[int, ...]) -> tuple[int, ...]:
    return (1,) + tuple(shape[1:])


class TruthWriter:
    """Create the truth group up front, then fill it chunk by chunk.

    Parameters
    ----------
    path : path
        ``.../truth.zarr`` (overwritten).
    grid : Grid
        The phantom's fine grid.
    n_frames, n_knots, n_cameras : int
    flow_shape : (int, int)
        ``FlowGrid.shape`` (rows, cols).
    attrs : dict
        Root attributes (JSON-able): generation parameters.
    """

    def __init__(self, path: str | os.PathLike, *, grid: Grid, n_frames: int, n_knots: int, n_cameras: int,
                 flow_shape: tuple[int, int], attrs: dict):
        self.path = Path(path)
        g = zarr.open_group(str(self.path), mode="w", zarr_format=3)
        g.attrs.update({"format": TRUTH_FORMAT, **attrs})
        nz, ny, nx = grid.shape
        h, w = flow_shape
        va = {**grid.to_attrs(), "units": "1 (n - 1)"}
        g.create_array("time", shape=(n_frames,), chunks=(n_frames,), dtype="float64", fill_value=np.nan,
                       dimension_names=["frame"], attributes={"units": "s"})
        g.create_array("refractivity", shape=(n_frames, nz, ny, nx), chunks=(1, nz, ny, nx), dtype="float32",
                       fill_value=np.nan, dimension_names=["frame", "z", "y", "x"], attributes=va)
        g.create_array("knot_time", shape=(n_knots,), chunks=(max(n_knots, 1),), dtype="float64",
                       fill_value=np.nan, dimension_names=["knot"], attributes={"units": "s"})
        g.create_array("knot_refractivity", shape=(n_knots, nz, ny, nx), chunks=(1, nz, ny, nx),
                       dtype="float32", fill_value=np.nan, dimension_names=["knot", "z", "y", "x"], attributes=va)
        g.create_array("time_offset", shape=(n_cameras,), chunks=(n_cameras,), dtype="float64",
                       fill_value=np.nan, dimension_names=["camera"], attributes={"units": "s"})
        for name, comp, units in (("d_in", 3, "1"), ("d_out", 3, "1"), ("deflection", 2, "px"),
                                  ("deflection_rs", 2, "px")):
            g.create_array(name, shape=(n_cameras, n_frames, h, w, comp), chunks=(1, 1, h, w, comp),
                           dtype="float32", fill_value=np.nan,
                           dimension_names=["camera", "frame", "v", "u", "component"],
                           attributes={"units": units})
        self._g = g

    def write_times(self, time: np.ndarray, knot_time: np.ndarray, time_offset: np.ndarray) -> None:
        self._g["time"][:] = np.asarray(time, dtype=np.float64)
        self._g["knot_time"][:] = np.asarray(knot_time, dtype=np.float64)
        self._g["time_offset"][:] = np.asarray(time_offset, dtype=np.float64)

    def write_refractivity(self, k: int, volume: np.ndarray) -> None:
        self._g["refractivity"][k] = np.asarray(volume, dtype=np.float32)

    def write_knot(self, j: int, volume: np.ndarray) -> None:
        self._g["knot_refractivity"][j] = np.asarray(volume, dtype=np.float32)

    def write_camera_frame(self, c: int, k: int, *, d_in=None, d_out=None, deflection=None,
                           deflection_rs=None) -> None:
        for name, a in (("d_in", d_in), ("d_out", d_out), ("deflection", deflection),
                        ("deflection_rs", deflection_rs)):
            if a is not None:
                self._g[name][c, k] = np.asarray(a, dtype=np.float32)


@dataclass(frozen=True)
class Truth:
    """Ground truth opened from ``truth.zarr`` (arrays are lazy zarr arrays).

    Attributes
    ----------
    grid_origin, voxel_size : ndarray (3,)
    time : ndarray (frame,)
    refractivity : zarr array (frame, z, y, x)
    knot_time : ndarray (knot,)
    knot_refractivity : zarr array (knot, z, y, x)
    time_offset : ndarray (camera,)
    group : zarr Group
    attrs : dict
    """

    grid_origin: np.ndarray
    voxel_size: np.ndarray
    time: np.ndarray
    refractivity: Any
    knot_time: np.ndarray
    knot_refractivity: Any
    time_offset: np.ndarray
    group: Any
    attrs: dict


def _open_group(path: str | os.PathLike, what: str, *, checked_reads: bool = False):
    p = location.normalize(path)
    if not location.exists(p):
        raise StoreError(f"{what} does not exist", file=p)
    try:
        if checked_reads:
            from schlieren.storage.integrity import checked

            return zarr.open_group(checked(p, read_only=True), mode="r")
        return location.zarr_open_group(p, mode="r")
    except Exception as exc:  # zarr raises several types for a non-group
        raise StoreError(f"cannot open {what} as a Zarr group ({type(exc).__name__})", file=p) from exc


def read_truth(path: str | os.PathLike) -> Truth:
    """Open a ground-truth group written by :class:`TruthWriter`."""
    g = _open_group(path, "truth")
    if g.attrs.get("format") != TRUTH_FORMAT:
        raise StoreError(f"not a truth group (format {g.attrs.get('format')!r})", file=str(path), field="format")
    r = g["refractivity"]
    return Truth(grid_origin=np.asarray(r.attrs["origin"], dtype=np.float64),
                 voxel_size=np.asarray(r.attrs["voxel_size"], dtype=np.float64),
                 time=np.asarray(g["time"][:]), refractivity=r, knot_time=np.asarray(g["knot_time"][:]),
                 knot_refractivity=g["knot_refractivity"], time_offset=np.asarray(g["time_offset"][:]),
                 group=g, attrs=dict(g.attrs))


def read_store_refractivity(path: str | os.PathLike) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """Open a result store's ``refractivity`` (frame, z, y, x) and ``time`` (frame,) (SPEC section 2).

    Returns
    -------
    refractivity : zarr array, lazy
    time : ndarray (frame,)
    origin, voxel_size : ndarray (3,)
    """
    g = _open_group(path, "store", checked_reads=True)  # a corrupt or lost chunk raises ChunkError
    for name in ("refractivity", "time"):
        if name not in g:
            raise StoreError(f"the store has no '{name}' array", file=str(path), field=name)
    r = g["refractivity"]
    try:
        origin = np.asarray(r.attrs["origin"], dtype=np.float64)
        vs = np.broadcast_to(np.asarray(r.attrs["voxel_size"], dtype=np.float64), (3,)).copy()
    except KeyError as exc:
        raise StoreError("refractivity lacks the origin/voxel_size attributes", file=str(path),
                         field=f"refractivity.attrs.{exc.args[0]}") from None
    return r, np.asarray(g["time"][:], dtype=np.float64), origin, vs


def read_store_frames(path: str | os.PathLike) -> np.ndarray:
    """Capture frame index of every store frame (the ``frame`` coordinate; 0.. without one)."""
    g = _open_group(path, "store")
    if "frame" in g:
        return np.asarray(g["frame"][:], dtype=np.int64)
    return np.arange(int(g["time"].shape[0]), dtype=np.int64)


def write_lab_truth(path: str | os.PathLike, record: dict) -> Path:
    """Write the lab effects drawn for a capture (``lab.json``, module notes) with its format tag."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({"format": LAB_FORMAT, **record}))
    return p


def read_lab_truth(path: str | os.PathLike) -> dict:
    """Read ``lab.json`` (the file, or the session folder / ``truth.zarr`` beside it).

    Returns the record with each camera's entries as float64 arrays (int64 for the pixel
    positions), or raises :class:`StoreError` when there is none (a clean capture).
    """
    p = Path(path)
    if p.is_dir():
        p = (p.parent if p.name.endswith(".zarr") else p) / "lab.json"
    if not p.is_file():
        raise StoreError("no lab effects recorded (a clean capture?)", file=str(p))
    rec = json.loads(p.read_text())
    if rec.get("format") != LAB_FORMAT:
        raise StoreError(f"not a lab record (format {rec.get('format')!r})", file=str(p), field="format")
    ints = {"hot", "dead", "stuck"}
    rec["cameras"] = {name: {k: np.asarray(v, dtype=np.int64 if k in ints else np.float64).reshape(
        (-1, 2) if k in ints else np.shape(v)) for k, v in cam.items()} for name, cam in rec["cameras"].items()}
    return rec


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON (NaN/inf written as strings)."""
    def fix(o):
        if isinstance(o, float) and not np.isfinite(o):
            return str(o)
        if isinstance(o, dict):
            return {k: fix(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [fix(v) for v in o]
        return o

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        json.dump(fix(obj), fh, indent=2)


def export_background(path: str | os.PathLike, width_px: int, height_px: int, dpi: float, *,
                      seed: int = 0, feature_mm: float | None = None, bands: int = 3) -> dict:
    """Write a printable Wavelet Noise background (PNG with its DPI recorded).

    Parameters
    ----------
    path : path
        Output PNG.
    width_px, height_px : int
        Image size in printer pixels.
    dpi : float
        Print resolution; the print measures ``width_px / dpi`` x ``height_px / dpi`` inches.
    seed : int
    feature_mm : float, optional
        Finest coefficient spacing on paper (mm); default 3 printer pixels.
    bands : int

    Returns
    -------
    dict with the print size in millimetres and the spacing used.
    """
    from PIL import Image

    from schlieren.pipeline.synthetic.background import background_image, make_background, wavelet_noise_tile

    pixel = 0.0254 / float(dpi)
    spacing = 3 * pixel if feature_mm is None else feature_mm * 1e-3
    bg = make_background(np.zeros(3), np.array([0.0, 1.0, 0.0]), spacing=spacing,
                         tile=wavelet_noise_tile(256, seed=seed), bands=bands, seed=seed)
    img = background_image(bg, int(width_px), int(height_px), pixel_size=pixel)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.rint(img).astype(np.uint8), mode="L").save(str(p), dpi=(float(dpi), float(dpi)))
    return {"path": str(p), "width_mm": width_px / dpi * 25.4, "height_mm": height_px / dpi * 25.4,
            "dpi": float(dpi), "feature_mm": spacing * 1e3}
