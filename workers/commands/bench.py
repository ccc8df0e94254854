"""``schlieren bench table1|realistic|spacetime [...]``.

``table1`` reproduces the paper's Table 1 (sec. 6) on the project's synthetic plume and
writes ``benchmarks/results/table1.md`` and ``table1.json`` (see
:mod:`schlieren.workers.bench`). ``realistic`` runs the realistic capture family (CFD
flows, weak deflections, lossy video, each capture clean and as a lab records it;
:mod:`schlieren.workers.realistic`) and writes ``benchmarks/results/realistic[_LABEL].md``
/ ``.json``. ``spacetime`` runs the family's cases rendered with more frames (``--frames``,
default 7) with space-time reconstruction on and scores it against the same run's per-frame
solve (:mod:`schlieren.workers.bench.spacetime`, ``benchmarks/results/spacetime[_LABEL].md`` /
``.json``).
"""

from __future__ import annotations


from schlieren.workers.cli import CLIError
from schlieren.workers.commands._args import image_size

QUICK_SIZE = (160, 120)
QUICK_VOXEL = 0.005


_size = image_size(32)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("bench", help="reproduce the paper's benchmark tables on synthetic data",
                              description="Reproduce a table of the paper on the project's synthetic plume.")
    p.add_argument("table", choices=["table1", "realistic", "spacetime"],
                   help="table1: reconstruction errors per rig (paper sec. 6); realistic: the realistic capture "
                        "family (CFD plumes and jets, weak deflections, lossy video; needs the 'bench' extra); "
                        "spacetime: the family's cases with more frames, space-time against per-frame")
    p.add_argument("--quick", action="store_true",
                   help=f"a small subset: one half ring of 3 cameras, {QUICK_SIZE[0]}x{QUICK_SIZE[1]} images, "
                        f"1 frame, {QUICK_VOXEL * 1000:.0f} mm voxels (for tests)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="work folder for sessions and stores (default: a temporary folder, deleted)")
    p.add_argument("--results", metavar="DIR", default="benchmarks/results",
                   help="where table1.md / table1.json go (default benchmarks/results)")
    p.add_argument("--rigs", default=None, help="comma-separated RING:CAMERAS, default "
                                                "half:8,half:16,half:32,full:7,full:15,full:31")
    p.add_argument("--size", type=_size, default=None, help="image WIDTHxHEIGHT (default 480x360)")
    p.add_argument("--frames", type=int, default=None,
                   help="output frames per rig (default 3; spacetime: frames of each case, default 7)")
    p.add_argument("--voxel", type=float, default=None, help="reconstruction voxel, metres (default 0.0025)")
    p.add_argument("--workers", type=int, default=None,
                   help="local Dask workers for the pipeline runs; 0 = serial (default 2, quick: 0)")
    p.add_argument("--seed", type=int, default=0)
    r = p.add_argument_group("realistic")
    r.add_argument("--cases", default=None, help="comma-separated case names or prefixes (default: all)")
    r.add_argument("--role", choices=["tune", "report"], default=None, help="only the tune or the report cases")
    r.add_argument("--variant", choices=["clean", "lab"], default=None,
                   help="only the clean cases, or only the lab captures (the -lab and -laball cases); default both")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="run parameters (YAML) instead of the defaults (table1: flow.factor is the "
                        "benchmark's rendering factor, the largest flow.auto_factor may take)")
    r.add_argument("--label", default="", help="results go to realistic_LABEL.md/.json (default: realistic.md)")
    r.add_argument("--manifest-voxel", type=float, default=None, metavar="METRES",
                   help="run on manifests that give this voxel_size (default: the pipeline chooses it)")
    r.add_argument("--no-truth-rows", action="store_true",
                   help="skip the reconstruction from the truth's deflections (faster)")
    r.add_argument("--keep-stores", action="store_true",
                   help="keep the stores of a --label run (deleted after scoring by default: 0.1-1.7 GB per "
                        "case with its geometry cache; probes fill a disk); unlabelled runs keep store.zarr")
    p.set_defaults(func=handler)


