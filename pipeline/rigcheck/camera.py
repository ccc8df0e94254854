"""One camera's check (:func:`check_camera` -> :class:`CameraCheck`): everything
``schlieren check`` says about a camera, computed from its reference frames, a few frames
of the capture and its strobe window, before anyone reconstructs."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline.flow.params import FlowParams, window_for_voxel
from schlieren.pipeline.geometry import AUTO_PX_PER_VOXEL, Camera, Grid, pixel_footprint
from schlieren.pipeline.rigcheck.image import clipped_fractions, focus_energy, hot_pixels
from schlieren.pipeline.rigcheck.motion import GlobalShift, global_shift
from schlieren.pipeline.rigcheck.noise import predicted_flow_noise, sensor_noise, sensor_noise_from_pairs
from schlieren.pipeline.rigcheck.params import CheckParams
from schlieren.pipeline.sync.strobe import detect_flash, offset_from_flash

__all__ = ["CameraCheck", "Footprint", "check_camera", "footprint"]


@dataclass(frozen=True)
class Footprint:
    """The volume's image in one camera.

    Attributes
    ----------
    box : (int, int, int, int)
        ``(column0, row0, column1, row1)`` of the projected box's bounding rectangle,
        clipped to the image (half-open).
    size : (int, int)
        Its width and height, pixels.
    fraction : float
        Its area over the image's.
    metres_per_px : float
        The pixel's footprint at the volume centre.
    px_per_voxel : float
        The run's voxel in this camera's pixels.
    implied_voxel : float
        The voxel these pixels imply (``AUTO_PX_PER_VOXEL`` pixels per voxel), metres.
    """

    box: tuple[int, int, int, int]
    size: tuple[int, int]
    fraction: float
    metres_per_px: float
    px_per_voxel: float
    implied_voxel: float


def footprint(cam: Camera, grid: Grid) -> Footprint:
    """The volume's footprint in ``cam`` (:class:`Footprint`)."""
    uv = cam.project(grid.corners())
    W, H = cam.image_size
    uv = uv[np.isfinite(uv).all(axis=1)]
    if len(uv) == 0:
        box = (0, 0, 0, 0)
    else:
        lo = np.clip(np.floor(uv.min(axis=0)), 0, [W, H]).astype(int)
        hi = np.clip(np.ceil(uv.max(axis=0)) + 1, 0, [W, H]).astype(int)
        box = (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))
    size = (box[2] - box[0], box[3] - box[1])
    mpp = pixel_footprint(cam, grid.center)
    return Footprint(box, size, size[0] * size[1] / float(W * H), mpp, grid.voxel_size / mpp,
                     AUTO_PX_PER_VOXEL * mpp)


@dataclass(frozen=True)
class CameraCheck:
    """What ``schlieren check`` found for one camera (see :func:`check_camera`).

    Attributes
    ----------
    name : str
    noise : float
        Sensor noise of one frame, grey levels.
    noise_source : str
        How it was measured.
    flow_noise : float
        Predicted flow noise (pixels, per component, median over the volume's footprint).
    window : int
        The LK window the run will use (pixels).
    focus : float
        Finest-scale texture energy of the reference (:func:`focus_energy`).
    clipped : (float, float)
        Fractions of the reference clipped black, white.
    shifts : tuple of GlobalShift
        Each checked frame's shift against the reference.
    hot, dead : ndarray, shape (n, 2)
        ``(row, column)`` of the hot (dead) pixels.
    flash : str
        Where the strobe flash was found, or why not ("" without a strobe window).
    offset : float or None
        The time offset the flash gives, seconds.
    footprint : Footprint
    notes : tuple of str
        Warnings, one line each.
    """

    name: str
    noise: float
    noise_source: str
    flow_noise: float
    window: int
    focus: float
    clipped: tuple[float, float]
    shifts: tuple
    hot: np.ndarray
    dead: np.ndarray
    flash: str
    offset: float | None
    footprint: Footprint
    notes: tuple = field(default=())

    @property
    def shift(self) -> GlobalShift | None:
        """The checked frame that moved most (None: no frame checked)."""
        return max(self.shifts, key=lambda s: s.magnitude) if self.shifts else None


def _noise(reference_frames: np.ndarray, frames: np.ndarray | None, full_scale: float) -> tuple[float, str]:
    if len(reference_frames) >= 2:
        return sensor_noise(reference_frames, full_scale=full_scale), f"{len(reference_frames)} reference frames"
    if frames is not None and len(frames) >= 2:
        return sensor_noise_from_pairs(frames), f"{len(frames)} consecutive frames"
    return float("nan"), "unknown (one reference image, fewer than 2 frames)"


