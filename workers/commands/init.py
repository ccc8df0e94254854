"""``schlieren init SESSION_DIR --videos 'cams/*.mp4' --calibration calibration.yaml ...``.

Writes ``SESSION_DIR/session.yaml`` (docs/session.md) from the cameras' videos or image
sequences and a calibration (from ``schlieren calibrate``, or imported: OpenCV
FileStorage YAML/XML, Kalibr camchain.yaml, the documented JSON; docs/calibration.md),
after checking every camera's frame count, size and frame rate (they must agree with
each other and with the calibration). Each camera's reference (no-flow background) is
frames A:B of its own frames (``--reference-frames``), extracted losslessly into
``<camera>/reference/`` and averaged by ``schlieren run``. Cameras are matched by name: a
video's file stem, an image sequence's folder (``cam00/frames/%05d.png`` -> cam00) or
``NAME=PATH`` must be a camera name of the calibration. The session is loaded back with
the session reader before it is written, and a failed init leaves nothing behind.
"""

from __future__ import annotations

import argparse
import logging

from schlieren.workers.commands._args import frame_range

log = logging.getLogger(__name__)


def _floats(text: str, n: int, flag: str) -> list[float]:
    from schlieren.workers.cli import CLIError

    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise CLIError(f"{flag} {text!r}: expected {n} comma-separated numbers")
    return vals


def _per_camera(items, flag: str, names):
    """``["0.0"]`` -> 0.0 for every camera; ``["cam0=0.0", "1e-3"]`` -> ``{name: value}``
    (the bare value for cameras not named); no items -> None."""
    from schlieren.workers.cli import CLIError

    if not items:
        return None
    default, named = None, {}
    for item in items:
        name, _, value = item.rpartition("=")
        try:
            v = float(value)
        except ValueError:
            raise CLIError(f"{flag} {item!r}: expected [NAME=]NUMBER") from None
        if name:
            named[name] = v
        else:
            default = v
    if not named:
        return default
    out = {n: default for n in names if default is not None}
    out.update(named)
    return out


def _per_camera_text(items, flag: str, names):
    """``["top_first"]`` -> for every camera; ``["cam0=bottom_first"]`` -> ``{name: value}``."""
    out = {}
    for item in items or []:
        name, _, value = item.rpartition("=")
        for n in ([name] if name else names):
            out[n] = value
    return out or None


