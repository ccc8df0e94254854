"""What a lab records beyond the ideal capture: a shaking camera, flickering light, defocus, bad pixels.

Every accuracy figure of the renderer's clean captures assumes a camera that stays where
its reference was recorded, a steady lamp, a background in focus and a flawless sensor.
:class:`LabParams` switches on, each independently, what a real BOS capture carries
(issue 33), so the pipeline can be judged on it:

* **Camera motion** against the reference: the tripod settles (a constant offset), shakes
  (a random walk per frame) and turns slightly about the optical axis. The motion is a
  rotation of the camera about its optical centre (:func:`motion_rotation`), so the whole
  image moves, the background and the volume alike (no parallax: a tripod's head turns
  far more than it translates), by the homography ``K D K^-1`` (:func:`motion_homography`;
  in undistorted pixel coordinates). The reference is recorded at the calibrated pose;
  each raw frame is rendered with the moved camera (rays traced through the flow and the
  background from the new pose).
* **Lamp flicker**: a gain and an offset per frame, and with a rolling shutter under
  mains-powered light a row banding, a sinusoid in row time at the light's flicker
  frequency (twice the mains frequency) whose phase follows the frame's start time
  (:func:`row_gain`).
* **Defocus** of the background (the camera focuses on the volume): a Gaussian blur of
  the rendered image (:func:`defocus`).
* **Vignetting**: a radial gain ``1 - v (r / r_corner)^2`` about the principal point.
* **Sensor defects**: hot pixels (stuck at full scale), dead pixels (stuck at 0) and
  pixels stuck at one grey level, at the same places in the reference and every frame.

All effects are drawn once per camera (:func:`draw_camera`) from the caller's generator
and returned as plain arrays, so the caller can record them as the capture's truth.
Pure numpy/scipy; the renderer (:mod:`.render`) stays unaware of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from schlieren.pipeline.geometry import Camera, rodrigues
from schlieren.pipeline.params import param, parameters

__all__ = ["LabParams", "LAB_PRESETS", "CameraLab", "draw_camera", "motion_rotation", "motion_homography",
           "moved_camera", "row_gain", "vignette", "defocus", "photometry", "apply_defects"]


@parameters
class LabParams:
    """What a lab's capture carries beyond the ideal one; every effect is off by default."""

    motion_offset: float = param(
        0.0, unit="px", ge=0.0, le=50.0,
        help="Constant displacement of the image against the reference, at the principal point, in a random "
             "direction per camera: where the tripod settled after the reference.")
    motion_walk: float = param(
        0.0, unit="px", ge=0.0, le=10.0,
        help="Random walk of the image per raw frame: each frame after the first adds a Gaussian step of this "
             "standard deviation along each image axis.")
    roll: float = param(
        0.0, unit="deg", ge=0.0, le=10.0,
        help="Constant rotation of the camera about its optical axis against the reference, random sign per camera"
             " (positive turns the image content from +u towards +v).")
    roll_walk: float = param(
        0.0, unit="deg", ge=0.0, le=1.0,
        help="Random walk of that rotation: Gaussian steps of this standard deviation per raw frame.")
    flicker_gain: float = param(
        0.0, unit="1", ge=0.0, le=0.5,
        help="Lamp brightness per frame (reference frames included): the image times `1 + N(0, flicker_gain)`, "
             "drawn independently for each frame and camera.")
    flicker_offset: float = param(
        0.0, unit="grey level", ge=0.0, le=50.0,
        help="Grey levels (8-bit scale) `N(0, flicker_offset)` added per frame (stray light, black level).")
    banding: float = param(
        0.0, unit="1", ge=0.0, le=0.5,
        help="Relative amplitude of the row banding of a rolling shutter under mains-powered light: rows times `1 "
             "+ banding sin(2 pi f t_row + phase)`; 0 = none.")
    banding_frequency: float = param(
        100.0, unit="Hz", gt=0.0,
        help="The light's flicker frequency `f`: twice the mains frequency (100 Hz at 50 Hz mains, 120 at 60).")
    defocus: float = param(
        0.0, unit="px", ge=0.0, le=20.0,
        help="Sigma of the Gaussian blur of the background image: the camera is focused on the volume.")
    vignetting: float = param(
        0.0, unit="1", ge=0.0, lt=1.0,
        help="Relative brightness lost at the image corners (radial gain `1 - v (r / r_corner)^2`).")
    hot_pixels: int = param(
        0, unit="1", ge=0,
        help="Pixels per camera stuck at full scale, at the same places in the reference and every frame.")
    dead_pixels: int = param(
        0, unit="1", ge=0,
        help="Pixels per camera stuck at 0.")
    stuck_pixels: int = param(
        0, unit="1", ge=0,
        help="Pixels per camera stuck at one random grey level each.")

    @property
    def moves(self) -> bool:
        """Whether any frame's camera pose differs from the reference's."""
        return any(getattr(self, k) > 0 for k in ("motion_offset", "motion_walk", "roll", "roll_walk"))

    @property
    def active(self) -> bool:
        """Whether any effect is switched on."""
        return any(getattr(self, f.name) > 0 for f in dataclasses.fields(self) if f.name != "banding_frequency")


