"""One camera's check (:func:`check_camera` -> :class:`CameraCheck`): everything
``schlieren check`` says about a camera, computed from its reference frames, a few frames
of the capture and its strobe window, before anyone reconstructs.

The camera's motion against the reference and its defective pixels are measured by the
run's own capture kernels (:mod:`schlieren.pipeline.capture`: the registration on the
pixels whose rays miss the volume, and the hot / dead / stuck pixel tests), with the
run's parameters, so the check reports what the run will find and remove."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline import capture as cap
from schlieren.pipeline.capture import CaptureParams
from schlieren.pipeline.flow.focus import AUTO, resolve_presmooth
from schlieren.pipeline.flow.params import FlowParams, window_for_voxel
from schlieren.pipeline.flow.reference import prepare_reference
from schlieren.pipeline.geometry import AUTO_PX_PER_VOXEL, Camera, Grid, pixel_footprint
from schlieren.pipeline.rigcheck.image import clipped_fractions, focus_energy
from schlieren.pipeline.rigcheck.noise import predicted_flow_noise, sensor_noise, sensor_noise_from_pairs
from schlieren.pipeline.rigcheck.params import CheckParams
from schlieren.pipeline.sync.strobe import detect_flash, offset_from_flash

__all__ = ["CameraCheck", "FrameMotion", "Footprint", "check_camera", "footprint", "frame_motions"]


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
class FrameMotion:
    """A checked frame's motion against the reference, flow convention
    ``frame(p) ~= reference(p + motion(p))`` (:func:`~schlieren.pipeline.capture.register_background`).

    Attributes
    ----------
    frame : int
        Index of the frame in the camera's frames.
    motion : ndarray, shape (8,)
        :data:`~schlieren.pipeline.capture.MOTION_PARAMS` (pixels about the image centre).
    extent : float
        The largest displacement it gives a pixel of the image, pixels.
    sigma : float
        Standard deviation of that displacement, from the fit's noise, pixels.
    """

    frame: int
    motion: np.ndarray
    extent: float
    sigma: float

    @property
    def du(self) -> float:
        """Displacement at the image centre along the columns (x), pixels."""
        return float(self.motion[0])

    @property
    def dv(self) -> float:
        """Displacement at the image centre along the rows (y), pixels."""
        return float(self.motion[1])

    @property
    def rotation(self) -> float:
        """Rotation of the image, radians (x towards y)."""
        return float(0.5 * (self.motion[4] - self.motion[3]))

    @property
    def magnitude(self) -> float:
        """:attr:`extent`."""
        return self.extent


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
    motions : tuple of FrameMotion
        Each checked frame's motion against the reference.
    hot, dead, stuck : ndarray, shape (n, 2)
        ``(row, column)`` of the hot, dead and stuck pixels
        (:func:`~schlieren.pipeline.capture.find_defective_pixels`).
    flash : str
        Where the strobe flash was found, or why not ("" without a strobe window).
    offset : float or None
        The time offset the flash gives, seconds.
    footprint : Footprint
    notes : tuple of str
        Warnings, one line each.
    n_reference : int
        The reference frames the run averages (the flow noise's reference term).
    """

    name: str
    noise: float
    noise_source: str
    flow_noise: float
    window: int
    focus: float
    clipped: tuple[float, float]
    motions: tuple
    hot: np.ndarray
    dead: np.ndarray
    flash: str
    offset: float | None
    footprint: Footprint
    notes: tuple = field(default=())
    stuck: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    n_reference: int = 1

    @property
    def shift(self) -> FrameMotion | None:
        """The checked frame that moved most (None: no frame checked)."""
        return max(self.motions, key=lambda s: s.extent) if self.motions else None


def _noise(reference_frames: np.ndarray, frames: np.ndarray | None, full_scale: float,
           static: np.ndarray) -> tuple[float, str]:
    if len(reference_frames) >= 2:
        return sensor_noise(reference_frames, full_scale=full_scale), f"{len(reference_frames)} reference frames"
    if frames is not None and len(frames) >= 2:
        return sensor_noise_from_pairs(frames, where=static), f"{len(frames)} frames, where the volume is not seen"
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


