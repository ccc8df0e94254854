"""What a lab capture's defects cost, and what the capture corrections win back (issue 33).

    python benchmarks/capture_defects.py [--clean /work/realistic/plume1-16cam-640]
        [--work capture-defects-out] [--seed 0] [--runs clean,lab-off,lab,...]

Takes a rendered clean session of the realistic family (default: ``plume1-16cam-640``,
16 cameras at 640x480, 0.25 px deflections; ``schlieren bench realistic`` renders it) and
writes a *lab* copy of it with what a lab records, applied to the rendered frames after
the fact (:func:`perturb_session`):

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

Other sessions (:data:`SESSIONS`) keep one defect each, in focus (``motion``, ``flicker``,
``pixels``), or the defocus alone. The true motion, defective pixels and lamp are stored
beside each perturbed session (``motion_truth.json``, ``defects_truth.json``,
``lamp_truth.json``). Each run then
reconstructs a session with a configuration and is scored against the truth: whole box and
in-plume dB, the masks' and the hull's fill fractions, the motion the flow still shows on
the static cells (median over camera-frames), the stored motion against the true one
(RMS displacement error over the image), the defective pixels found, and the pipeline's
time; with the lamp drawn, the stored gain and offset profiles against the true ones.
``--score-lab STORE`` scores stores of captures rendered with lab effects (the family's
``-lab`` cases) against their ``lab.json`` the same way (:func:`score_lab_store`). Writes
``benchmarks/results/capture_defects.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CLEAN = Path("/work/realistic/plume1-16cam-640")


@dataclasses.dataclass(frozen=True)
class LabSpec:
    """The perturbations of :func:`perturb_session` (see the module docstring)."""

    motion_start: float = 0.1       # px
    motion_step: float = 0.05       # px per frame
    rotation_start: float = 1e-4    # rad
    rotation_step: float = 3e-5     # rad per frame
    defocus: float = 0.7            # px (Gaussian sigma)
    noise: float = 1.5              # grey levels after the blur
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


# ------------------------------------------------------------------------------ runs
#: The perturbed sessions (``None``: the clean one itself).
SESSIONS = {
    "clean": None,
    "lab": LabSpec(),
    "sharp": LabSpec(defocus=0.0),  # everything but the defocus (which no correction undoes)
    "defocus": LabSpec(motion=False, photometric=False, defects=False),  # the defocus alone
    # each correctable defect alone, in focus
    "motion": LabSpec(defocus=0.0, photometric=False, defects=False),
    "flicker": LabSpec(defocus=0.0, motion=False, defects=False),
    "pixels": LabSpec(defocus=0.0, motion=False, photometric=False),
}
_OFF = {"capture": {"motion_model": "none", "photometric": False, "defective_pixels": False}}
#: name -> (session, params, description)
RUNS = {
    "clean": ("clean", {}, "clean capture, defaults"),
    "clean-off": ("clean", _OFF, "clean capture, capture corrections off (today's pipeline)"),
    "lab-off": ("lab", _OFF, "lab capture, capture corrections off (today's pipeline)"),
    "lab": ("lab", {}, "lab capture, defaults (motion, photometric, defective pixels)"),
    "lab-motion-only": ("lab", {"capture": {"photometric": False, "defective_pixels": False}},
                        "lab capture, motion only"),
    "lab-no-motion": ("lab", {"capture": {"motion_model": "none"}},
                      "lab capture, photometric and defective pixels only"),
    "lab-background": ("lab", {"capture": {"motion_source": "background"}},
                       "lab capture, defaults but motion_source background (no resampling)"),
    "sharp-off": ("sharp", _OFF, "lab capture without defocus, corrections off"),
    "sharp": ("sharp", {}, "lab capture without defocus, defaults"),
    "defocus": ("defocus", {}, "clean capture with the defocus alone, defaults"),
    "motion": ("motion", {}, "camera motion alone, defaults"),
    "motion-off": ("motion", _OFF, "camera motion alone, corrections off"),
    "flicker": ("flicker", {}, "flicker and row banding alone, defaults"),
    "flicker-off": ("flicker", _OFF, "flicker and row banding alone, corrections off"),
    "pixels": ("pixels", {}, "hot, dead and stuck pixels alone, defaults"),
    "pixels-off": ("pixels", _OFF, "hot, dead and stuck pixels alone, corrections off"),
}


def run_one(name: str, session: Path, truth: Path, store: Path, params: dict, *, motion_truth=None,
            defects_truth=None, lamp_truth=None, spec: LabSpec | None = None) -> dict:
    """Reconstruct ``session`` serially with ``params`` and score it."""
    from schlieren.pipeline.stages import config_from_dict
    from schlieren.storage import bench_io
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.run import run_session

    bench_io.remove_tree(store)
    t0 = time.perf_counter()
    summary = run_session(session, store, serial=True, config=config_from_dict(params))
    seconds = time.perf_counter() - t0
    res = {"run": name, "describe": RUNS[name][2] if name in RUNS else name, "params": params,
           "pipeline_seconds": seconds,
           "cpu_seconds": {k: float(v) for k, v in (summary.stage_cpu_seconds or {}).items()}}
    if not summary.ok:
        res["failures"] = dict(summary.root_failures())
        return res
    ev = evaluate(store, truth)
    res.update(psnr=ev["overall"]["psnr"], psnr_plume=ev["plume"]["psnr"], warnings=list(summary.warnings))
    res.update(_store_metrics(store, session, motion_truth, defects_truth))
    if lamp_truth and spec is not None and spec.photometric:
        res.update(_photometric_errors(store, session, lamp_truth, spec))
    return res


def _store_metrics(store: Path, session: Path, motion_truth, defects_truth) -> dict:
    """Fill fractions, the motion left in the flow, the motion's error and the defects found."""
    from schlieren.pipeline import capture
    from schlieren.storage.session import load_session
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store, mode="r")
    sess = load_session(session)
    g = sess.grid
    a = st.attrs
    f = int(a["run"]["flow_factor"])
    raw_first, first = int(a["run"]["raw_first"]), int(a["run"]["frames"][0])
    n = int(a["run"]["n_frames"])
    flow_raw = np.asarray(st.array("flow_raw")[:])
    stored = np.asarray(st.array("background_motion")[:])
    left, err = [], []
    for c, cam in enumerate(sess.cameras):
        cells = capture.static_cells(capture.static_region(cam, g.vmin, g.vmax), f)
        for j in range(first - raw_first, first - raw_first + n):
            m, _ = capture.fit_flow_motion(flow_raw[c, j], cells, cam.image_size, f)
            left.append(capture.motion_extent(m, cam.image_size))
            if motion_truth and motion_truth.get(cam.name):
                true = np.asarray(motion_truth[cam.name][str(raw_first + j)])
                err.append(_displacement_rms(stored[c, j] - true, cam.image_size))
    out = {"mask_fill": float(np.mean(st.array("mask")[:])), "hull_fill": float(np.mean(st.array("hull")[:])),
           "motion_left_median": float(np.median(left))}
    if err:
        out["motion_error_rms"] = float(np.sqrt(np.mean(np.square(err))))
        out["motion_error_max"] = float(np.max(err))
    out["defects"] = _defects_found(np.asarray(st.array("defective_pixels")[:]), sess, defects_truth)
    return out