#: Named settings. ``lab``: the reference lab capture of issue 33 (a tripod shaking by a
#: 0.05 px random walk per frame from a 0.1 px start, lamp flicker of 2 % gain and 1 grey
#: level per frame, the background 0.7 px out of focus, 25 hot pixels per camera).
#: ``lab-all``: that plus every other effect (a 0.01 degree roll walking 0.005 degree per
#: frame, 1 % row banding at 100 Hz, 20 % vignetting, 25 dead and 10 stuck pixels).
LAB_PRESETS: dict[str, LabParams] = {
    "lab": LabParams(motion_offset=0.1, motion_walk=0.05, flicker_gain=0.02, flicker_offset=1.0, defocus=0.7,
                     hot_pixels=25),
    "lab-all": LabParams(motion_offset=0.1, motion_walk=0.05, roll=0.01, roll_walk=0.005, flicker_gain=0.02,
                         flicker_offset=1.0, banding=0.01, banding_frequency=100.0, defocus=0.7, vignetting=0.2,
                         hot_pixels=25, dead_pixels=25, stuck_pixels=10),
}


@dataclass(frozen=True)
class CameraLab:
    """One camera's drawn lab effects (every raw frame ``f`` of the capture, every reference frame ``r``).

    Attributes
    ----------
    shift : ndarray, shape (n_raw, 2)
        Image displacement of the principal point against the reference (u, v pixels).
    roll : ndarray, shape (n_raw,)
        Rotation about the optical axis (radians; positive turns +u towards +v).
    rotation : ndarray, shape (n_raw, 3, 3)
        ``D``: camera coordinates of a world point in the moved pose are ``D`` times its
        coordinates in the reference pose (the moved camera's ``R`` is ``D R``).
    homography : ndarray, shape (n_raw, 3, 3)
        ``K D K^-1``: reference pixel -> frame pixel (undistorted pixel coordinates).
    gain, offset, phase : ndarray, shape (n_raw,)
        Lamp gain, offset (grey levels) and the banding phase at row 0 (radians).
    ref_gain, ref_offset, ref_phase : ndarray, shape (n_ref,)
        The same for the reference frames.
    hot, dead, stuck : ndarray, shape (k, 2) int
        (row, column) of the defective pixels.
    stuck_value : ndarray, shape (k,)
        The stuck pixels' values on the 8-bit scale.
    """

    shift: np.ndarray
    roll: np.ndarray
    rotation: np.ndarray
    homography: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    phase: np.ndarray
    ref_gain: np.ndarray
    ref_offset: np.ndarray
    ref_phase: np.ndarray
    hot: np.ndarray
    dead: np.ndarray
    stuck: np.ndarray
    stuck_value: np.ndarray


def motion_rotation(shift, roll: float, focal: float) -> np.ndarray:
    """The camera-frame rotation ``D`` that moves the principal point's image by ``shift``
    pixels and turns the image by ``roll`` radians about it.

    ``D = R_n(roll) A`` with ``A`` the smallest rotation taking the optical axis ``e_z`` to
    ``n = (du / f, dv / f, 1) / |.|`` and ``R_n`` a rotation about ``n``: the point seen
    along the optical axis at the reference is seen along ``n``, exactly ``shift`` away.
    """
    du, dv = float(shift[0]), float(shift[1])
    n = np.array([du / focal, dv / focal, 1.0])
    n /= np.linalg.norm(n)
    axis = np.cross([0.0, 0.0, 1.0], n)
    s = np.linalg.norm(axis)
    A = np.eye(3) if s < 1e-300 else rodrigues(axis / s * np.arctan2(s, n[2]))
    return rodrigues(n * float(roll)) @ A


def motion_homography(camera: Camera, rotation: np.ndarray) -> np.ndarray:
    """``K D K^-1``: where a reference pixel (undistorted coordinates) is seen after the rotation."""
    return camera.K @ rotation @ np.linalg.inv(camera.K)


def moved_camera(camera: Camera, rotation: np.ndarray) -> Camera:
    """``camera`` turned by ``rotation`` about its optical centre (background plane unchanged)."""
    C = camera.center
    R = rotation @ camera.R
    return dataclasses.replace(camera, R=R, t=-R @ C)


def _walk(rng: np.random.Generator, n: int, start, step: float, shape=()) -> np.ndarray:
    """``start`` at the first of ``n`` frames, then Gaussian steps of sigma ``step`` (per component)."""
    steps = rng.normal(0.0, 1.0, (n,) + shape) * step
    steps[0] = 0.0
    return np.asarray(start, dtype=np.float64) + np.cumsum(steps, axis=0)