def frame_motions(cam: Camera, grid: Grid, reference: np.ndarray, frames, *, frame_indices=None,
                  defects: np.ndarray | None = None, static: np.ndarray | None = None, flow: FlowParams = FlowParams(),
                  capture: CaptureParams = CaptureParams()) -> tuple[FrameMotion, ...]:
    """Each frame's motion against the reference, measured as the run measures it: the
    registration (:func:`~schlieren.pipeline.capture.register_background`) on the pixels
    whose rays miss the volume box (:func:`~schlieren.pipeline.capture.static_region`,
    ``capture.static_margin``), the defective pixels and their neighbours left out, with
    the run's motion model, photometric profiles and pre-smoothed pyramid (``flow``).

    Parameters
    ----------
    cam : Camera
    grid : Grid
        The reconstruction volume (its box).
    reference : ndarray, shape (H, W)
        The reference (mean of its frames), grey levels.
    frames : sequence of ndarray, shape (H, W)
    frame_indices : sequence of int, optional
        The frames' indices (default 0, 1, ...).
    defects : ndarray, shape (H, W), optional
        :func:`~schlieren.pipeline.capture.find_defective_pixels`' map.
    static : ndarray, shape (H, W), bool, optional
        The camera's static region, when already computed.
    """
    if frames is None or len(frames) == 0:
        return ()
    prep = prepare_reference(reference, presmooth=flow.presmooth, levels=flow.levels)
    if static is None:
        static = cap.static_region(cam, grid.vmin, grid.vmax, margin=capture.static_margin)
    valid = cap.valid_pixels(defects)
    size = tuple(cam.image_size)
    idx = range(len(frames)) if frame_indices is None else frame_indices
    out = []
    for i, frame in zip(idx, frames):
        fit = cap.register_background(prep, frame, static=static, valid=valid, model=capture.motion_model,
                                      photometric=capture.photometric, banding_rows=capture.banding_rows,
                                      min_static_fraction=capture.min_static_fraction)
        out.append(FrameMotion(int(i), fit.motion, cap.motion_extent(fit.motion, size), float(fit.motion_sigma)))
    return tuple(out)


def _defects(reference_frames: np.ndarray, frames, capture: CaptureParams) -> np.ndarray:
    """The run's defective-pixel map (its tests and thresholds, its false-alarm control of
    the stuck test) from the reference frames, each one as the run reads them, and the
    checked frames."""
    stack = list(reference_frames) + ([] if frames is None else list(frames))
    return cap.find_defective_pixels(stack, threshold=capture.defect_threshold, stuck_ratio=capture.stuck_ratio)


def _notes(flow_noise: float, motions, clipped, hot, dead, stuck, flash: str, offset, fp: Footprint, strobe: bool,
           params: CheckParams) -> list[str]:
    notes = []
    if flow_noise > params.max_flow_noise:
        notes.append(f"predicted flow noise {flow_noise:.3f} px above {params.max_flow_noise:g} px (background "
                     "texture too weak or the sensor too noisy)")
    moved = [s for s in motions if s.extent > params.max_shift]
    if moved:
        worst = max(moved, key=lambda s: s.extent)
        notes.append(f"moved against its reference by up to {worst.extent:.3f} px ({len(moved)} of "
                     f"{len(motions)} frames checked): every deflection carries it")
    if sum(clipped) > params.max_clipped:
        notes.append(f"{100 * clipped[0]:.1f} % of the reference clipped black, {100 * clipped[1]:.1f} % white")
    if len(hot) + len(dead):
        notes.append(f"{len(hot)} hot and {len(dead)} dead pixels")
    if len(stuck):
        notes.append(f"{len(stuck)} stuck pixels")
    if strobe and offset is None:
        notes.append(f"flash: {flash}")
    if fp.fraction == 0:
        notes.append("the volume is not in the image")
    return notes


