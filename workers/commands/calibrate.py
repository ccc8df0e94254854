"""``schlieren calibrate SOURCE... --squares 10x7 --square-size S --marker-size M --out FILE``.

Calibrates every camera of a rig from ChArUco board views (Zhang 1999, then a joint
bundle adjustment) and writes ``calibration.yaml`` (``format: schlieren-calibration/1``),
whose camera entries ``schlieren init`` copies into a session manifest.

How the command line is organised
---------------------------------
* One positional ``SOURCE`` per camera: a video file, a folder of images, or a quoted
  glob pattern of images, optionally prefixed ``NAME=``. Without a prefix the camera is
  named after the video's stem or the images' folder (``calib/cam00/*.png`` -> ``cam00``).
* View ``i`` of every camera is the same instant: frame ``i * --step`` of synchronised
  videos, or the ``i * --step``-th image (name order) of each folder. Hold the board
  still for a moment at each pose if the cameras are not genlocked. Views seen by
  several cameras link them; each camera also needs views of its own that fill its
  frame at varied tilts (for its intrinsics and distortion).
* World frame (SPEC: z up): the board pose in view ``--world-board-view`` (default 0).
  ``--world-board-orientation flat`` (default): lay the board face-up on a horizontal
  surface in the middle of the volume for that view; the origin is the centre of its
  chessboard area, x runs along its columns (the first number of ``--squares``), z points
  up out of the printed face. ``upright``: stand the board vertically, printed top edge
  up; x along its columns, z up along its rows, y into the board.
* Background planes: ``--background-board [NAME=]PATH`` (repeatable): images of a board
  stuck flat on that camera's background (move it between images to cover the area
  behind the volume); a plane is fitted through all its corners. Or
  ``--background-distance [NAME=]D``: the plane perpendicular to the optical axis, D
  metres in front of the camera (without NAME=: every camera without a board).
"""

from __future__ import annotations

import argparse
import logging
import os

log = logging.getLogger(__name__)


def parse_squares(text: str) -> tuple[int, int]:
    """``"10x7"`` -> ``(10, 7)`` (columns x rows of chessboard squares)."""
    from schlieren.workers.cli import CLIError

    try:
        a, b = text.lower().replace("*", "x").split("x")
        return int(a), int(b)
    except ValueError:
        raise CLIError(f"--squares {text!r}: expected COLUMNSxROWS, e.g. 10x7") from None


def _named_values(items, what: str) -> tuple[float | None, dict]:
    """``["3.5", "cam01=4.0"]`` -> ``(3.5, {"cam01": 4.0})``."""
    from schlieren.workers.cli import CLIError

    default, named = None, {}
    for item in items or []:
        name, _, value = item.rpartition("=")
        try:
            v = float(value)
        except ValueError:
            raise CLIError(f"{what} {item!r}: expected [NAME=]METRES") from None
        if v <= 0:
            raise CLIError(f"{what} {item!r}: the distance must be positive")
        if name:
            named[name] = v
        else:
            default = v
    return default, named


def detect_source(source, board, *, step: int = 1, max_views: int | None = None):
    """Board detections of one camera's views.

    Returns
    -------
    detections : list of BoardDetection
        Index = view.
    image_size : tuple of int
        ``(width, height)``.
    """
    from schlieren.pipeline.calibration import detect_board
    from schlieren.storage.calibration_io import iter_board_frames

    dets, size = [], None
    for view, img in iter_board_frames(source, step=step, max_views=max_views):
        size = (img.shape[1], img.shape[0])
        det = detect_board(img, board)
        while len(dets) < view:
            dets.append(None)
        dets.append(det)
    log.info("camera %s: board found in %d of %d views", source.name,
             sum(1 for d in dets if d is not None and len(d) >= 4), len(dets))
    return dets, size