def _defects(rng: np.random.Generator, params: LabParams, image_size: tuple[int, int]):
    W, H = image_size
    counts = (params.hot_pixels, params.dead_pixels, params.stuck_pixels)
    total = int(sum(counts))
    if total > W * H:
        raise ValueError(f"{total} defective pixels do not fit a {W}x{H} sensor")
    flat = rng.choice(W * H, size=total, replace=False) if total else np.zeros(0, dtype=np.int64)
    rc = np.stack([flat // W, flat % W], axis=-1).astype(np.int64)
    a, b = counts[0], counts[0] + counts[1]
    return rc[:a], rc[a:b], rc[b:], rng.uniform(0.0, 255.0, counts[2])


def draw_camera(params: LabParams, camera: Camera, rng: np.random.Generator, *, n_raw: int, n_ref: int,
                frame_rate: float, lamp_phase: float) -> CameraLab:
    """Draw one camera's lab effects for ``n_raw`` raw frames and ``n_ref`` reference frames.

    The banding phase of raw frame ``f`` is the light's phase at the start of its row 0,
    ``lamp_phase + 2 pi f_light (time_offset + f / frame_rate)`` (one lamp for the whole rig);
    the reference frames, recorded at another time, take uniform random phases.
    """
    focal = float(camera.K[0, 0])
    ang = rng.uniform(0.0, 2.0 * np.pi)
    start = params.motion_offset * np.array([np.cos(ang), np.sin(ang)])
    shift = _walk(rng, n_raw, start, params.motion_walk, (2,))
    roll = _walk(rng, n_raw, np.deg2rad(params.roll) * rng.choice([-1.0, 1.0]), np.deg2rad(params.roll_walk))
    rot = np.stack([motion_rotation(s, r, focal) for s, r in zip(shift, roll)])
    hom = np.stack([motion_homography(camera, d) for d in rot])
    gain = 1.0 + rng.normal(0.0, 1.0, n_raw) * params.flicker_gain
    offset = rng.normal(0.0, 1.0, n_raw) * params.flicker_offset
    t0 = (0.0 if camera.time_offset is None else camera.time_offset) + np.arange(n_raw) / frame_rate
    phase = np.mod(lamp_phase + 2.0 * np.pi * params.banding_frequency * t0, 2.0 * np.pi)
    ref_gain = 1.0 + rng.normal(0.0, 1.0, n_ref) * params.flicker_gain
    ref_offset = rng.normal(0.0, 1.0, n_ref) * params.flicker_offset
    ref_phase = rng.uniform(0.0, 2.0 * np.pi, n_ref)
    hot, dead, stuck, stuck_value = _defects(rng, params, camera.image_size)
    return CameraLab(shift=shift, roll=roll, rotation=rot, homography=hom, gain=gain, offset=offset, phase=phase,
                     ref_gain=ref_gain, ref_offset=ref_offset, ref_phase=ref_phase, hot=hot, dead=dead,
                     stuck=stuck, stuck_value=stuck_value)


def row_gain(height: int, *, gain: float, phase: float, banding: float, frequency: float,
             line_time: float) -> np.ndarray:
    """Lamp gain of every image row, shape (H,): ``gain (1 + banding sin(2 pi f v line_time + phase))``."""
    v = np.arange(height, dtype=np.float64)
    return gain * (1.0 + banding * np.sin(2.0 * np.pi * frequency * v * line_time + phase))


def vignette(camera: Camera, strength: float) -> np.ndarray:
    """Radial gain ``1 - strength (r / r_corner)^2`` about the principal point, shape (H, W)."""
    W, H = camera.image_size
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    u = np.arange(W) - cx
    v = np.arange(H) - cy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    corner = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0, W - 1) for y in (0, H - 1))
    return 1.0 - strength * r2 / corner


def defocus(image: np.ndarray, sigma: float) -> np.ndarray:
    """The image blurred by a Gaussian of ``sigma`` pixels (edges extended); 0 returns it unchanged."""
    if sigma <= 0:
        return image
    return ndimage.gaussian_filter(image, sigma, mode="nearest")


def photometry(image: np.ndarray, params: LabParams, camera: Camera, *, gain: float, offset: float,
               phase: float, vignetting: np.ndarray | None = None) -> np.ndarray:
    """Defocus, vignetting, the lamp's gain and banding, and the offset, in that order (a new array).

    ``image`` is the noise-free render (grey levels, 8-bit scale); ``vignetting`` a
    precomputed :func:`vignette` map (computed here when None and ``params.vignetting`` > 0).
    """
    out = defocus(np.asarray(image, dtype=np.float64), params.defocus)
    if params.vignetting > 0:
        out = out * (vignette(camera, params.vignetting) if vignetting is None else vignetting)
    rows = row_gain(out.shape[0], gain=gain, phase=phase, banding=params.banding,
                    frequency=params.banding_frequency, line_time=camera.line_time)
    return out * rows[:, None] + offset


def apply_defects(frame: np.ndarray, lab: CameraLab) -> np.ndarray:
    """The digitised frame with the defective pixels set (hot: full scale, dead: 0, stuck:
    their value scaled to the frame's bit depth); a new array."""
    out = frame.copy()
    top = np.iinfo(frame.dtype).max
    out[lab.hot[:, 0], lab.hot[:, 1]] = top
    out[lab.dead[:, 0], lab.dead[:, 1]] = 0
    out[lab.stuck[:, 0], lab.stuck[:, 1]] = np.rint(lab.stuck_value * (top / 255.0)).astype(frame.dtype)
    return out
