"""``schlieren check SESSION [--out DIR] [--watch]``: the rig checked in seconds, before
anyone reconstructs (docs/check.md)."""

from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser(
        "check", help="check a session's rig in seconds: noise, focus, exposure, motion, hot pixels, flash, "
                      "footprint, expected accuracy",
        description="Per camera: the sensor noise and the flow noise it predicts against the reference's "
                    "texture, focus, clipped pixels, the frames' shift against the reference, hot and dead "
                    "pixels, the strobe flash and its time offset, the volume's footprint and the voxel it "
                    "implies; then the in-plume accuracy the benchmark family reached with the nearest rig. "
                    "Prints a table and writes an HTML page (docs/check.md).")
    p.add_argument("session", nargs="?", default=None, metavar="SESSION",
                   help="session folder or session.yaml")
    p.add_argument("--watch", default=None, metavar="FOLDER",
                   help="re-check FOLDER (a session being recorded) whenever its files change, printing only "
                        "what changed; Ctrl-C ends it")
    p.add_argument("--interval", type=float, default=2.0, metavar="S", help="--watch: seconds between polls")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="folder of the HTML page (default: check-<session name> in the current folder)")
    p.add_argument("--no-html", action="store_true", help="print the table only")
    p.add_argument("--results", default=None, metavar="DIR",
                   help="the benchmark family's results (default: the checkout's benchmarks/results)")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.storage.report import safe_name
    from schlieren.workers.check import check_session, table_text, watch, write_page
    from schlieren.workers.cli import CLIError

    if args.watch is not None:
        if args.interval <= 0:
            raise CLIError("--interval must be positive (seconds)")
        return watch(args.watch, interval=args.interval, results=args.results)
    if args.session is None:
        raise CLIError("give a SESSION (or --watch FOLDER)")
    rig = check_session(args.session, results=args.results)
    print(table_text(rig))
    if not args.no_html:
        index = write_page(rig, args.out or f"check-{safe_name(rig.name)}")
        print(f"page: {index}")
    return 0
