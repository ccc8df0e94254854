"""``schlieren submit SESSION --out STORE --cluster slurm|pbs|kubernetes --config FILE``.

Creates the cluster on a batch system (dask-jobqueue for SLURM/PBS, the Dask Kubernetes
operator for Kubernetes) from a YAML config (see ``deploy/slurm/jobqueue.yaml`` and
``deploy/kubernetes/schlieren.yaml``), connects a client, runs the session on it and
closes the cluster. ``--dry-run`` prints the worker job script (SLURM/PBS) or the
``DaskCluster`` manifest (Kubernetes) and submits nothing.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path
from typing import Any

from schlieren.workers.cli import CLIError
from schlieren.workers.commands._args import positive_int

KINDS = ("slurm", "pbs", "kubernetes")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "submit",
        help="run a session on a SLURM, PBS or Kubernetes cluster",
        description=(
            "Start Dask workers through the batch system (dask-jobqueue or the Dask Kubernetes operator), "
            "process the session on them and shut them down. The scheduler runs in this process; its "
            "dashboard binds loopback (reach it through an SSH tunnel)."
        ),
    )
    p.add_argument("session", help="session folder or its session.yaml")
    p.add_argument("--out", required=True, help="result store (Zarr v3 folder)")
    p.add_argument("--cluster", required=True, choices=KINDS, help="batch system")
    p.add_argument("--config", required=True, metavar="FILE", help="cluster config YAML (deploy/slurm/jobqueue.yaml, ...)")
    p.add_argument("--scale", type=positive_int, default=None, metavar="N",
                   help="worker jobs (SLURM/PBS) or pods (Kubernetes)")
    p.add_argument("--frames", default=None, metavar="A:B", help="half-open frame range to process")
    p.add_argument("--params", default=None, metavar="FILE", help="YAML file of run parameters")
    p.add_argument("--report", default=None, metavar="FILE", help="write a Dask performance report (HTML)")
    from schlieren.workers.commands.run import add_log_arg  # stdlib-only module

    add_log_arg(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--frames-per-task", type=positive_int, default=None, metavar="N",
                   help="frames of one camera per task in the cheap 2D stages "
                        "(default: the deflection about 3.1 megapixels per task)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a result store of another session or configuration at --out (a store of "
                        "this same run is resumed either way)")
    p.add_argument("--verify", action="store_true",
                   help="before resuming, read every chunk of the existing store and check its checksum "
                        "(as `schlieren run --verify`); damaged chunks are recomputed with everything downstream")
    from schlieren.workers.commands.run import add_keep_arg

    add_keep_arg(p)
    p.add_argument("--dry-run", action="store_true", help="print the job script / manifest and exit")
    p.set_defaults(func=handler)


def load_submit_config(path: str | Path, *, scale: int | None = None) -> dict[str, Any]:
    """Read a submit config with ``yaml.safe_load`` (no tags, nothing executed).

    ``scale`` overrides ``schlieren.scale`` (and drops ``schlieren.adapt``). Raises ``CLIError`` with one line on any
    problem (missing file, YAML error, not a mapping).
    """
    import yaml

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CLIError(f"config {p}: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise CLIError(f"config {p}{where}: {problem}") from None
    if not isinstance(data, dict):
        raise CLIError(f"config {p}: expected a mapping with 'jobqueue:' or 'kubernetes:' and 'schlieren:' sections")
    data = copy.deepcopy(data)
    if scale is not None:
        if scale < 1:
            raise CLIError(f"--scale must be at least 1, got {scale}")
        sec = data.get("schlieren") or {}
        if not isinstance(sec, dict):
            raise CLIError(f"config {p}: the 'schlieren' section must be a mapping")
        # a fixed number of jobs / pods: drop any adaptive range of the config
        data["schlieren"] = {**{k: v for k, v in sec.items() if k != "adapt"}, "scale": scale}
    return data


def render(kind: str, config: dict[str, Any]) -> str:
    """What ``--dry-run`` prints: the worker job script or the DaskCluster manifest (YAML).

    Certificates need not exist yet: the script names their paths (a note on stderr says
    which are missing)."""
    from schlieren.workers.cluster import daskcluster_manifest, job_script

    if kind == "kubernetes":
        import yaml

        return yaml.safe_dump(daskcluster_manifest(config), sort_keys=False)
    _note_missing_certificates(config)
    return job_script(kind, config, check_files=False)


def _note_missing_certificates(config: dict[str, Any]) -> None:
    from schlieren.workers.cluster import schlieren_section
    from schlieren.workers.security import ROLES, tls_files_from_config

    tls = schlieren_section(config).get("tls")
    if not tls:
        return
    missing = sorted({str(p) for role in ROLES for p in vars(tls_files_from_config(tls, role)).values()
                      if not Path(p).is_file()})
    if missing:
        print(f"note: TLS certificates not found yet ({', '.join(missing)}); make them with "
              "`schlieren tls init DIR` before submitting", file=sys.stderr)


def handler(args: argparse.Namespace) -> int:
    from schlieren.workers.cluster import make_batch_cluster, schlieren_section

    config = load_submit_config(args.config, scale=args.scale)
    try:
        sec = schlieren_section(config)
        if args.dry_run:
            print(render(args.cluster, config))
            return 0
    except (ValueError, TypeError, FileNotFoundError, RuntimeError) as exc:
        raise CLIError(f"config {args.config}: {exc}") from None

    # the run entry points belong to the executor; imported here so this module loads without them
    from schlieren.storage.session import load_session
    from schlieren.workers.commands.run import check_out, load_params, open_run_log, parse_frames, print_summary

    frames = parse_frames(args.frames)
    run_config = load_params(args.params)
    session = load_session(args.session, frames=frames)  # bad input refused before any job starts
    check_out(args.out)
    with open_run_log(args.log, session.name) as run_log:
        try:
            cluster = make_batch_cluster(args.cluster, config)
        except (ValueError, TypeError, FileNotFoundError, RuntimeError) as exc:
            raise CLIError(f"config {args.config}: {exc}") from None
        with cluster:
            summary = _run_on(cluster, args, sec, session, run_config, run_log)
    print_summary(summary, stream=sys.stderr)  # the stream of now (tests swap sys.stderr)
    return 0 if summary.ok else 1


def _run_on(cluster, args: argparse.Namespace, sec: dict[str, Any], session, run_config, run_log):
    """Connect to the batch cluster, run the session on it; a cluster that cannot run it
    (no worker joined in time, jobs that keep ending) is one line, not a hang."""
    from schlieren.workers.cluster import ClusterOptions, ClusterStalled, connect, dashboard_line, stop_on_stall
    from schlieren.workers.commands.run import fan_out, log_finished
    from schlieren.workers.progress import StageProgress
    from schlieren.workers.run import run_session

    timeout = sec["wait_timeout"]
    try:
        with stop_on_stall(cluster), connect(
            cluster,
            ClusterOptions(tomo_slots=sec["tomo_slots"]),
            mode=args.cluster,
            wait_workers=sec["wait_workers"],
            timeout=float(timeout) if timeout is not None else None,
        ) as (client, info):
            line = dashboard_line(client)
            if line:
                print(line, file=sys.stderr)
            with StageProgress(enabled=not args.no_progress) as prog:
                summary = run_session(
                    session,
                    args.out,
                    client=client,
                    config=run_config,
                    report=args.report,
                    on_receipt=fan_out(prog.receipt, run_log.receipt),
                    on_failure=fan_out(prog.failure, run_log.failure),
                    on_plan=prog.plan,
                    frames_per_task=args.frames_per_task,
                    overwrite=bool(args.overwrite),
                    verify=bool(args.verify),
                    keep=getattr(args, "keep", None),
                )
            log_finished(run_log, summary)
            summary.dashboard = info.dashboard_link
    except ClusterStalled as exc:
        raise CLIError(f"{exc}; every completed chunk is kept, submit again to resume") from None
    return summary