def _photometric_errors(store: Path, session: Path, lamp_truth: dict, spec: LabSpec) -> dict:
    """The stored gain and offset profiles (``photometric``) against the lamp drawn: RMS
    over knots and processed camera-frames of the gain's error, of the offset's error in
    grey levels, and of the true gain's departure from 1 (the size of what was removed)."""
    from schlieren.storage.session import load_session
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store, mode="r")
    sess = load_session(session)
    a = st.attrs
    raw_first, first, n = int(a["run"]["raw_first"]), int(a["run"]["frames"][0]), int(a["run"]["n_frames"])
    knots = np.asarray(st.array("row_knot")[:], np.float64)
    ph = np.asarray(st.array("photometric")[:], np.float64)
    dg, do, g0, o0 = [], [], [], []
    for c, cam in enumerate(sess.cameras):
        for j in range(first - raw_first, first - raw_first + n):
            gain, offset = true_photometric(lamp_truth[cam.name], spec, knots, raw_first + j)
            dg.append(ph[c, j, 0] - gain)
            do.append(ph[c, j, 1] - offset)
            g0.append(gain - 1.0)
            o0.append(offset)
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    return {"gain_error_rms": rms(dg), "offset_error_rms": rms(do), "gain_true_rms": rms(g0),
            "offset_true_rms": rms(o0)}


