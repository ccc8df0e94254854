"""Synthesise a capture session with its ground truth (``schlieren synth``).

Glue only: the physics is in :mod:`schlieren.pipeline.synthetic`, the files in
:mod:`schlieren.storage.synthetic_io`. Frames are rendered frame by frame (all cameras of
one raw frame share the phantom's time knots) and streamed to disk, so memory stays
bounded by one frame's knots plus the reference images.

Timeline (``docs/design.md``): camera ``c`` has a hidden offset ``off_c`` chosen so that
the strobe flash at session time 0 lights a band of rows in raw frame 1 (and possibly the
bottom rows of frame 0); the manifest's ``frames`` are ``[4, 4 + N)`` so processed
frames never carry the flash and the two raw frames before them (2, 3) that a temporal
resampler may load are clean too; two extra raw frames are rendered after the range.
Output instant ``k`` is ``time[k] = (4 + k) / frame_rate + mean(off) + 0.5 * H * line_time``.
"""

from __future__ import annotations

import dataclasses
import logging
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid, Medium
from schlieren.pipeline.synthetic import render as R
from schlieren.pipeline.synthetic import lab as L
from schlieren.pipeline.synthetic.background import Texture, make_background, make_texture_background, wavelet_noise_tile
from schlieren.pipeline.synthetic.phantoms import make_phantom
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.synthetic.tracer import active_box, field_stack
from schlieren.storage import synthetic_io as sio

__all__ = ["SynthResult", "synthesize", "FIRST_FRAME", "FLASH_FRAME", "DISTORTION", "LAB_STREAM"]

log = logging.getLogger(__name__)

FLASH_FRAME = 1
FIRST_FRAME = 4
TAIL_FRAMES = 2   # raw frames rendered after the processed range (rolling-shutter resampling margin)
DEFAULT_BOX = ((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3))
#: Lens distortion of ``distortion=True`` (OpenCV k1 k2 p1 p2 k3).
DISTORTION = (-0.05, 0.02, 0.0005, -0.0003, 0.0)
#: The lab effects draw from their own generator, ``default_rng((seed, LAB_STREAM))``, so
#: the main generator's sequence (offsets, sensor noise) is the same with and without them:
#: a case's clean and lab captures share their sensor noise.
LAB_STREAM = 33


@dataclass
class SynthResult:
    """What :func:`synthesize` wrote.

    Attributes
    ----------
    session : Path
        ``session.yaml``.
    truth : Path
        ``truth.zarr``.
    time_offsets : ndarray (camera,)
        The hidden per-camera offsets (seconds).
    times : ndarray (frame,)
        Output instants of the processed frames.
    frames : (int, int)
        Processed raw-frame range.
    timings : dict
        Seconds spent per phase.
    """

    session: Path
    truth: Path
    time_offsets: np.ndarray
    times: np.ndarray
    frames: tuple[int, int]
    timings: dict = field(default_factory=dict)