def _config(args):
    from schlieren.workers.bench import QUICK_RIGS, Table1Config, parse_rigs

    base = Table1Config(frames=3, workers=2)
    if args.quick:
        base = Table1Config(rigs=QUICK_RIGS, size=QUICK_SIZE, frames=1, recon_voxel=QUICK_VOXEL, workers=0,
                            plain_rig=QUICK_RIGS[0], hull_rig=QUICK_RIGS[0])
    kw = {"seed": args.seed}
    if args.rigs:
        try:
            kw["rigs"] = parse_rigs(args.rigs)
        except ValueError as exc:
            raise CLIError(f"--rigs: {exc}") from None
    if args.size:
        kw["size"] = args.size
    if args.frames is not None:
        if args.frames < 1:
            raise CLIError("--frames must be at least 1")
        kw["frames"] = args.frames
    if args.voxel is not None:
        if not 0 < args.voxel < 0.1:
            raise CLIError("--voxel must be in (0, 0.1) metres")
        kw["recon_voxel"] = args.voxel
    if args.workers is not None:
        if args.workers < 0:
            raise CLIError("--workers must be >= 0")
        kw["workers"] = args.workers
    only_realistic = {"--cases": args.cases, "--role": args.role, "--variant": args.variant,
                      "--label": args.label or None,
                      "--manifest-voxel": args.manifest_voxel, "--no-truth-rows": args.no_truth_rows or None,
                      "--keep-stores": args.keep_stores or None}
    given = [k for k, v in only_realistic.items() if v is not None]
    if given:
        raise CLIError(f"{', '.join(given)}: options of `schlieren bench realistic`, not of table1")
    if args.params:
        kw["params"] = _run_params(args.params)
    import dataclasses

    return dataclasses.replace(base, **kw)


def _run_params(path: str) -> dict:
    """The ``--params`` file as a mapping, checked against the run parameters before any work."""
    from schlieren.pipeline.stages import config_from_dict
    from schlieren.storage.params_io import read_params

    try:
        data = read_params(path)
        config_from_dict(data)
    except (TypeError, ValueError) as exc:
        raise CLIError(f"--params {path}: {exc}") from None
    return data


def _machine() -> str:
    import os
    import platform

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{os.cpu_count()} cores ({platform.machine()}), shared with other jobs (1-min load {load:.1f} at the end)"


def _realistic(args) -> int:
    import contextlib
    import re
    import time
    from pathlib import Path

    from rich.console import Console

    from schlieren.pipeline.stages import config_from_dict
    from schlieren.workers import realistic as rb

    console = Console(stderr=True)
    if args.label and not re.fullmatch(r"[A-Za-z0-9_.-]+", args.label):
        raise CLIError("--label may hold letters, digits, '_', '.' and '-' only")
    try:
        cases = rb.QUICK_CASES if args.quick else rb.select_cases(args.cases, role=args.role, variant=args.variant)
    except ValueError as exc:
        raise CLIError(f"--cases: {exc}") from None
    if not cases:
        raise CLIError("no case selected")
    config = config_from_dict(_run_params(args.params)) if args.params else None
    if not args.quick and not _has_bench_extra():
        raise CLIError("the realistic family needs PhiFlow and imageio-ffmpeg: pip install 'schlieren[bench]' "
                       "(python3 dev.py installs them)")
    if args.manifest_voxel is not None and not 0 < args.manifest_voxel < 0.1:
        raise CLIError("--manifest-voxel must be in (0, 0.1) metres")
    workers = args.workers if args.workers is not None else (0 if args.quick else 2)
    if workers < 0:
        raise CLIError("--workers must be >= 0")
    work = Path(args.out or "realistic-out")
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        client = None
        if workers > 0:
            from schlieren.workers.cluster import ClusterOptions, open_client

            client, _info = stack.enter_context(open_client(ClusterOptions(workers=workers, dashboard_address=":0")))
            _numba_follows_environment()
        result = rb.run_family(work, cases, config=config, client=client, label=args.label,
                               truth_rows=not args.no_truth_rows, progress=lambda m: console.print(m),
                               voxel=args.manifest_voxel, keep_stores=args.keep_stores or not args.label)
    result["wall_seconds"] = time.perf_counter() - t0
    machine = _machine()
    result["machine"] = machine
    name = "realistic" + (f"_{args.label}" if args.label else "")
    return _write_family(Path(args.results), name, rb.family_markdown(result, machine=machine), result, console)


def _write_family(out, name: str, markdown: str, result: dict, console) -> int:
    """Write a family benchmark's ``<name>.md`` / ``.json`` under ``out``; 1 if a case's run failed."""
    from schlieren.storage import bench_io

    bench_io.write_text(out / f"{name}.md", markdown)
    bench_io.write_json(out / f"{name}.json", result)
    console.print(f"wrote {out / (name + '.md')} and {out / (name + '.json')} ({result['wall_seconds']:.0f} s)")
    failed = [c["case"] for c in result["cases"] if c.get("failures")]
    if failed:
        console.print(f"pipeline failures: {', '.join(failed)}")
        return 1
    return 0