def add_parser(sub) -> None:
    p = sub.add_parser("init", help="write a session.yaml from camera videos or image sequences and a "
                                    "calibration file",
                       description=__doc__.split("\n", 1)[1].strip().replace("``", ""),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("session_dir", metavar="SESSION_DIR", help="session folder (created if missing)")
    p.add_argument("--videos", nargs="+", action="extend", default=[], metavar="[NAME=]PATH", dest="videos",
                   help="each camera's video (or a quoted glob of videos, or a folder of videos; camera = file "
                        "stem), or a multi-page TIFF")
    p.add_argument("--images", nargs="+", action="extend", default=[], metavar="[NAME=]PATH", dest="videos",
                   help="each camera's image sequence: a printf pattern (cam00/frames/%%05d.png), a quoted glob "
                        "('cam00/*.tif') or a folder of images (camera = the folder's name; a folder named "
                        "frames or images gives its parent's). A file missing between numbered files is a "
                        "frame the camera dropped. --videos and --images take the same forms and may be mixed")
    p.add_argument("--calibration", nargs="+", required=True, metavar="[NAME=]FILE",
                   help="calibration.yaml from schlieren calibrate, a JSON file of the same form, Kalibr "
                        "camchain.yaml, or one OpenCV FileStorage YAML/XML per camera (camera = file stem)")
    p.add_argument("--interlaced", action="append", default=[], metavar="[NAME=]ORDER",
                   help="interlaced video (top_first or bottom_first): each field is processed as a frame "
                        "of its own at twice the frame rate, with its own row timing")
    p.add_argument("--reference-frames", required=True, metavar="A:B",
                   help="frames without flow, averaged into each camera's reference")
    p.add_argument("--volume", required=True, metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                   help="reconstruction box in world metres (z up); write --volume=-0.1,... when "
                        "it starts with a minus sign")
    p.add_argument("--voxel-size", type=float, default=None, metavar="M",
                   help="voxel edge, metres (default: none in session.yaml: the run chooses it from the cameras' "
                        "pixel footprint, 2 image pixels per voxel, docs/session.md)")
    p.add_argument("--frame-rate", type=float, default=None, metavar="FPS",
                   help="frames per second (default: the videos', which must agree)")
    p.add_argument("--frames", default=None, metavar="A:B", help="half-open range of frames to process")
    p.add_argument("--strobe-frames", default=None, metavar="A:B",
                   help="frames where every camera sees the sync flash (sync.strobe.search_frames); they may not "
                        "overlap --frames, which then defaults to the frames after them")
    p.add_argument("--time-offset", action="append", default=[], metavar="[NAME=]SECONDS",
                   help="camera time offsets instead of a strobe (one value for all, or per camera)")
    p.add_argument("--line-time", action="append", default=[], metavar="[NAME=]SECONDS",
                   help="rolling-shutter line time (default 0 = global shutter)")
    p.add_argument("--background-distance", action="append", default=[], metavar="[NAME=]METRES",
                   help="background distance for cameras whose calibration has no background plane")
    p.add_argument("--name", default=None, help="session name (default: the folder's name)")
    p.add_argument("--copy-videos", action="store_true",
                   help="copy the frames (video or image files) from outside SESSION_DIR into it")
    p.add_argument("--count-frames", action="store_true",
                   help="count frames by decoding every video (exact, slow) instead of trusting "
                        "the container")
    p.add_argument("--force", action="store_true", help="replace an existing session.yaml")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.storage.calibration_io import import_calibration
    from schlieren.storage.scaffold import find_sources, scaffold_session
    from schlieren.storage.session import load_session
    from schlieren.workers.cli import CLIError

    vol = _floats(args.volume, 6, "--volume")
    if not args.videos:
        raise CLIError("give each camera's frames: --videos or --images")
    if args.voxel_size is not None and args.voxel_size <= 0:
        raise CLIError("--voxel-size must be positive (metres)")
    videos = find_sources(args.videos, base=args.session_dir)
    names = list(videos)
    fields = _per_camera_text(args.interlaced, "--interlaced", names)
    path = scaffold_session(
        args.session_dir, videos, import_calibration(args.calibration), interlaced=fields,
        reference_frames=frame_range(args.reference_frames, "--reference-frames"),
        volume_min=vol[:3], volume_max=vol[3:], voxel_size=args.voxel_size,
        frame_rate=args.frame_rate,
        frames=frame_range(args.frames, "--frames") if args.frames else None,
        strobe_frames=frame_range(args.strobe_frames, "--strobe-frames") if args.strobe_frames else None,
        time_offsets=_per_camera(args.time_offset, "--time-offset", names),
        line_times=_per_camera(args.line_time, "--line-time", names),
        background_distance=_per_camera(args.background_distance, "--background-distance", names),
        name=args.name, copy_videos=args.copy_videos, count_frames=args.count_frames,
        overwrite=args.force)
    session = load_session(path)  # the reader `schlieren run` uses: fail here, not later
    voxel = "" if args.voxel_size is not None else \
        f" of {1e3 * session.grid.voxel_size:.2f} mm (chosen from the cameras' pixel footprint)"
    print(f"wrote {path}: {len(session.cameras)} cameras, {session.n_frames_available} frames at "
          f"{session.frame_rate:g} fps, frames {list(session.frames)} to process, grid "
          f"{' x '.join(str(s) for s in session.grid.shape[::-1])} voxels (x, y, z){voxel}")
    return 0