def _flash(cam: Camera, strobe_rows, first: int, frame_rate: float) -> tuple[str, float | None]:
    if strobe_rows is None:
        return "", None
    try:
        det = detect_flash(strobe_rows)
    except ValueError as exc:
        return str(exc).split(":")[0], None
    where = f"frame {first + det.frame} rows {det.first_row}-{det.last_row} (SNR {det.confidence:.0f})"
    if cam.line_time <= 0:
        return where, None
    try:
        return where, offset_from_flash(det, first_frame=first, frame_rate=frame_rate, line_time=cam.line_time)
    except ValueError as exc:
        return f"{where}: {exc}", None


# long: the one place that gathers a camera's numbers (each is one call) and its notes
def check_camera(cam: Camera, grid: Grid, reference_frames: np.ndarray, frames: np.ndarray | None = None, *,
                 strobe_rows: np.ndarray | None = None, strobe_first: int = 0, frame_rate: float = 60.0,
                 full_scale: float = 255.0, flow: FlowParams = FlowParams(),
                 params: CheckParams = CheckParams()) -> CameraCheck:
    """Check one camera.

    Parameters
    ----------
    cam : Camera
    grid : Grid
        The reconstruction volume (its voxel).
    reference_frames : ndarray, shape (n, H, W)
        The reference's frames (one or more), grey levels.
    frames : ndarray, shape (k, H, W), optional
        A few frames of the capture (their global shift against the reference).
    strobe_rows : ndarray, shape (F, H), optional
        Row means of the strobe window's frames (:func:`~schlieren.pipeline.sync.row_means`).
    strobe_first : int
        Index of the strobe window's first frame.
    frame_rate : float
    full_scale : float
        The frames' largest raw value (255, 65535).
    flow : FlowParams
        The run's flow parameters (window, pre-smoothing, regularisation).
    params : CheckParams
    """
    refs = np.asarray(reference_frames, dtype=np.float32)
    reference = refs.mean(axis=0)
    noise, source = _noise(refs, frames, full_scale)
    fp = footprint(cam, grid)
    window = window_for_voxel(fp.px_per_voxel, flow.window_per_voxel) if flow.window_per_voxel > 0 else flow.window
    sigma = predicted_flow_noise(reference, noise=noise if np.isfinite(noise) else 0.0, n_reference=len(refs),
                                 window=window, window_type=flow.window_type, presmooth=flow.presmooth,
                                 regularisation=flow.regularisation)
    c0, r0, c1, r1 = fp.box
    region = sigma[r0:r1, c0:c1] if (c1 > c0 and r1 > r0) else sigma
    flow_noise = float(np.median(region))
    focus = focus_energy(reference, noise=(noise if np.isfinite(noise) else 0.0) / np.sqrt(len(refs)))
    clipped = clipped_fractions(reference, full_scale=full_scale)
    hot, dead = hot_pixels(reference, sigmas=params.hot_sigmas, min_step=params.hot_min_step * full_scale / 255.0,
                           full_scale=full_scale)
    shifts = tuple(global_shift(reference, f) for f in frames) if frames is not None else ()
    flash, offset = _flash(cam, strobe_rows, strobe_first, frame_rate)
    notes = []
    if flow_noise > params.max_flow_noise:
        notes.append(f"predicted flow noise {flow_noise:.3f} px above {params.max_flow_noise:g} px (background "
                     "texture too weak or the sensor too noisy)")
    moved = [s for s in shifts if s.magnitude > params.max_shift]
    if moved:
        worst = max(moved, key=lambda s: s.magnitude)
        notes.append(f"moved against its reference by up to {worst.magnitude:.3f} px ({len(moved)} of "
                     f"{len(shifts)} frames checked): every deflection carries it")
    if sum(clipped) > params.max_clipped:
        notes.append(f"{100 * clipped[0]:.1f} % of the reference clipped black, {100 * clipped[1]:.1f} % white")
    if len(hot) + len(dead):
        notes.append(f"{len(hot)} hot and {len(dead)} dead pixels")
    if strobe_rows is not None and offset is None:
        notes.append(f"flash: {flash}")
    if fp.fraction == 0:
        notes.append("the volume is not in the image")
    return CameraCheck(cam.name, noise, source, flow_noise, window, focus, clipped, shifts, hot, dead, flash,
                       offset, fp, tuple(notes))