def run_calibration(sources, board, params, *, step: int = 1, max_views: int | None = None,
                    background_boards=None, background_distance: float | None = None,
                    background_distances: dict | None = None):
    """Detect, calibrate the rig and estimate the background planes.

    Parameters
    ----------
    sources : list of BoardSource
        One per camera (names unique).
    board : BoardSpec
    params : CalibrationParams
    step, max_views : int
        See :func:`schlieren.storage.calibration_io.iter_board_frames`.
    background_boards : dict of str to BoardSource, optional
        Per camera, views of a board on its background.
    background_distance : float, optional
        Background distance (metres) for cameras without a board or a named distance.
    background_distances : dict of str to float, optional
        Per-camera background distances.

    Returns
    -------
    RigCalibration
        With ``background`` filled where known.

    Raises
    ------
    SchlierenInputError
        Naming the camera (and its files) when its board views cannot calibrate it.
    """
    from dataclasses import asdict, replace

    from schlieren.pipeline.calibration import CalibrationError, calibrate_rig
    from schlieren.storage.errors import SchlierenInputError

    by_name = _sources_by_name(sources, background_boards, background_distances)
    background_boards = dict(background_boards or {})
    background_distances = dict(background_distances or {})
    detections, sizes = {}, {}
    for s in sources:
        detections[s.name], sizes[s.name] = detect_source(s, board, step=step, max_views=max_views)
    try:
        rig = calibrate_rig(detections, sizes, board, **asdict(params))
    except CalibrationError as exc:
        src = by_name.get(exc.camera)
        raise SchlierenInputError(str(exc), file=src.label if src else None, camera=exc.camera) from None

    cams = []
    for cam in rig.cameras:
        bg = None
        if cam.name in background_boards:
            bg = _background_plane(cam, background_boards[cam.name], board, params)
        elif cam.name in background_distances:
            bg = {"distance": background_distances[cam.name]}
        elif background_distance is not None:
            bg = {"distance": float(background_distance)}
        cams.append(replace(cam, background=bg))
    return replace(rig, cameras=tuple(cams))


def _sources_by_name(sources, background_boards, background_distances) -> dict:
    """Camera name -> source; refuses two sources of one name and backgrounds of unknown cameras."""
    from schlieren.storage.errors import SchlierenInputError

    names = [s.name for s in sources]
    for n in names:
        if names.count(n) > 1:
            raise SchlierenInputError("two sources have the same camera name; prefix them with "
                                      "NAME= to tell them apart", camera=n)
    by_name = {s.name: s for s in sources}
    for n in list(background_boards or {}) + list(background_distances or {}):
        if n not in by_name:
            raise SchlierenInputError(f"background given for an unknown camera (cameras: "
                                      f"{', '.join(names)})", camera=n)
    return by_name


def _background_plane(cam, bsrc, board, params) -> dict:
    """The background plane of calibrated camera ``cam`` fitted through the corners of the
    board views ``bsrc`` (a board stuck on its background): ``{"point", "normal"}``."""
    from schlieren.pipeline.calibration import CalibrationError, background_plane, detect_board
    from schlieren.storage.calibration_io import iter_board_frames
    from schlieren.storage.errors import SchlierenInputError

    dets = []
    for _, img in iter_board_frames(bsrc):
        if (img.shape[1], img.shape[0]) != tuple(cam.image_size):
            raise SchlierenInputError(
                f"background image is {img.shape[1]}x{img.shape[0]} pixels but the camera's "
                f"board views are {cam.image_size[0]}x{cam.image_size[1]}",
                file=bsrc.label, camera=cam.name)
        dets.append(detect_board(img, board))
    try:
        plane = background_plane(dets, board, K=cam.K, dist=cam.dist, R=cam.R, t=cam.t,
                                 min_corners=params.min_corners, name=cam.name)
    except CalibrationError as exc:
        raise SchlierenInputError(str(exc), file=bsrc.label, camera=cam.name) from None
    return {"point": plane["point"], "normal": plane["normal"]}