def check_camera(cam: Camera, grid: Grid, reference_frames: np.ndarray, frames: np.ndarray | None = None, *,
                 frame_indices=None, n_reference: int | None = None, strobe_rows: np.ndarray | None = None,
                 strobe_first: int = 0, frame_rate: float = 60.0, full_scale: float = 255.0,
                 flow: FlowParams = FlowParams(), capture: CaptureParams = CaptureParams(),
                 params: CheckParams = CheckParams()) -> CameraCheck:
    """Check one camera.

    Parameters
    ----------
    cam : Camera
    grid : Grid
        The reconstruction volume (its voxel and box).
    reference_frames : ndarray, shape (n, H, W)
        The reference's frames (one or more), grey levels.
    frames : ndarray, shape (k, H, W), optional
        A few frames of the capture (their motion against the reference).
    frame_indices : sequence of int, optional
        Their indices in the camera's frames.
    n_reference : int, optional
        Frames the run's reference averages (default ``n``): the flow noise's reference term.
    strobe_rows : ndarray, shape (F, H), optional
        Row means of the strobe window's frames (:func:`~schlieren.pipeline.sync.row_means`).
    strobe_first : int
        Index of the strobe window's first frame.
    frame_rate : float
    full_scale : float
        The frames' largest raw value (255, 65535).
    flow : FlowParams
        The run's flow parameters (window, pre-smoothing, regularisation, levels).
    capture : CaptureParams
        The run's capture corrections (motion model, static margin, defect tests).
    params : CheckParams
    """
    refs = np.asarray(reference_frames, dtype=np.float32)
    reference = refs.mean(axis=0)
    static = cap.static_region(cam, grid.vmin, grid.vmax, margin=capture.static_margin)
    noise, source = _noise(refs, frames, full_scale, static)
    if flow.presmooth == AUTO:  # the run's choice for this camera (pipeline/flow/focus.py)
        flow = dataclasses.replace(flow, presmooth=resolve_presmooth(
            AUTO, reference, method=flow.method, noise=noise if np.isfinite(noise) else 0.0, n_frames=len(refs)))
    fp = footprint(cam, grid)
    window = window_for_voxel(fp.px_per_voxel, flow.window_per_voxel) if flow.window_per_voxel > 0 else flow.window
    n_ref = len(refs) if n_reference is None else max(int(n_reference), 1)
    flow_noise = _flow_noise(reference, fp, noise=noise if np.isfinite(noise) else 0.0, n_reference=n_ref,
                             window=window, flow=flow)
    focus = focus_energy(reference, noise=(noise if np.isfinite(noise) else 0.0) / np.sqrt(len(refs)))
    clipped = clipped_fractions(reference, full_scale=full_scale)
    defects = _defects(refs, frames, capture) if capture.defective_pixels else None
    hot, dead, stuck = ((np.argwhere(defects & bit) if defects is not None else np.zeros((0, 2), np.int64))
                        for bit in (cap.HOT, cap.DEAD, cap.STUCK))
    motions = () if capture.motion_model == "none" else \
        frame_motions(cam, grid, reference, frames, frame_indices=frame_indices, defects=defects, static=static,
                      flow=flow, capture=capture)
    flash, offset = _flash(cam, strobe_rows, strobe_first, frame_rate)
    notes = _notes(flow_noise, motions, clipped, hot, dead, stuck, flash, offset, fp, strobe_rows is not None, params)
    return CameraCheck(cam.name, noise, source, flow_noise, window, focus, clipped, motions, hot, dead, flash,
                       offset, fp, tuple(notes), stuck, n_ref)


def _flow_noise(reference: np.ndarray, fp: Footprint, *, noise: float, n_reference: int, window: int,
                flow: FlowParams) -> float:
    """Median predicted flow noise over the volume's footprint (the whole image when the
    volume is not in it), computed on the footprint and the filters' reach around it only
    (the same values inside it; the regularisation's mean tensor is the crop's)."""
    H, W = reference.shape
    c0, r0, c1, r1 = fp.box if fp.size[0] > 0 and fp.size[1] > 0 else (0, 0, W, H)
    reach = 2 * int(np.ceil(3.0 * flow.presmooth)) + window // 2 + 4  # two pre-smoothings, the gradient, the window
    a0, b0 = max(r0 - reach, 0), max(c0 - reach, 0)
    crop = reference[a0:min(r1 + reach, H), b0:min(c1 + reach, W)]
    sigma = predicted_flow_noise(crop, noise=noise, n_reference=n_reference, window=window,
                                 window_type=flow.window_type, presmooth=flow.presmooth,
                                 regularisation=flow.regularisation)
    return float(np.median(sigma[r0 - a0:r1 - a0, c0 - b0:c1 - b0]))
