"""Lab copies of a rendered clean session: what a lab records, applied to the rendered
frames after the fact (issue 33; :func:`perturb_session`).

* camera motion against the reference: per camera, a random walk of 0.05 px per frame
  from a 0.1 px start (random directions) and of 3e-5 rad per frame in rotation from
  1e-4 rad, applied by three shears of FFT line shifts (all-pass: no smoothing, unlike
  an interpolating warp);
* the background 0.7 px out of focus (a Gaussian blur of every frame and reference frame),
  with fresh sensor noise so that the noise stays at the clean capture's 1.5 grey levels;
* lamp flicker: per frame a gain of 1 + N(0, 2 %) and an offset of N(0, 1) grey levels,
  and row banding of a rolling shutter under 100 Hz light (a 1 % gain sinusoid in row time,
  15.4 us per row, random phase per frame), on the reference frames too;
* 25 defective pixels per camera: 15 hot (255), 5 dead (0), 5 stuck at a random grey
  level, in the reference frames and the frames.

:data:`SESSIONS` names the copies benchmarks/capture_defects.py reconstructs: all of it
(``lab``), all but the defocus (``sharp``), or one defect each (``defocus``, and in focus
``motion``, ``flicker``, ``pixels``), or, in focus, the sensor noise raised until the flow
noise is the defocus's (``noisy``: as ``schlieren check`` predicts it; ``noisier``: as the
runs measure it). The true motion, defective pixels and lamp are written
beside each copy (``motion_truth.json``, ``defects_truth.json``, ``lamp_truth.json``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

@dataclasses.dataclass(frozen=True)
class LabSpec:
    """The perturbations of :func:`perturb_session` (see the module docstring)."""

    motion_start: float = 0.1       # px
    motion_step: float = 0.05       # px per frame
    rotation_start: float = 1e-4    # rad
    rotation_step: float = 3e-5     # rad per frame
    defocus: float = 0.7            # px (Gaussian sigma)
    noise: float = 1.5              # grey levels after the blur
    extra_noise: float = 0.0        # grey levels of white noise added (in quadrature) on top
    gain: float = 0.02              # std of the per-frame gain
    offset: float = 1.0             # std of the per-frame offset, grey levels
    banding: float = 0.01           # amplitude of the row banding's gain
    mains_hz: float = 100.0         # flicker frequency of the light
    line_time: float = 1.54e-5      # s per row
    hot: int = 15
    dead: int = 5
    stuck: int = 5
    motion: bool = True
    photometric: bool = True
    defects: bool = True


# ------------------------------------------------------------------------------ perturbation
def _shift_lines(a: np.ndarray, shifts: np.ndarray, axis: int) -> np.ndarray:
    """``out[..., i] = a[..., i + s]`` along ``axis``, one sub-pixel shift per line, by the
    Fourier shift theorem (reflective padding against wrap-around)."""
    a = np.moveaxis(np.asarray(a, np.float64), axis, -1)
    n, pad = a.shape[-1], 32
    ap = np.concatenate([a[..., pad:0:-1], a, a[..., -2:-pad - 2:-1]], axis=-1)
    N = ap.shape[-1]
    k = np.fft.rfftfreq(N)
    s = np.asarray(shifts, np.float64)[:, None]
    out = np.fft.irfft(np.fft.rfft(ap, axis=-1) * np.exp(2j * np.pi * k * s), n=N, axis=-1)[..., pad:pad + n]
    return np.moveaxis(out, -1, axis)


def rigid_motion(img: np.ndarray, tx: float, ty: float, theta: float) -> tuple[np.ndarray, np.ndarray]:
    """``img`` seen by a camera that turned: ``out(p) = img(c + T(p - c))``, ``c`` the image
    centre, ``T(q) = R (q + t)`` with ``R`` a rotation by ``theta``, by three shears (x, y, x)
    of Fourier line shifts (Paeth's decomposition) and a final y shift. Returns the image
    and ``T``'s motion vector (:data:`schlieren.pipeline.capture.MOTION_PARAMS`)."""
    H, W = img.shape
    y = np.arange(H) - (H - 1) / 2.0
    x = np.arange(W) - (W - 1) / 2.0
    a, b = -np.tan(theta / 2.0), np.sin(theta)
    s = _shift_lines(img, a * y, axis=1)
    s = _shift_lines(s, b * x, axis=0)
    s = _shift_lines(s, a * y + tx, axis=1)
    s = _shift_lines(s, np.full(W, ty), axis=0)

    def T(qx, qy):
        px, py = qx + tx, qy + ty
        X = px + a * py
        return X + a * (py + b * X), py + b * X

    t0 = np.array(T(0.0, 0.0))
    ex, ey = np.array(T(1.0, 0.0)) - t0, np.array(T(0.0, 1.0)) - t0
    motion = np.array([t0[0], t0[1], ex[0] - 1.0, ey[0], ex[1], ey[1] - 1.0, 0.0, 0.0])
    return s, motion


def perturb_session(clean: Path, lab: Path, spec: LabSpec = LabSpec(), *, seed: int = 0) -> dict:
    """Write ``lab``: ``clean``'s session with the perturbations of ``spec`` (module docstring).

    Returns the true motion: ``{camera: {raw frame: motion vector}}`` (also written to
    ``lab/motion_truth.json``), the defective pixels (``lab/defects_truth.json``) and the
    lamp's gain, offset and banding phase per reference frame and frame
    (``lab/lamp_truth.json``).
    """
    from schlieren.storage.session import load_session

    sess = load_session(clean / "session.yaml")
    rng = np.random.default_rng(seed)
    if lab.exists():
        shutil.rmtree(lab)
    lab.mkdir(parents=True)
    shutil.copy(clean / "session.yaml", lab / "session.yaml")
    os.symlink((clean / "truth.zarr").resolve(), lab / "truth.zarr")
    motions, defects, lamps = {}, {}, {}
    for cam in sess.cameras:
        src_dir = clean / cam.name
        W, H = cam.image_size
        frames = sorted((src_dir / "frames").glob("*.png"))
        refs = sorted((src_dir / "reference").glob("*.png"))
        pix = _defect_pixels(rng, H, W, spec)
        defects[cam.name] = {k: v.tolist() for k, v in pix.items()}
        walk = _motion_walk(rng, len(frames), spec)
        cam_motion, cam_lamp = {}, {"reference": [], "frames": {}}
        for kind, files in (("reference", refs), ("frames", frames)):
            (lab / cam.name / kind).mkdir(parents=True)
            for i, path in enumerate(files):
                img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
                m = None
                if kind == "frames" and spec.motion:
                    img, m = rigid_motion(img, *walk[i])
                    cam_motion[i] = m.tolist()
                img, lamp = _optics_and_sensor(img, rng, spec, pix)
                if kind == "frames":
                    cam_lamp["frames"][i] = lamp
                else:
                    cam_lamp["reference"].append(lamp)
                cv2.imwrite(str(lab / cam.name / kind / path.name), img)
        motions[cam.name] = cam_motion
        lamps[cam.name] = cam_lamp
    (lab / "motion_truth.json").write_text(json.dumps(motions))
    (lab / "defects_truth.json").write_text(json.dumps(defects))
    (lab / "lamp_truth.json").write_text(json.dumps(lamps))
    return {"motion": motions, "defects": defects, "lamp": lamps}


def _motion_walk(rng, n: int, spec: LabSpec) -> list[tuple[float, float, float]]:
    """Per raw frame ``(tx, ty, theta)``: a random walk from a random start direction."""
    ang = rng.uniform(0, 2 * np.pi)
    t = spec.motion_start * np.array([np.cos(ang), np.sin(ang)])
    th = spec.rotation_start * rng.choice([-1.0, 1.0])
    out = []
    for _ in range(n):
        out.append((float(t[0]), float(t[1]), float(th)))
        a = rng.uniform(0, 2 * np.pi)
        t = t + spec.motion_step * np.array([np.cos(a), np.sin(a)])
        th = th + spec.rotation_step * rng.standard_normal()
    return out


def _defect_pixels(rng, H: int, W: int, spec: LabSpec) -> dict:
    n = spec.hot + spec.dead + spec.stuck if spec.defects else 0
    idx = rng.choice(H * W, size=n, replace=False)
    rows, cols = np.unravel_index(idx, (H, W))
    kinds = np.array(["hot"] * spec.hot + ["dead"] * spec.dead + ["stuck"] * spec.stuck)[:n]
    values = np.where(kinds == "hot", 255.0, np.where(kinds == "dead", 0.0, rng.uniform(40, 220, n)))
    return {"rows": rows, "cols": cols, "kinds": kinds, "values": values}


def _optics_and_sensor(img: np.ndarray, rng, spec: LabSpec, pix: dict) -> tuple[np.ndarray, dict]:
    """Defocus, fresh sensor noise, flicker and banding, defective pixels, 8-bit
    quantisation; returns the image and the lamp drawn (gain, offset, banding phase)."""
    H, W = img.shape
    if spec.defocus > 0:
        img = ndimage.gaussian_filter(img, spec.defocus, mode="reflect")
        # white noise through the blur keeps 1 / (2 sqrt(pi) sigma) of its deviation
        kept = spec.noise / (2.0 * np.sqrt(np.pi) * spec.defocus)
        img = img + rng.normal(0.0, np.sqrt(max(spec.noise ** 2 - kept ** 2, 0.0)), img.shape)
    if spec.extra_noise > 0:
        img = img + rng.normal(0.0, spec.extra_noise, img.shape)
    lamp = {"gain": 1.0, "offset": 0.0, "phase": 0.0}
    if spec.photometric:
        lamp["phase"] = float(rng.uniform(0, 2 * np.pi))
        lamp["gain"] = float(1.0 + spec.gain * rng.standard_normal())
        lamp["offset"] = float(spec.offset * rng.standard_normal())
        img = lamp["gain"] * _banding(spec, lamp["phase"], np.arange(H))[:, None] * img + lamp["offset"]
    if len(pix["rows"]):
        img[pix["rows"], pix["cols"]] = pix["values"]
    return np.clip(np.round(img), 0, 255).astype(np.uint8), lamp


def _banding(spec: LabSpec, phase: float, rows) -> np.ndarray:
    """The row banding's gain of a rolling shutter under ``spec.mains_hz`` light."""
    return 1.0 + spec.banding * np.sin(2 * np.pi * spec.mains_hz * spec.line_time * np.asarray(rows, float) + phase)


def true_photometric(lamp: dict, spec: LabSpec, knots: np.ndarray, raw_frame: int) -> tuple[np.ndarray, np.ndarray]:
    """The gain and offset profiles at ``knots`` that map one camera's averaged reference
    onto its frame ``raw_frame`` (:class:`schlieren.pipeline.capture.Photometric`): with
    reference frames ``g_r b_r(row) I + o_r`` averaged to ``G(row) I + O``, the frame
    ``g b(row) I + o`` is ``gain (ref - O) + o`` with ``gain = g b / G``."""
    refs = lamp["reference"]
    G = np.mean([r["gain"] * _banding(spec, r["phase"], knots) for r in refs], axis=0)
    O = float(np.mean([r["offset"] for r in refs]))
    f = lamp["frames"][str(raw_frame)]
    gain = f["gain"] * _banding(spec, f["phase"], knots) / G
    return gain, f["offset"] - gain * O


#: The perturbed sessions (``None``: the clean one itself).
SESSIONS = {
    "clean": None,
    "lab": LabSpec(),
    "sharp": LabSpec(defocus=0.0),  # everything but the defocus (which no correction undoes)
    "defocus": LabSpec(motion=False, photometric=False, defects=False),  # the defocus alone
    # in focus, the sensor noise raised until the flow noise is the defocus's (schlieren check's
    # predicted flow noise 0.0171 px against 0.0123 clean: 1.39 x the clean 1.53 grey levels)
    "noisy": LabSpec(defocus=0.0, motion=False, photometric=False, defects=False, extra_noise=1.48),
    # ... or until the flow noise measured outside the masks is the defocus run's (0.0161 px against
    # 0.0095 clean: 1.69 x)
    "noisier": LabSpec(defocus=0.0, motion=False, photometric=False, defects=False, extra_noise=2.09),
    # each correctable defect alone, in focus
    "motion": LabSpec(defocus=0.0, photometric=False, defects=False),
    "flicker": LabSpec(defocus=0.0, motion=False, defects=False),
    "pixels": LabSpec(defocus=0.0, motion=False, photometric=False),
}