def _report(rig, out: str) -> str:
    import numpy as np

    lines = [f"{'camera':<12} {'size':>10} {'views':>5} {'points':>6} {'fx':>9} {'fy':>9} "
             f"{'RMS px':>7}  {'centre (m)':<26} background"]
    for c in rig.cameras:
        C = c.center
        if c.background is None:
            bg = "(none: give --background-distance to init)"
        elif "distance" in c.background:
            bg = f"distance {c.background['distance']:.3f} m"
        else:
            p, n = np.asarray(c.background["point"]), np.asarray(c.background["normal"])
            bg = f"plane at {np.round(p, 3).tolist()}, normal {np.round(n, 3).tolist()}"
        lines.append(f"{c.name:<12} {c.image_size[0]:>4}x{c.image_size[1]:<5} {c.n_views:>5} {c.n_points:>6} "
                     f"{c.K[0, 0]:>9.2f} {c.K[1, 1]:>9.2f} {c.rms:>7.3f}  "
                     f"{'[%.3f, %.3f, %.3f]' % tuple(C):<26} {bg}")
    lines.append(f"overall RMS reprojection error {rig.rms:.3f} px; world = board in view "
                 f"{rig.world_board_view} ({rig.world_board_orientation}); written to {out}")
    return "\n".join(lines)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate", help="calibrate the cameras from ChArUco board images or videos",
        description=__doc__.split("\n", 1)[1].strip().replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sources", nargs="+", metavar="SOURCE",
                   help="per camera: [NAME=]video file, image folder or quoted glob pattern")
    p.add_argument("--board", default="charuco", choices=["charuco"], help="board type")
    p.add_argument("--squares", required=True, metavar="CxR", help="chessboard squares, e.g. 10x7")
    p.add_argument("--square-size", type=float, required=True, metavar="M", help="square edge, metres")
    p.add_argument("--marker-size", type=float, required=True, metavar="M", help="marker edge, metres")
    p.add_argument("--dictionary", default="DICT_5X5_100",
                   help="ArUco dictionary of the board (cv2.aruco name, default DICT_5X5_100)")
    p.add_argument("--legacy-pattern", action="store_true",
                   help="board printed by OpenCV < 4.6 (even number of rows)")
    p.add_argument("--out", required=True, help="calibration file to write (YAML)")
    p.add_argument("--step", type=int, default=1, metavar="N", help="use every N-th frame/image")
    p.add_argument("--max-views", type=int, default=None, metavar="N", help="use at most N views per camera")
    p.add_argument("--n-dist", type=int, default=5, choices=[0, 2, 4, 5, 8],
                   help="distortion coefficients to estimate (OpenCV order k1 k2 p1 p2 k3 ...)")
    p.add_argument("--min-corners", type=int, default=6, help="fewest corners for a view to count")
    p.add_argument("--min-views", type=int, default=4, help="fewest usable views per camera")
    p.add_argument("--world-board-view", type=int, default=0, metavar="VIEW",
                   help="view whose board pose defines the world frame (default 0)")
    p.add_argument("--world-board-orientation", default="flat", choices=["flat", "upright"],
                   help="flat: board lying face-up (z out of its face); upright: standing, top edge up")
    p.add_argument("--background-board", action="append", default=[], metavar="[NAME=]PATH",
                   help="images of a board on a camera's background (image, folder or glob); repeatable")
    p.add_argument("--background-distance", action="append", default=[], metavar="[NAME=]METRES",
                   help="background plane distance along the optical axis; repeatable")
    p.add_argument("--robust-scale", type=float, default=1.0, metavar="PX",
                   help="Huber scale of the bundle adjustment, pixels")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.pipeline.calibration import BoardSpec, CalibrationError, CalibrationParams
    from schlieren.storage.calibration_io import resolve_source, write_calibration
    from schlieren.workers.cli import CLIError

    squares = parse_squares(args.squares)
    try:
        board = BoardSpec(squares, args.square_size, args.marker_size, args.dictionary, args.legacy_pattern)
    except CalibrationError as exc:
        raise CLIError(f"board: {exc}") from None
    sources = [resolve_source(a) for a in args.sources]
    bg_boards = {}
    for a in args.background_board:
        src = resolve_source(a, single_image=True)
        bg_boards[src.name] = src
    default_d, named_d = _named_values(args.background_distance, "--background-distance")
    params = CalibrationParams(n_dist=args.n_dist, min_corners=args.min_corners, min_views=args.min_views,
                               world_board_view=args.world_board_view,
                               world_board_orientation=args.world_board_orientation,
                               robust_scale=args.robust_scale)
    rig = run_calibration(sources, board, params, step=args.step, max_views=args.max_views,
                          background_boards=bg_boards, background_distance=default_d,
                          background_distances=named_d)
    out_dir = os.path.dirname(os.path.abspath(args.out))
    out = write_calibration(args.out, rig, board=board,
                            sources={s.name: os.path.relpath(s.label, out_dir) for s in sources})
    print(_report(rig, str(out)))
    return 0