def _spacetime(args) -> int:
    import contextlib
    import re
    import time
    from pathlib import Path

    from rich.console import Console

    from schlieren.pipeline.stages import config_from_dict
    from schlieren.workers import realistic as rb
    from schlieren.workers.bench import spacetime as sb

    console = Console(stderr=True)
    if args.label and not re.fullmatch(r"[A-Za-z0-9_.-]+", args.label):
        raise CLIError("--label may hold letters, digits, '_', '.' and '-' only")
    frames = sb.DEFAULT_FRAMES if args.frames is None else args.frames
    if not 3 <= frames <= 9:
        raise CLIError("--frames must be in 3..9 (the CFD runs cover 9 processed frames)")
    try:
        cases = sb.longer_cases(rb.select_cases(args.cases, role=args.role), frames)
    except ValueError as exc:
        raise CLIError(f"--cases: {exc}") from None
    if not cases:
        raise CLIError("no case selected")
    if not _has_bench_extra():
        raise CLIError("the realistic family needs PhiFlow and imageio-ffmpeg: pip install 'schlieren[bench]'")
    config = config_from_dict(_run_params(args.params)) if args.params else None
    workers = 2 if args.workers is None else args.workers
    if workers < 0:
        raise CLIError("--workers must be >= 0")
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        client = None
        if workers > 0:
            from schlieren.workers.cluster import ClusterOptions, open_client

            client, _info = stack.enter_context(open_client(ClusterOptions(workers=workers, dashboard_address=":0")))
            _numba_follows_environment()
        result = sb.run_family(Path(args.out or "realistic-out"), cases, config=config, client=client,
                               label=args.label, keep_stores=args.keep_stores or not args.label,
                               progress=lambda m: console.print(m))
    result["wall_seconds"] = time.perf_counter() - t0
    result["machine"] = _machine()
    name = "spacetime" + (f"_{args.label}" if args.label else "")
    command = "schlieren bench spacetime" + (f" --cases {args.cases}" if args.cases else "") + \
        (f" --role {args.role}" if args.role else "") + (f" --frames {frames}" if args.frames else "") + \
        (f" --params {args.params}" if args.params else "")
    return _write_family(Path(args.results), name,
                         sb.spacetime_markdown(result, machine=result["machine"], command=command), result, console)


def _numba_follows_environment() -> None:
    """Make this process's numba read the thread cap the local cluster's nannies just exported.

    The nannies run in this process and put ``NUMBA_NUM_THREADS=1`` into its environment
    (``workers/cluster/settings.py``), but numba reads the environment only when it compiles.
    The benchmark runs numba kernels here too (rendering, the truth rows): if the first of
    them runs from the disk cache, numba starts its pool at the old count, and the next
    compile refuses the changed variable ("Cannot set NUMBA_NUM_THREADS to a different
    value once the threads have been launched"). Reading it now starts the pool at the cap.
    """
    from numba.core import config
    from numba.np.ufunc import parallel

    if not parallel._is_initialized:
        config.reload_config()


def _has_bench_extra() -> bool:
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in ("phi", "imageio_ffmpeg"))


def handler(args) -> int:
    if args.table == "realistic":
        return _realistic(args)
    if args.table == "spacetime":
        return _spacetime(args)
    import contextlib
    import tempfile
    import time
    from pathlib import Path

    from rich.console import Console

    from schlieren.storage import bench_io
    from schlieren.workers.bench import rig_failures, run_table1, table1_markdown

    console = Console(stderr=True)
    cfg = _config(args)
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if args.out:
            work = Path(args.out)
        else:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="schlieren-bench-")))
        client = None
        executor = "serial"
        if cfg.workers > 0:
            from schlieren.workers.cluster import ClusterOptions, open_client

            client, _info = stack.enter_context(open_client(ClusterOptions(workers=cfg.workers,
                                                                           dashboard_address=":0")))
            _numba_follows_environment()
            executor = f"local Dask cluster, {cfg.workers} workers x 1 thread"
        result = run_table1(work, cfg, client=client, progress=lambda m: console.print(m))
    wall = time.perf_counter() - t0
    result["wall_seconds"] = wall
    result["executor"] = executor
    machine = _machine()
    result["machine"] = machine
    md = table1_markdown(result, wall_seconds=wall, executor=executor, machine=machine)
    out = Path(args.results)
    bench_io.write_text(out / "table1.md", md)
    bench_io.write_json(out / "table1.json", result)
    console.print(f"wrote {out / 'table1.md'} and {out / 'table1.json'} ({wall:.0f} s)")
    failed = rig_failures(result)
    if failed:
        console.print(f"pipeline failures: {', '.join(failed)}")
        return 1
    return 0