def _displacement_rms(dm: np.ndarray, image_size) -> float:
    """RMS over the image (every 8th pixel) of the displacement of motion vector ``dm``."""
    from schlieren.pipeline.capture import motion_displacement

    W, H = image_size
    y, x = np.mgrid[0:H:8, 0:W:8]
    dx, dy = motion_displacement(dm, x, y, image_size)
    return float(np.sqrt(np.mean(dx * dx + dy * dy)))


def _defects_found(found: np.ndarray, sess, truth) -> dict:
    total = int(np.count_nonzero(found))
    if truth is None:
        return {"flagged": total}
    hit = missed = 0
    for c, cam in enumerate(sess.cameras):
        t = truth[cam.name]
        ok = found[c, t["rows"], t["cols"]] != 0
        hit += int(np.count_nonzero(ok))
        missed += int(np.count_nonzero(~ok))
    return {"flagged": total, "found": hit, "missed": missed, "false": total - hit}


# ------------------------------------------------------------------------------ rendered lab captures
def score_lab_store(store: Path, session_dir: Path) -> dict:
    """A store of a capture rendered with lab effects (``schlieren synth --lab``, the family's
    ``-lab`` cases) against what its ``lab.json`` says was drawn: the stored motion's RMS
    displacement error over the image (and the true motion's RMS), the gain and offset
    profiles' RMS errors (and the true ones' departures), and the defective pixels found."""
    from schlieren.storage.session import load_session
    from schlieren.storage.store import ResultStore
    from schlieren.pipeline.capture import motion_displacement
    from schlieren.storage.synthetic_io import read_lab_truth

    lab = read_lab_truth(session_dir)
    st = ResultStore.open(store, mode="r")
    sess = load_session(session_dir / "session.yaml")
    a = st.attrs
    raw_first, first, n = int(a["run"]["raw_first"]), int(a["run"]["frames"][0]), int(a["run"]["n_frames"])
    motion = np.asarray(st.array("background_motion")[:], np.float64)
    ph = np.asarray(st.array("photometric")[:], np.float64)
    knots = np.asarray(st.array("row_knot")[:], np.float64)
    found = np.asarray(st.array("defective_pixels")[:])
    band, hz, line = float(lab["params"].get("banding", 0.0)), float(lab["params"].get("banding_frequency", 100.0)), \
        float(lab["line_time"])
    err, true, dg, do, g0, o0 = [], [], [], [], [], []
    hit = missed = 0
    for c, cam in enumerate(sess.cameras):
        t = lab["cameras"][cam.name]
        W, H = cam.image_size
        y, x = np.mgrid[0:H:8, 0:W:8].astype(np.float64)
        ref = {k: np.asarray(t["ref_" + k], np.float64) for k in ("gain", "offset", "phase")}
        G = np.mean(ref["gain"][:, None] * (1.0 + band * np.sin(2 * np.pi * hz * line * knots[None] +
                                                                 ref["phase"][:, None])), axis=0)
        O = float(np.mean(ref["offset"]))
        for j in range(first - raw_first, first - raw_first + n):
            r = raw_first + j
            Hi = np.linalg.inv(np.asarray(t["homography"][r], np.float64))  # frame pixel -> reference pixel
            den = Hi[2, 0] * x + Hi[2, 1] * y + Hi[2, 2]
            tx = (Hi[0, 0] * x + Hi[0, 1] * y + Hi[0, 2]) / den - x
            ty = (Hi[1, 0] * x + Hi[1, 1] * y + Hi[1, 2]) / den - y
            mx, my = motion_displacement(motion[c, j], x, y, cam.image_size)
            err.append(float(np.sqrt(np.mean((mx - tx) ** 2 + (my - ty) ** 2))))
            true.append(float(np.sqrt(np.mean(tx ** 2 + ty ** 2))))
            gain = t["gain"][r] * (1.0 + band * np.sin(2 * np.pi * hz * line * knots + t["phase"][r])) / G
            offset = t["offset"][r] - gain * O
            dg.append(ph[c, j, 0] - gain)
            do.append(ph[c, j, 1] - offset)
            g0.append(gain - 1.0)
            o0.append(offset)
        pix = [tuple(p) for k in ("hot", "dead", "stuck") for p in t.get(k, [])]
        if pix:
            rows, cols = np.asarray(pix).T
            ok = found[c, rows, cols] != 0
            hit += int(np.count_nonzero(ok))
            missed += int(np.count_nonzero(~ok))
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    total = int(np.count_nonzero(found))
    return {"motion_error_rms": rms(err), "motion_error_max": float(np.max(err)), "motion_true_rms": rms(true),
            "gain_error_rms": rms(dg), "offset_error_rms": rms(do), "gain_true_rms": rms(g0),
            "offset_true_rms": rms(o0), "defects": {"flagged": total, "found": hit, "missed": missed,
                                                    "false": total - hit}}


