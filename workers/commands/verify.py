"""``schlieren verify STORE [--repair] [--quick] [--json FILE]``: check every chunk of a result store."""

from __future__ import annotations

import sys


def add_parser(sub) -> None:
    p = sub.add_parser(
        "verify", help="check every chunk of a result store (checksums, chunks lost under completion markers)",
        description="Read every chunk of a result store and check its CRC-32C, and that every chunk of a "
                    "completed task exists. Prints one line per damaged chunk (array, chunk, the task that "
                    "writes it). With --repair, clears the completion markers of the damaged tasks and of "
                    "everything downstream of them and removes the damaged files: rerunning `schlieren run` "
                    "then recomputes exactly those tasks. Exit code 0 if intact, 1 if damaged.")
    p.add_argument("store", help="result store (Zarr folder)")
    p.add_argument("--repair", action="store_true",
                   help="unmark damaged tasks and everything downstream, remove damaged chunk files")
    p.add_argument("--quick", action="store_true",
                   help="list the chunk files and read the markers only (what every rerun does)")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the findings as JSON")
    p.set_defaults(func=handler)


def handler(args) -> int:
    import contextlib

    from schlieren.storage.integrity import as_json
    from schlieren.storage.store import ResultStore
    from schlieren.storage.synthetic_io import write_json
    from schlieren.workers.run import store_lease
    from schlieren.workers.verify import verify_store

    with store_lease(args.store, purpose="verify --repair") if args.repair else contextlib.nullcontext():
        store = ResultStore.open(args.store, mode="r+" if args.repair else "r")
        report = verify_store(store, full=not args.quick, repair=args.repair)
    if report.scan.legacy:
        print(f"{args.store}: written by an older version without chunk checksums: chunks were only "
              "decoded, and lost chunks cannot be told from empty ones", file=sys.stderr)
    for line in report.lines(50):
        print(f"  - {line}")
    print(f"{args.store}: {report.summary()}")
    if report.repaired and report.invalidated:
        print(f"rerun `schlieren run SESSION --out {args.store}` to recompute them")
    if args.json:
        write_json(args.json, {**as_json(report.scan), "invalidated": report.invalidated,
                               "removed_files": report.removed_files})
    return 0 if report.ok else 1
