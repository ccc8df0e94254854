"""``schlieren export STORE --format vti|raw|nrrd|ome-zarr [--quantity Q] [--out DIR] [--frames A:B]``."""

from __future__ import annotations

from schlieren.storage.export import FORMATS, QUANTITIES


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="export volumes for ParaView, renderers and OME-Zarr viewers "
                                      "(vti, raw+mhd, nrrd, ome-zarr)",
                       description="Write one volume quantity per frame with its world origin and spacing "
                                   "(metres): vti, raw (+mhd), nrrd or ome-zarr. Prints the files to open: the "
                                   ".pvd (vti), the .mhd headers (raw), the .nrrd files or the OME-Zarr group.")
    p.add_argument("store", help="result store (Zarr folder)")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("--quantity", default="refractivity", choices=list(QUANTITIES))
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default: STORE_<format> beside it)")
    p.add_argument("--frames", default=None, metavar="A:B", help="half-open range of store frames")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.workers.commands.run import parse_frames
    from schlieren.workers.report import generate_export

    res = generate_export(args.store, args.out, format=args.format, quantity=args.quantity,
                          frames=parse_frames(args.frames))
    for path in res.entry_points:
        print(path)
    return 0
