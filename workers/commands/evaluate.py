"""``schlieren evaluate STORE --truth TRUTH``: accuracy table (SPEC section 4)."""

from __future__ import annotations


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="accuracy of a store against synthetic ground truth",
                              description="Relative RMS and PSNR of the refractivity per frame and overall, over "
                                          "the whole box and in the plume (voxels where the truth departs "
                                          "from ambient by more than 1 % of its range).")
    p.add_argument("store", metavar="STORE")
    p.add_argument("--truth", required=True, metavar="TRUTH", help="truth.zarr written by `schlieren synth`")
    p.add_argument("--json", metavar="FILE", default=None, help="also write the figures as JSON")
    p.set_defaults(func=handler)


def _fmt(x: float, spec: str) -> str:
    return format(x, spec) if x == x and abs(x) != float("inf") else str(x)


def handler(args) -> int:
    import sys

    from rich.console import Console
    from rich.table import Table

    from schlieren.storage.synthetic_io import write_json
    from schlieren.workers.evaluate import evaluate

    res = evaluate(args.store, args.truth)
    table = Table(title=f"accuracy of {args.store}")
    for col in ("frame", "time (s)", "RMS (%)", "PSNR (dB)", "in-plume RMS (%)", "in-plume PSNR (dB)",
                "peak ratio", "truth"):
        table.add_column(col, justify="right")
    for r in res["frames"]:
        table.add_row(str(r["frame"]), f"{r['time']:.6f}", _fmt(100 * r["rms"], ".3f"), _fmt(r["psnr"], ".2f"),
                      _fmt(100 * r["rms_plume"], ".3f"), _fmt(r["psnr_plume"], ".2f"), _fmt(r["peak_ratio"], ".3f"),
                      r["truth_from"])
    o, p = res["overall"], res["plume"]
    table.add_row("all", "", _fmt(100 * o["rms"], ".3f"), _fmt(o["psnr"], ".2f"), _fmt(100 * p["rms"], ".3f"),
                  _fmt(p["psnr"], ".2f"), "", f"{o['frames']} frames", style="bold")
    # to a file or a pipe: the whole table on lines as long as it needs (rich would squeeze it to 80 columns)
    (Console() if sys.stdout.isatty() else Console(width=10_000, soft_wrap=False)).print(table)
    if args.json:
        write_json(args.json, res)
    return 0