class _KnotFields:
    """Field stacks of the phantom's knots, cached across consecutive frames."""

    def __init__(self, phantom, grid: Grid):
        self.phantom = phantom
        self.grid = grid
        self._cache: dict[int, np.ndarray] = {}

    def get(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        idx = self.phantom.knots_covering(t0, t1)
        for k in [k for k in self._cache if k not in set(idx.tolist())]:
            del self._cache[k]
        for k in idx:
            if k not in self._cache:
                self._cache[int(k)] = field_stack([self.phantom.knot_refractivity(int(k))], self.grid)[0]
        return np.stack([self._cache[int(k)] for k in idx]), self.phantom.knot_times[idx]


# over 80 lines only by its numpydoc parameters: the steps are the functions below it
def synthesize(out_dir, *, cameras: int = 16, ring: str = "half", phantom: str = "plume", frames: int = 8,
               size: tuple[int, int] = (1440, 1080), flow_factor: int = 3, seed: int = 0, noise: float = 1.5,
               bit_depth: int = 8, video: bool = False, strobe: bool = True, distortion: bool = False,
               voxel_size: float | None = None, recon_voxel: float = 0.0025, frame_rate: float = 60.0,
               line_time: float = 1.54e-5, box=DEFAULT_BOX, radius: float = 2.5,
               background_distance: float = 2.5, height_jitter: float = 0.0, supersample: int = 3,
               exposure: float = 1.0 / 120.0, medium: Medium = Medium(), knot_dt: float | None = None,
               step: float | None = None, name: str | None = None, video_codec: str = "ffv1",
               video_bits_per_pixel: float = 0.16, reference_frames: int = 0,
               manifest_voxel: bool = True, lab: L.LabParams | None = None,
               texture: Texture | None = None) -> SynthResult:
    """Render a synthetic session and its ground truth into ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Receives ``session.yaml``, ``camNN/frames/%05d.png`` (or ``camNN/capture.mkv``),
        ``camNN/reference.png`` and ``truth.zarr``.
    cameras, ring :
        Rig (see :func:`schlieren.pipeline.synthetic.rig.make_rig`).
    phantom : {"plume", "tealights", "blob"} or callable
        A phantom by name, or a factory ``phantom(fine_grid, *, t_start, duration, seed,
        medium, knot_dt) -> Phantom`` (e.g. a CFD simulation); the truth is stored on the
        returned phantom's own grid.
    frames : int
        Frames to process (N); ``FIRST_FRAME + N + TAIL_FRAMES`` raw frames are rendered.
    size : (int, int)
        Image ``(width, height)``.
    flow_factor : int
        Flow-grid downsampling factor of the truth deflections (also the trace lattice stride).
    seed : int
    noise : float
        Sensor noise (8-bit grey levels).
    bit_depth : {8, 16}
    video : bool
        Encode each camera as a video instead of PNG frames (8-bit only).
    video_codec : {"ffv1", "h264"}
        Lossless FFV1 (default) or lossy H.264 at ``video_bits_per_pixel`` bits per pixel
        and frame (camcorder-like: 0.16, :class:`~schlieren.storage.synthetic_io.VideoSink`).
    manifest_voxel : bool
        Write ``recon_voxel`` as the manifest's ``volume.voxel_size``; False leaves it out,
        so the pipeline chooses the voxel from the cameras' pixel footprint.
    reference_frames : int
        0: one noise-free reference image per camera. ``N > 0``: ``N`` reference frames
        (no flow) with the same sensor noise as the capture, as a PNG sequence, or in
        video mode a video with the capture's codec; the pipeline averages them, as a
        lab would record its reference.
    strobe : bool
        Flash in raw frame 1 and ``sync.strobe`` in the manifest (offsets hidden); False
        writes each camera's ``time_offset`` instead and renders no flash.
    distortion : bool
        Mild radial/tangential lens distortion on every camera.
    voxel_size : float, optional
        Phantom (truth) voxel size in metres; default ``recon_voxel / 2``.
    recon_voxel : float
        The manifest's reconstruction voxel size (metres).
    frame_rate, line_time, exposure :
        Camera timing (seconds); ``exposure`` is used for the flash band.
    box : ((x, y, z), (x, y, z))
        Volume corners (metres).
    supersample : int
        Sub-positions per pixel side.
    knot_dt : float, optional
        Phantom time-knot spacing; default ``1 / (4 frame_rate)``.
    step : float, optional
        RK4 step (metres); default the phantom voxel size.
    lab : LabParams, optional
        What a lab records beyond the ideal capture (:mod:`schlieren.pipeline.synthetic.lab`:
        camera motion against the reference, lamp flicker and banding, defocus, vignetting,
        sensor defects); what was drawn is written to ``lab.json`` beside ``truth.zarr``
        (:func:`schlieren.storage.synthetic_io.read_lab_truth`). The truth's deflections are
        the flow's alone, on the calibrated (reference) pose.
    texture : Texture, optional
        The background pattern and its scale; default Wavelet Noise with its finest
        spacing 1.5 camera pixels.
    """
    t_all = _time.perf_counter()
    timings: dict[str, float] = {}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    W, H = int(size[0]), int(size[1])
    if bit_depth not in (8, 16):
        raise ValueError("bit_depth must be 8 or 16")
    if video and bit_depth != 8:
        raise ValueError("video output is 8-bit only")
    if H * line_time > 1.0 / frame_rate:
        raise ValueError("H * line_time exceeds the frame period")
    opt = _Options(cameras=cameras, ring=ring, frames=frames, W=W, H=H, flow_factor=flow_factor, seed=seed,
                   noise=noise, bit_depth=bit_depth, video=video, video_codec=video_codec,
                   video_bits_per_pixel=video_bits_per_pixel, reference_frames=reference_frames, strobe=strobe,
                   supersample=supersample, exposure=exposure, frame_rate=frame_rate, line_time=line_time,
                   step=step, medium=medium,
                   knot_dt=knot_dt if knot_dt is not None else 1.0 / (4.0 * frame_rate),
                   lab=lab if lab is not None and lab.active else None, texture=texture)
    rng = np.random.default_rng(seed)
    grid = Grid(box[0], box[1], recon_voxel)
    fine = Grid(box[0], box[1], voxel_size if voxel_size is not None else recon_voxel / 2.0)
    rig, offsets = _rig(opt, grid, rng, radius=radius, background_distance=background_distance,
                        height_jitter=height_jitter, distortion=distortion)
    A = FIRST_FRAME
    times = (A + np.arange(frames)) / frame_rate + offsets.mean() + 0.5 * H * line_time
    t0 = _time.perf_counter()
    ph, fine, phantom = _phantom(phantom, fine, opt, offsets)
    timings["phantom"] = _time.perf_counter() - t0
    tw = _write_truth_volumes(out / "truth.zarr", opt, ph, fine, grid, times, offsets, phantom)
    t0 = _time.perf_counter()
    cams = _backgrounds_and_references(out, opt, rig, rng, _lab_draws(opt, rig))
    timings["references"] = _time.perf_counter() - t0
    timings["frames_total"], timings["truth_traces"] = _render_frames(out, opt, cams, ph, fine, offsets, times,
                                                                      tw, rng)
    if opt.lab is not None:
        sio.write_lab_truth(out / "lab.json", _lab_record(opt, cams))
    files = {c.camera.name: c.files for c in cams}
    session = sio.write_manifest(out, name=name or f"synthetic-{phantom}-{cameras}{ring}", frame_rate=frame_rate,
                                 frames=(A, A + frames), grid=grid, medium=medium, cameras=rig, camera_files=files,
                                 strobe_search=(0, A) if strobe else None, voxel_size=manifest_voxel)
    timings["total"] = _time.perf_counter() - t_all
    return SynthResult(session=session, truth=out / "truth.zarr", time_offsets=offsets, times=times,
                       frames=(A, A + frames), timings=timings)


@dataclass(frozen=True)
class _Options:
    """The settings of one :func:`synthesize` call that its steps share (its arguments;
    ``W, H`` the image size, ``knot_dt`` with its default applied)."""

    cameras: int
    ring: str
    frames: int
    W: int
    H: int
    flow_factor: int
    seed: int
    noise: float
    bit_depth: int
    video: bool
    video_codec: str
    video_bits_per_pixel: float
    reference_frames: int
    strobe: bool
    supersample: int
    exposure: float
    frame_rate: float
    line_time: float
    step: float | None
    medium: Medium
    knot_dt: float
    lab: L.LabParams | None = None
    texture: Texture | None = None

    @property
    def n_raw(self) -> int:
        """Raw frames rendered: the flash and resampling margin, the processed ones, the tail."""
        return FIRST_FRAME + self.frames + TAIL_FRAMES


def _rig(opt: _Options, grid: Grid, rng, *, radius, background_distance, height_jitter, distortion):
    """The cameras (:func:`~schlieren.pipeline.synthetic.rig.make_rig`) with their hidden
    time offsets, and the offsets: the flash (t = 0) lights rows ending near a random row
    ``r_edge`` in frame :data:`FLASH_FRAME`."""
    W, H = opt.W, opt.H
    dist = list(DISTORTION) if distortion else None
    rig = make_rig(opt.cameras, ring=opt.ring, grid=grid, radius=radius, image_size=(W, H),
                   background_distance=background_distance, height_jitter=height_jitter, distortion=dist,
                   line_time=opt.line_time, seed=opt.seed)
    r_edge = rng.uniform(0.25 * H, 0.75 * H, opt.cameras)
    offsets = -FLASH_FRAME / opt.frame_rate - r_edge * opt.line_time - rng.uniform(0.0, opt.line_time, opt.cameras)
    return [c.with_time_offset(o) for c, o in zip(rig, offsets)], offsets


def _phantom(phantom, fine: Grid, opt: _Options, offsets: np.ndarray):
    """``(phantom, truth grid, phantom name)``: the phantom by name or from its factory, with
    knots covering every row of every rendered frame (a knot spacing of slack each side)."""
    kdt = opt.knot_dt
    t_lo = offsets.min() - kdt
    t_hi = offsets.max() + (opt.n_raw - 1) / opt.frame_rate + opt.H * opt.line_time + kdt
    if callable(phantom):
        ph = phantom(fine, t_start=t_lo, duration=t_hi - t_lo, seed=opt.seed, medium=opt.medium, knot_dt=kdt)
        if ph.knot_times[0] > t_lo + 1e-9 or ph.knot_times[-1] < t_hi - 1e-9:
            raise ValueError(f"the phantom's knots [{ph.knot_times[0]:.4f}, {ph.knot_times[-1]:.4f}] s do not "
                             f"cover the capture [{t_lo:.4f}, {t_hi:.4f}] s")
        return ph, ph.grid, ph.name
    ph = make_phantom(phantom, fine, t_start=t_lo, duration=t_hi - t_lo, seed=opt.seed, medium=opt.medium,
                      knot_dt=kdt)
    return ph, fine, phantom


def _write_truth_volumes(truth_path: Path, opt: _Options, ph, fine: Grid, grid: Grid, times: np.ndarray,
                         offsets: np.ndarray, phantom_name: str) -> sio.TruthWriter:
    """Create ``truth.zarr`` and write its times, the knots spanning the processed instants
    (one frame period of slack each side) and the refractivity at each output instant; the
    per-camera truth is written while the frames are rendered."""
    A, frames = FIRST_FRAME, opt.frames
    store_knots = ph.knots_covering(times[0] - 1.0 / opt.frame_rate, times[-1] + 1.0 / opt.frame_rate)
    attrs = {"phantom": phantom_name, "cameras": opt.cameras, "ring": opt.ring, "frames": [A, A + frames],
             "frame_rate": opt.frame_rate, "line_time": opt.line_time, "image_size": [opt.W, opt.H],
             "flow_factor": opt.flow_factor, "seed": opt.seed, "noise": opt.noise, "bit_depth": opt.bit_depth,
             "strobe": opt.strobe, "supersample": opt.supersample, "exposure": opt.exposure,
             "knot_dt": opt.knot_dt, "voxel_size": fine.voxel_size,
             "video": (opt.video_codec if opt.video else None), "reference_frames": opt.reference_frames,
             **({"lab": dataclasses.asdict(opt.lab)} if opt.lab is not None else {}),
             **({"texture": dataclasses.asdict(opt.texture)} if opt.texture is not None else {}),
             "r_ambient": opt.medium.refractivity_ambient,
             "volume": {"min": list(grid.vmin), "max": list(grid.vmax), "voxel_size": grid.voxel_size},
             "time_note": "time[k] = (A + k)/frame_rate + mean(time_offset) + 0.5*H*line_time; "
                          "the phantom is linear in time between knot_time samples"}
    tw = sio.TruthWriter(truth_path, grid=fine, n_frames=frames, n_knots=len(store_knots), n_cameras=opt.cameras,
                         flow_shape=FlowGrid((opt.W, opt.H), opt.flow_factor).shape, attrs=attrs)
    tw.write_times(times, ph.knot_times[store_knots], offsets)
    for j, k in enumerate(store_knots):
        tw.write_knot(j, ph.knot_refractivity(int(k)))
    for k, t in enumerate(times):
        tw.write_refractivity(k, ph.refractivity(float(t)))
    return tw


@dataclass
class _CameraOutput:
    """One camera's background, noise-free reference image and capture output, and its
    drawn lab effects (with the vignetting map they share)."""

    camera: Camera
    background: object  # the background pattern (make_background)
    reference: np.ndarray
    files: tuple  # the manifest's (frames, reference) entries
    sink: sio.VideoSink | None = None  # the capture video (video mode)
    lab: L.CameraLab | None = None
    vignette: np.ndarray | None = None


def _lab_draws(opt: _Options, rig) -> list[L.CameraLab | None]:
    """Every camera's lab effects (:func:`~schlieren.pipeline.synthetic.lab.draw_camera`),
    from the generator of :data:`LAB_STREAM`; Nones without ``opt.lab``."""
    if opt.lab is None:
        return [None] * len(rig)
    lab_rng = np.random.default_rng((opt.seed, LAB_STREAM))
    lamp_phase = float(lab_rng.uniform(0.0, 2.0 * np.pi))
    return [L.draw_camera(opt.lab, cam, lab_rng, n_raw=opt.n_raw, n_ref=opt.reference_frames,
                          frame_rate=opt.frame_rate, lamp_phase=lamp_phase) for cam in rig]


def _background(opt: _Options, cam: Camera, i: int, tile: np.ndarray):
    """Camera ``i``'s background pattern: Wavelet Noise 1.5 pixels fine by default, else ``opt.texture``."""
    zbg = float(np.linalg.norm(cam.center - cam.bg_point))
    if opt.texture is None:
        return make_background(cam.bg_point, cam.bg_normal, spacing=1.5 * zbg / cam.K[0, 0], tile=tile,
                               seed=opt.seed * 1000 + i + 1)
    return make_texture_background(cam.bg_point, cam.bg_normal, opt.texture, pixel_footprint=zbg / cam.K[0, 0],
                                   tile=tile, seed=opt.seed * 1000 + i + 1)


def _backgrounds_and_references(out: Path, opt: _Options, rig, rng, labs) -> list[_CameraOutput]:
    """Every camera's background pattern and reference image, the reference written (one
    noise-free image, or ``reference_frames`` noisy frames or a video of them), and in video
    mode the capture video opened."""
    W, H = opt.W, opt.H
    tile = wavelet_noise_tile(256, seed=opt.seed)
    cams = []
    for i, (cam, lab) in enumerate(zip(rig, labs)):
        bg = _background(opt, cam, i, tile)
        ref = R.reference_image(cam, bg, supersample=opt.supersample, stride=opt.flow_factor)
        vig = L.vignette(cam, opt.lab.vignetting) if lab is not None and opt.lab.vignetting > 0 else None
        co = _CameraOutput(cam, bg, ref, (), lab=lab, vignette=vig)
        rel_ref = _write_reference(out, opt, co, rng)
        if opt.video:
            co.sink = sio.VideoSink(out, cam.name, opt.frame_rate, (W, H), codec=opt.video_codec,
                                    bits_per_pixel=opt.video_bits_per_pixel)
            co.files = (co.sink.rel, rel_ref)
        else:
            co.files = (sio.frame_pattern(cam.name), rel_ref)
        cams.append(co)
    return cams


def _lab_frame(opt: _Options, cam: _CameraOutput, image: np.ndarray, *, rng, noise: float, gain: float = 1.0,
               offset: float = 0.0, phase: float = 0.0, lit: np.ndarray | None = None) -> np.ndarray:
    """A noise-free render through the camera's lab photometry (defocus, vignetting, lamp),
    the flash on the ``lit`` rows, the sensor, and the camera's defective pixels."""
    if cam.lab is not None:
        image = L.photometry(image, opt.lab, cam.camera, gain=gain, offset=offset, phase=phase,
                             vignetting=cam.vignette)
    if lit is not None and lit.any():
        image = R.apply_flash(image, lit, R.RenderParams().flash_gain)
    frame = R.sensor(image, noise=noise, bit_depth=opt.bit_depth, rng=rng)
    return frame if cam.lab is None else L.apply_defects(frame, cam.lab)


def _write_reference(out: Path, opt: _Options, cam: _CameraOutput, rng) -> str:
    """Write the camera's reference recording; its path relative to ``out``. With lab effects
    each reference frame has its own lamp gain, offset and banding phase; a single noise-free
    reference (``reference_frames`` 0) is the ideal average: no flicker, no banding."""
    name, ref, lab = cam.camera.name, cam.reference, cam.lab
    if opt.reference_frames <= 0:
        if lab is not None:
            img = L.photometry(ref, dataclasses.replace(opt.lab, banding=0.0), cam.camera, gain=1.0, offset=0.0,
                               phase=0.0, vignetting=cam.vignette)
            return sio.write_reference(out, name, L.apply_defects(
                R.sensor(img, noise=0.0, bit_depth=opt.bit_depth, rng=rng), lab))
        return sio.write_reference(out, name, R.sensor(ref, noise=0.0, bit_depth=opt.bit_depth, rng=rng))

    def frames():
        for r in range(opt.reference_frames):
            yield _lab_frame(opt, cam, ref, rng=rng, noise=opt.noise, **({} if lab is None else dict(
                gain=lab.ref_gain[r], offset=lab.ref_offset[r], phase=lab.ref_phase[r])))

    if opt.video:
        sink = sio.VideoSink(out, name, opt.frame_rate, (opt.W, opt.H), codec=opt.video_codec,
                             bits_per_pixel=opt.video_bits_per_pixel, name="reference")
        for img in frames():
            sink.write(img)
        sink.close()
        return sink.rel
    return sio.write_reference_frames(out, name, frames())


def _render_frames(out: Path, opt: _Options, cams: list[_CameraOutput], ph, fine: Grid, offsets: np.ndarray,
                   times: np.ndarray, tw: sio.TruthWriter, rng) -> tuple[float, float]:
    """Render every raw frame of every camera and, at the processed instants, the truth
    traces; returns the seconds spent in all and in the truth traces."""
    fg = FlowGrid((opt.W, opt.H), opt.flow_factor)
    lattice = R.make_lattice((opt.W, opt.H), opt.flow_factor)
    knots = _KnotFields(ph, fine)
    t_render = 0.0
    t_truth = 0.0
    for f in range(opt.n_raw):
        t0 = _time.perf_counter()
        fields, kt = knots.get(offsets.min() + f / opt.frame_rate,
                               offsets.max() + f / opt.frame_rate + opt.H * opt.line_time)
        trace = dict(fields=fields, knot_times=kt, fine=fine, lattice=lattice,
                     clip_box=active_box(fields, fine, tol=1e-5))
        k = f - FIRST_FRAME
        for i, cam in enumerate(cams):
            dpx = _capture_frame(out, opt, cam, f, rng, **trace)
            if 0 <= k < opt.frames:
                ts = _time.perf_counter()
                _truth_frame(opt, cam, i, k, float(times[k]), dpx, fg, tw, **trace)
                t_truth += _time.perf_counter() - ts
        t_render += _time.perf_counter() - t0
        log.info("synth: raw frame %d/%d done", f + 1, opt.n_raw)
    for c in cams:
        if c.sink is not None:
            c.sink.close()
    return t_render, t_truth


def _capture_frame(out: Path, opt: _Options, cam: _CameraOutput, f: int, rng, *, fields, knot_times, fine,
                   lattice, clip_box) -> np.ndarray:
    """Render, flash, digitise and write raw frame ``f`` of one camera (rolling shutter:
    each row at its own time; with lab motion, from the camera's moved pose and every pixel
    rendered); returns its image-plane deflections (pixels)."""
    camera = cam.camera
    moved = cam.lab is not None and opt.lab.moves
    if moved:
        camera = L.moved_camera(cam.camera, cam.lab.rotation[f])
    tr = R.trace_lattice(camera, lattice, fields, knot_times, fine, frame=f, frame_rate=opt.frame_rate,
                         step=opt.step, n_ambient=opt.medium.n_ambient, clip_box=clip_box)
    if moved:
        img, dpx = R.render_frame(camera, cam.background, tr, lattice, supersample=opt.supersample)
    else:
        img, dpx = R.render_image(camera, cam.background, tr, lattice, cam.reference, supersample=opt.supersample)
    lit = R.flash_rows(cam.camera, f, frame_rate=opt.frame_rate, exposure=opt.exposure) if opt.strobe else None
    lamp = {} if cam.lab is None else dict(gain=cam.lab.gain[f], offset=cam.lab.offset[f], phase=cam.lab.phase[f])
    frame_img = _lab_frame(opt, cam, img, rng=rng, noise=opt.noise, lit=lit, **lamp)
    if cam.sink is not None:
        cam.sink.write(frame_img)
    else:
        sio.write_frame(out, cam.camera.name, f, frame_img)
    return dpx


def _lab_record(opt: _Options, cams: list[_CameraOutput]) -> dict:
    """The drawn lab effects as JSON-able lists, per camera (``lab.json``, see
    :func:`schlieren.storage.synthetic_io.write_lab_truth`)."""
    per = {}
    for c in cams:
        lab = c.lab
        per[c.camera.name] = {k: np.asarray(getattr(lab, k)).tolist() for k in (
            "shift", "roll", "homography", "gain", "offset", "phase", "ref_gain", "ref_offset", "ref_phase", "hot",
            "dead", "stuck", "stuck_value")}
    return {"params": dataclasses.asdict(opt.lab), "raw_frames": opt.n_raw, "reference_frames": opt.reference_frames,
            "frame_rate": opt.frame_rate, "line_time": opt.line_time, "bit_depth": opt.bit_depth, "cameras": per}


def _truth_frame(opt: _Options, cam: _CameraOutput, i: int, k: int, t: float, dpx: np.ndarray, fg: FlowGrid,
                 tw: sio.TruthWriter, *, fields, knot_times, fine, lattice, clip_box) -> None:
    """Camera ``i``'s truth at output instant ``k`` (time ``t``, every row at once): ray
    directions in and out, the image-plane deflection, and the rolling-shutter frame's
    deflection ``dpx``, on the flow grid."""
    sl = (slice(R.MARGIN, R.MARGIN + fg.shape[0]), slice(R.MARGIN, R.MARGIN + fg.shape[1]))
    gs = R.trace_lattice(cam.camera, lattice, fields, knot_times, fine, frame=None, time=t,
                         frame_rate=opt.frame_rate, step=opt.step, n_ambient=opt.medium.n_ambient, clip_box=clip_box)
    _, dgs = R.render_image(cam.camera, cam.background, gs, lattice, cam.reference, supersample=opt.supersample)
    tw.write_camera_frame(i, k, d_in=gs.d_in[sl], d_out=gs.d_out[sl], deflection=R.cell_average(dgs, fg),
                          deflection_rs=R.cell_average(dpx, fg))
