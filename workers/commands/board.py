"""``schlieren board OUT_DIR``: the ChArUco calibration target and a BOS background, ready to print.

Writes ``charuco.png`` (the board ``schlieren calibrate`` detects, with the same
``--squares/--square-size/--marker-size/--dictionary``) and ``background.png`` (a
band-limited noise pattern, the BOS background) at ``--dpi``, with the DPI in the PNG
header: print both at 100 % (no "fit to page") and measure one printed square; give the
measured size to ``schlieren calibrate --square-size``.

Background feature size: the finest blobs should cover 2-3 camera pixels where the
background is seen, i.e. ``feature ~ 2.5 * pixel pitch * background distance / focal
length`` (e.g. 3.45 um pixels, 50 mm lens, background 2.5 m away: about 0.4 mm).
"""

from __future__ import annotations

import argparse

INCH = 0.0254


def _size(text: str) -> tuple[float, float]:
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError("expected WIDTHxHEIGHT in metres, e.g. 0.6x0.4") from None
    if not (w > 0 and h > 0):
        raise argparse.ArgumentTypeError("width and height must be positive metres")
    return w, h


def add_parser(sub) -> None:
    p = sub.add_parser("board", help="render the ChArUco target and a BOS background for printing",
                       description=__doc__.split("\n", 1)[1].strip().replace("``", ""),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", metavar="OUT_DIR", help="folder for charuco.png and background.png")
    p.add_argument("--squares", default="10x7", metavar="CxR", help="chessboard squares (default 10x7)")
    p.add_argument("--square-size", type=float, default=0.03, metavar="M", help="square edge, metres (0.03)")
    p.add_argument("--marker-size", type=float, default=0.022, metavar="M", help="marker edge, metres (0.022)")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ArUco dictionary (cv2.aruco name)")
    p.add_argument("--legacy-pattern", action="store_true", help="OpenCV < 4.6 layout (even number of rows)")
    p.add_argument("--dpi", type=float, default=300.0, help="printer resolution, dots per inch (300)")
    p.add_argument("--background", type=_size, default=(0.42, 0.297), metavar="WxH",
                   help="background print size in metres (default 0.42x0.297, A3 landscape)")
    p.add_argument("--feature-size", type=float, default=0.0008, metavar="M",
                   help="finest feature of the background pattern, metres (default 0.8 mm)")
    p.add_argument("--seed", type=int, default=0, help="background pattern seed")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from pathlib import Path

    from schlieren.pipeline.calibration import BoardSpec, CalibrationError
    from schlieren.pipeline.synthetic.background import background_image, make_background, wavelet_noise_tile
    from schlieren.storage.calibration_io import write_print_image
    from schlieren.workers.cli import CLIError
    from schlieren.workers.commands.calibrate import parse_squares

    if not args.dpi > 0:
        raise CLIError("--dpi must be positive")
    try:
        board = BoardSpec(parse_squares(args.squares), args.square_size, args.marker_size, args.dictionary,
                          args.legacy_pattern)
    except CalibrationError as exc:
        raise CLIError(f"board: {exc}") from None
    pixel = INCH / args.dpi
    pps = max(8, int(round(args.square_size / pixel)))
    if args.feature_size < 2 * pixel:
        raise CLIError(f"--feature-size {args.feature_size:g} m is below two printer dots ({2 * pixel:.2g} m at "
                       f"{args.dpi:g} dpi): raise the dpi or the feature size")
    out = Path(args.out)
    charuco = write_print_image(out / "charuco.png", board.texture(pps, margin_squares=1), args.dpi)
    printed = pps * pixel
    w_px, h_px = (int(round(v / pixel)) for v in args.background)
    bg = make_background([0.0, 0.0, 0.0], [0.0, -1.0, 0.0], spacing=args.feature_size,
                         tile=wavelet_noise_tile(seed=args.seed), seed=args.seed)
    img = background_image(bg, w_px, h_px, pixel_size=pixel)
    background = write_print_image(out / "background.png", img, args.dpi)
    print(f"{charuco}: {board.squares[0]}x{board.squares[1]} squares of {printed * 1e3:.2f} mm "
          f"({pps} dots at {args.dpi:g} dpi); print at 100 % and measure a square for --square-size")
    print(f"{background}: {args.background[0]:g} x {args.background[1]:g} m ({w_px}x{h_px} dots), finest "
          f"features {args.feature_size * 1e3:.2g} mm")
    return 0
