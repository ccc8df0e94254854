"""``schlieren synth OUT_DIR``: a synthetic session with its ground truth.

The lab effects (:class:`~schlieren.pipeline.synthetic.lab.LabParams`) get one option
each, generated from the parameters' own units, bounds and meanings (one source of truth),
and ``--lab PRESET`` sets several at once; an option given explicitly overrides the preset.
"""

from __future__ import annotations

import dataclasses

from schlieren.workers.cli import CLIError
from schlieren.workers.commands._args import image_size, int_at_least, positive_int


_size = image_size(16)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("synth", help="write a synthetic session and its ground truth",
                              description="Render a synthetic BOS capture (paper sec. 6) and its ground truth.")
    p.add_argument("out_dir", metavar="OUT_DIR",
                   help="folder receiving session.yaml, the cameras' frames and references, and truth.zarr")
    p.add_argument("--cameras", type=int_at_least(2), default=16, metavar="N",
                   help="cameras on the ring around the volume (default 16)")
    p.add_argument("--ring", choices=["half", "full"], default="half",
                   help="cameras over half a circle (the paper's rig) or a full one (default half)")
    p.add_argument("--phantom", choices=["plume", "tealights", "blob"], default="plume",
                   help="the flow rendered: a rising buoyant plume, three tealight plumes or a static "
                        "Gaussian blob (default plume)")
    p.add_argument("--frames", type=positive_int, default=8, metavar="N",
                   help="frames to process (N); a flash and margin frames are rendered around them (default 8)")
    p.add_argument("--size", type=_size, default=(1440, 1080), metavar="WxH",
                   help="image size in pixels, WIDTHxHEIGHT (default 1440x1080)")
    p.add_argument("--flow-factor", type=int, default=3, metavar="N",
                   help="downsampling of the truth's deflections to the flow grid (default 3)")
    p.add_argument("--seed", type=int, default=0, help="random seed of rig jitter, background and noise (default 0)")
    p.add_argument("--noise", type=float, default=1.5, metavar="GREY",
                   help="sensor noise, standard deviation in 8-bit grey levels (default 1.5)")
    p.add_argument("--bit-depth", type=int, choices=[8, 16], default=8, help="bits per pixel of the frames (default 8)")
    p.add_argument("--video", action="store_true", help="lossless FFV1 video per camera instead of PNGs")
    p.add_argument("--no-strobe", action="store_true", help="write time_offset per camera instead of a flash")
    p.add_argument("--distortion", action="store_true", help="mild radial and tangential lens distortion on every "
                                                             "camera")
    p.add_argument("--voxel-size", type=float, default=None, metavar="M",
                   help="truth (phantom) voxel in metres (default: --recon-voxel / 2)")
    p.add_argument("--recon-voxel", type=float, default=0.0025, metavar="M",
                   help="the manifest's reconstruction voxel in metres (default 0.0025)")
    p.add_argument("--frame-rate", type=float, default=60.0, metavar="FPS",
                   help="frames per second of every camera (default 60)")
    p.add_argument("--line-time", type=float, default=1.54e-5, metavar="S",
                   help="rolling-shutter line time in seconds, 0 = global shutter (default 1.54e-5)")
    p.add_argument("--supersample", type=int, default=3, metavar="N",
                   help="sub-positions per pixel side when rendering (default 3)")
    p.add_argument("--height-jitter", type=float, default=0.0, metavar="M",
                   help="random camera height offsets, standard deviation in metres (default 0)")
    p.add_argument("--reference-frames", type=int_at_least(0), default=0,
                   help="noisy reference frames recorded per camera (averaged by the pipeline); 0 writes one "
                        "noise-free reference image (default 0)")
    p.add_argument("--texture", choices=["noise", "dots"], default="noise",
                   help="background: Wavelet Noise or a printed random dot pattern (default noise)")
    p.add_argument("--texture-scale", type=float, default=None, metavar="PX",
                   help="noise: the finest coefficient spacing; dots: the dot pitch; camera pixels at the "
                        "background (default 1.5 for noise, 4 for dots)")
    _add_lab_options(p)
    p.add_argument("--background-only", action="store_true",
                   help="only write a printable background OUT_DIR/background.png (see --print-size, --dpi)")
    p.add_argument("--print-size", type=_size, default=(7016, 4961), metavar="WxH",
                   help="printer pixels of --background-only (default 7016x4961: A4 at 600 dpi)")
    p.add_argument("--dpi", type=float, default=600.0, help="printer resolution of --background-only (default 600)")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from pathlib import Path

    from rich.console import Console

    console = Console()
    if args.background_only:
        from schlieren.storage.synthetic_io import export_background

        if args.dpi <= 0:
            raise CLIError("--dpi must be positive")
        info = export_background(Path(args.out_dir) / "background.png", args.print_size[0], args.print_size[1],
                                 args.dpi, seed=args.seed)
        console.print(f"wrote {info['path']}: {info['width_mm']:.1f} x {info['height_mm']:.1f} mm at "
                      f"{info['dpi']:.0f} dpi")
        return 0
    if args.flow_factor < 1:
        raise CLIError("--flow-factor must be at least 1")
    if args.video and args.bit_depth != 8:
        raise CLIError("--video needs --bit-depth 8")
    if args.size[1] * args.line_time > 1.0 / args.frame_rate:
        raise CLIError("height * --line-time exceeds the frame period 1/--frame-rate")
    from schlieren.workers.synth import synthesize

    lab, texture = _lab(args), _texture(args)
    res = synthesize(args.out_dir, cameras=args.cameras, ring=args.ring, phantom=args.phantom, frames=args.frames,
                     size=args.size, flow_factor=args.flow_factor, seed=args.seed, noise=args.noise,
                     bit_depth=args.bit_depth, video=args.video, strobe=not args.no_strobe,
                     distortion=args.distortion, voxel_size=args.voxel_size, recon_voxel=args.recon_voxel,
                     frame_rate=args.frame_rate, line_time=args.line_time, supersample=args.supersample,
                     height_jitter=args.height_jitter, reference_frames=args.reference_frames, lab=lab,
                     texture=texture)
    if lab is not None and lab.active:
        console.print(f"lab effects: {', '.join(f'{k} {v:g}' for k, v in _set_fields(lab).items())} "
                      f"(drawn per camera-frame: {res.truth.parent / 'lab.json'})")
    console.print(f"session: {res.session}\ntruth:   {res.truth}\nframes {res.frames[0]}..{res.frames[1]}, "
                  f"{res.timings['total']:.1f} s")
    return 0


