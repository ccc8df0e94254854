"""``schlieren report STORE [--out DIR] [--frames A:B] [--cameras N] [--truth TRUTH]``: figures and an HTML page."""

from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser("report", help="write figures and an HTML page for a result store",
                       description="Write PNG figures, an animation and index.html for a result store "
                                   "(partial runs show what exists). Prints the path of index.html.")
    p.add_argument("store", help="result store (Zarr folder)")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default: STORE_report beside it)")
    p.add_argument("--frames", default=None, metavar="A:B", help="half-open range of store frames to show")
    p.add_argument("--cameras", type=int, default=None, metavar="N",
                   help="per-camera figures for the first N cameras only (the residual table lists all)")
    p.add_argument("--truth", default=None, metavar="TRUTH",
                   help="truth.zarr of a synthetic session (`schlieren synth`): adds the accuracy table")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.workers.commands.run import parse_frames
    from schlieren.workers.report import make_report

    evaluation = None
    if args.truth:
        from schlieren.workers.evaluate import evaluate

        evaluation = evaluate(args.store, args.truth)
    index = make_report(args.store, args.out, frames=parse_frames(args.frames), max_cameras=args.cameras,
                        evaluation=evaluation)
    print(index)
    return 0