# ------------------------------------------------------------------------------ flow start
def flow_start_probe(clean: Path, *, camera: int = 0, frames=(4, 5, 6),
                     shifts=(0.1, 0.3, 0.5, 1.0, 2.0), theta: float = 2e-4) -> list[dict]:
    """Whether the flow should start from the motion (LK warps the reference by it in its
    own B-spline warp, without resampling it twice), only subtract it afterwards, or run on
    a reference resampled at the moved positions: one camera's frames moved by a known
    rigid motion, each way moved back onto the reference grid, their end-point error
    against the rendered truth (flow cells of 6 px, where the truth is)."""
    import functools

    import zarr

    from schlieren.pipeline import capture
    from schlieren.pipeline.flow import deflection_stage, prepare_reference
    from schlieren.pipeline.flow.splines import warp_image
    from schlieren.storage.frames import open_frames, read_reference
    from schlieren.storage.session import load_session
    from schlieren.pipeline.flow import window_for_voxel
    from schlieren.pipeline.geometry import pixel_footprint
    from schlieren.pipeline.stages import RunConfig, bind_flow_factor

    sess = load_session(clean / "session.yaml")
    cam, src = sess.cameras[camera], sess.sources[camera]
    flow = bind_flow_factor(RunConfig(), sess.cameras, sess.grid).flow
    grid = sess.grid  # the run's LK window (workers/tasks/deflection.py: flow_params)
    params = flow
    if flow.window_per_voxel > 0:
        px = grid.voxel_size / pixel_footprint(cam, grid.center)
        params = dataclasses.replace(flow, window=window_for_voxel(px, flow.window_per_voxel))
    f, size = params.factor, cam.image_size
    prep = prepare_reference(read_reference(src, camera_name=src.name), presmooth=params.presmooth, levels=params.levels)
    truth = zarr.open_group(str(clean / "truth.zarr"), mode="r")
    first = int(sess.frames[0])
    reader = open_frames(src, camera_name=src.name)

    def cells(d, k):  # block means onto cells of k flow cells
        h, w = d.shape[0] // k, d.shape[1] // k
        return d[:h * k, :w * k].reshape(h, k, w, k, -1).mean(axis=(1, 3))

    rows = []
    for s in (0.0,) + tuple(shifts):
        errs = {"subtract": [], "start": [], "warped": []}
        for fr in frames:
            t = cells(np.asarray(truth["deflection_rs"][camera, fr - first]), 6 // int(truth.attrs["flow_factor"]))
            img, m = rigid_motion(reader.read(fr).astype(np.float64), s, -0.6 * s, theta if s else 0.0)
            img = np.clip(np.round(img), 0, 255).astype(np.float32)
            field = functools.partial(capture.motion_displacement, m, image_size=size)
            start = deflection_stage(prep, img, params, motion=field)
            sub = deflection_stage(prep, img, params) - capture.motion_field(m, size, f)
            # the reference resampled at p + motion(p) (cubic B-spline), then the flow from zero
            yy, xx = np.mgrid[0:size[1], 0:size[0]].astype(np.float64)
            mx, my = field(xx, yy)
            ref_moved = warp_image(prep.image, np.dstack([mx, my]).astype(np.float32))
            warped = deflection_stage(prepare_reference(ref_moved, presmooth=params.presmooth, levels=params.levels), img, params)
            for key, d in (("start", start), ("subtract", sub), ("warped", warped)):
                d = capture.to_reference_grid(d, m, size, f)
                e = cells(d, 6 // f)[:t.shape[0], :t.shape[1]] - t
                errs[key].append(float(np.sqrt(np.nanmean(np.sum(e * e, axis=-1)))))
        rows.append({"shift": s, **{k: float(np.mean(v)) for k, v in errs.items()}})
    return rows


# ------------------------------------------------------------------------------ report
def markdown(result: dict) -> str:
    rows = result["runs"]
    lines = ["# Capture defects: clean vs lab vs lab with the capture corrections (issue 33)", "",
             f"Command: `python benchmarks/capture_defects.py {result['argv']}`. Clean session: "
             f"`{result['clean']}` (the realistic family's case, rendered by `schlieren bench realistic`); "
             "the lab session is the same capture with the perturbations of the benchmark's docstring "
             f"(seed {result['seed']}): {result['spec_text']}", "",
             "| run | whole box dB | in plume dB | mask fill | hull fill | motion left (median px) | "
             "motion error RMS px | gain error RMS (true) | offset error RMS grey (true) | "
             "defective pixels found / missed / false | pipeline s | deflection CPU s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        if "failures" in r:
            lines.append(f"| {r['describe']} | failed: {list(r['failures'].values())[:1]} | | | | | | | | | | |")
            continue
        d = r.get("defects", {})
        dtext = f"{d.get('found', '-')} / {d.get('missed', '-')} / {d.get('false', d.get('flagged', '-'))}"
        me = r.get("motion_error_rms")
        gtext, otext = "-", "-"
        if "gain_error_rms" in r:
            gtext = f"{r['gain_error_rms']:.4f} ({r['gain_true_rms']:.4f})"
            otext = f"{r['offset_error_rms']:.2f} ({r['offset_true_rms']:.2f})"
        lines.append(f"| {r['describe']} | {r['psnr']:.2f} | {r['psnr_plume']:.2f} | {r['mask_fill']:.3f} | "
                     f"{r['hull_fill']:.3f} | {r['motion_left_median']:.4f} | "
                     f"{'-' if me is None else f'{me:.4f}'} | {gtext} | {otext} | {dtext} | "
                     f"{r['pipeline_seconds']:.0f} | "
                     f"{r.get('cpu_seconds', {}).get('deflection', float('nan')):.1f} |")
    if result.get("lab_scores"):
        lines += ["", "## Captures rendered with lab effects", "",
                  "Stores of sessions rendered with lab effects (`schlieren synth --lab`, the family's `-lab` "
                  "cases), scored against the session's `lab.json`:", "",
                  "| store | motion error RMS px (max) | true motion RMS px | gain error RMS (true) | "
                  "offset error RMS grey (true) | defective pixels found / missed / false |",
                  "|---|---:|---:|---:|---:|---|"]
        for r in result["lab_scores"]:
            d = r["defects"]
            lines.append(f"| `{r['store']}` | {r['motion_error_rms']:.4f} ({r['motion_error_max']:.4f}) | "
                         f"{r['motion_true_rms']:.4f} | {r['gain_error_rms']:.4f} ({r['gain_true_rms']:.4f}) | "
                         f"{r['offset_error_rms']:.2f} ({r['offset_true_rms']:.2f}) | "
                         f"{d['found']} / {d['missed']} / {d['false']} |")
    if result.get("flow_start"):
        lines += ["", "## Start the flow from the motion, or subtract it afterwards", "",
                  f"One camera of the clean session (`{result['flow_start_camera']}`), its frames moved by a "
                  "known rigid motion (shift `s` along (1, -0.6) and a 2e-4 rad rotation; FFT shears), the true "
                  "motion removed either way and the result moved back onto the reference grid; end-point "
                  "error (px) against the rendered truth on 6 px cells, mean over the frames:", "",
                  "| shift s (px) | start from the motion | subtract afterwards | reference warped by the motion |",
                  "|---:|---:|---:|---:|"]
        lines += [f"| {r['shift']:.1f} | {r['start']:.4f} | {r['subtract']:.4f} | {r['warped']:.4f} |"
                  for r in result["flow_start"]]
    lines += ["", "* motion left: the largest displacement of the affine motion fitted (Tukey IRLS) to each "
              "camera-frame's stored `flow_raw` on the static cells, median over the processed camera-frames.",
              "* motion error: the stored `background_motion` against the true motion, RMS displacement over "
              "the image, RMS over the camera-frames (lab runs with motion estimated).",
              "* gain / offset error: the stored `photometric` profiles (gain, and offset in grey levels, at the "
              "row knots) against the lamp drawn, mapped onto the averaged reference (`true_photometric`), RMS over "
              "knots and processed camera-frames; in brackets the RMS of the true gain's departure from 1 and of "
              "the true offset: what there was to recover.",
              f"* Machine: {result['machine']}; timings are on a loaded machine (re-measure quiet)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--clean", type=Path, default=DEFAULT_CLEAN, help="a rendered clean session folder with truth.zarr")
    p.add_argument("--work", type=Path, default=Path("capture-defects-out"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs", default="clean,clean-off,lab,lab-off,sharp,defocus,lab-motion-only,lab-no-motion,"
                                     "lab-background")
    p.add_argument("--label", default="", help="results file suffix (capture_defects_LABEL.md)")
    p.add_argument("--score-lab", default="", metavar="STORE[,STORE...]",
                   help="also score stores of captures rendered with lab effects (the session is the store's folder, "
                        "its lab.json the truth)")
    p.add_argument("--flow-start", action="store_true", help="also measure starting the flow from the motion "
                                                              "against subtracting it (one camera)")
    args = p.parse_args(argv)
    results = []
    truths = {}
    for name in [r for r in args.runs.split(",") if r]:
        which, params, _ = RUNS[name]
        if which == "clean":
            src, truth = args.clean, (None, None, None)
        else:
            src = args.work / which
            if not (src / "motion_truth.json").exists():
                print(f"writing the {which} session {src}", file=sys.stderr)
                perturb_session(args.clean, src, SESSIONS[which], seed=args.seed)
            if which not in truths:
                lamp = src / "lamp_truth.json"
                truths[which] = (json.loads((src / "motion_truth.json").read_text()),
                                 json.loads((src / "defects_truth.json").read_text()),
                                 json.loads(lamp.read_text()) if lamp.exists() else None)
            truth = truths[which]
        print(f"{name}: running", file=sys.stderr)
        r = run_one(name, src / "session.yaml", src / "truth.zarr", args.work / f"store-{name}.zarr", params,
                    motion_truth=truth[0] or None, defects_truth=truth[1] or None, lamp_truth=truth[2],
                    spec=SESSIONS[which])
        print(f"{name}: {json.dumps({k: v for k, v in r.items() if k not in ('params', 'warnings')})}",
              file=sys.stderr)
        results.append(r)
    lab_scores = [dict(store=str(st), **score_lab_store(Path(st), Path(st).parent))
                  for st in args.score_lab.split(",") if st]
    load = os.getloadavg()[0]
    probe = flow_start_probe(args.clean) if args.flow_start else None
    spec = SESSIONS["lab"]
    result = {"flow_start": probe, "flow_start_camera": "cam00" if probe else None,
              "argv": " ".join(argv if argv is not None else sys.argv[1:]), "clean": str(args.clean),
              "seed": args.seed, "spec": dataclasses.asdict(spec),
              "spec_text": ", ".join(f"{k} {v}" for k, v in dataclasses.asdict(spec).items()),
              "machine": f"{os.cpu_count()} cores, 1-min load {load:.1f} at the end", "runs": results,
              "lab_scores": lab_scores}
    stem = "capture_defects" + (f"_{args.label}" if args.label else "")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2))
    (RESULTS / f"{stem}.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