def _lab_fields():
    from schlieren.pipeline.params import schema
    from schlieren.pipeline.synthetic.lab import LabParams

    return schema(LabParams)


def _add_lab_options(p) -> None:
    """``--lab PRESET`` and one option per :class:`LabParams` field (its meaning, unit, default)."""
    from schlieren.pipeline.synthetic.lab import LAB_PRESETS

    g = p.add_argument_group("lab effects", "what a lab records beyond the ideal capture (every effect off by "
                                            "default); drawn per camera and frame from --seed and written to "
                                            "lab.json beside truth.zarr")
    g.add_argument("--lab", choices=sorted(LAB_PRESETS), default=None,
                   help="a preset: 'lab' = camera shaking against the reference (0.05 px random walk per frame "
                        "from a 0.1 px offset), lamp flicker 2 %% gain and 1 grey level per frame, background "
                        "0.7 px out of focus, 25 hot pixels per camera; 'lab-all' = every effect. Options below "
                        "override it (default: none, a clean capture)")
    for fs in _lab_fields():
        unit = f"{fs.unit}, " if fs.unit and fs.unit != "1" else ""
        kind = int if fs.types == ("int",) else float
        g.add_argument("--" + fs.name.replace("_", "-"), type=kind, default=None, metavar="N" if kind is int else "X",
                       help=f"{fs.meaning} ({unit}default {fs.default:g}; {fs.valid})".replace("%", "%%"))


def _set_fields(lab) -> dict:
    return {f.name: getattr(lab, f.name) for f in dataclasses.fields(lab)
            if getattr(lab, f.name) != f.default}


def _lab(args):
    """The :class:`LabParams` of ``--lab`` and the lab options (None when none is given), checked."""
    from schlieren.pipeline.params import ParamsError, validate
    from schlieren.pipeline.synthetic.lab import LAB_PRESETS, LabParams

    given = {fs.name: getattr(args, fs.name) for fs in _lab_fields() if getattr(args, fs.name) is not None}
    if args.lab is None and not given:
        return None
    base = dataclasses.asdict(LAB_PRESETS[args.lab]) if args.lab else {}
    try:
        return validate(LabParams, {**base, **given})
    except ParamsError as exc:
        flag = "--" + exc.field.replace("_", "-") if exc.field else "lab effects"
        raise CLIError(f"{flag}: {exc.message}") from None


def _texture(args):
    from schlieren.pipeline.synthetic.background import Texture

    if args.texture == "noise" and args.texture_scale is None:
        return None
    scale = args.texture_scale if args.texture_scale is not None else (1.5 if args.texture == "noise" else 4.0)
    if not scale > 0:
        raise CLIError("--texture-scale must be positive")
    return Texture(kind=args.texture, scale=scale)
