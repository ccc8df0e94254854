"""``schlieren run SESSION --out STORE [--frames A:B] [--workers N | --scheduler ADDR | --serial]``."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """``"A:B"`` -> ``(A, B)``, a half-open range of frames; None stays None."""
    from schlieren.workers.commands._args import frame_range

    return None if text is None else frame_range(text, "--frames")


def add_common_run_args(p: argparse.ArgumentParser) -> None:
    from schlieren.workers.commands._args import positive_int

    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--workers", type=positive_int, default=None, metavar="N",
                      help="local cluster of N worker processes (threads capped); 1 = serial loop")
    mode.add_argument("--scheduler", default=None, metavar="ADDRESS",
                      help="an existing Dask scheduler, tcp://host:port or tls://host:port")
    mode.add_argument("--serial", action="store_true", help="run the reference loop in this process")
    p.add_argument("--tls", default=None, metavar="DIR",
                   help="folder with ca.pem, client.pem, client-key.pem for a tls:// scheduler")
    p.add_argument("--report", default=None, metavar="FILE", help="write a Dask performance report (HTML)")
    add_log_arg(p)
    p.add_argument("--params", default=None, metavar="FILE",
                   help="YAML file of run parameters (`schlieren params` prints them all with defaults)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a result store of another session or configuration at --out (a store of "
                        "this same run is resumed either way)")
    p.add_argument("--frames-per-task", type=positive_int, default=None, metavar="N",
                   help="frames of one camera per task in the cheap 2D stages (default: the deflection about "
                        "3.1 megapixels per task, 8 frames at 480x360, 2 at 1440x1080; results and resume do not "
                        "depend on it)")
    add_keep_arg(p)
    p.add_argument("--verify", action="store_true",
                   help="before resuming, read every chunk of the existing store and check its checksum "
                        "(a rerun always checks that the chunks of every completed task exist); damaged "
                        "chunks are recomputed with everything downstream")


def _keep(text: str) -> str:
    """An argparse ``type`` for ``--keep`` (checked here, so a typo stops before any work)."""
    from schlieren.workers.retention import arrays_to_drop

    try:
        arrays_to_drop(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--keep ")) from None
    return text


def add_keep_arg(p: argparse.ArgumentParser) -> None:
    from schlieren.workers.retention import KEEP_HELP

    p.add_argument("--keep", default="all", metavar="WHAT", type=_keep, help=KEEP_HELP)


def add_log_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log", default=None, metavar="FILE",
                   help="append one JSON line per task receipt (stage, camera, frame, seconds, cpu_seconds, "
                        "worker, solver iterations and residual) and per failure to FILE")


def fan_out(*callbacks):
    """One callback calling each of ``callbacks`` in turn."""
    def call(*args):
        for cb in callbacks:
            cb(*args)
    return call


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="process a capture session into a result store",
                       description="Process a capture session (session.yaml) into a Zarr result store. "
                                   "A rerun on the same store resumes from the completion markers.")
    p.add_argument("session", help="session folder or its session.yaml (or an fsspec URL: s3://bucket/capture)")
    p.add_argument("--out", required=True,
                   help="result store: a Zarr v3 folder, or an fsspec URL such as s3://bucket/run.zarr "
                        "(credentials and AWS_ENDPOINT_URL from the environment)")
    p.add_argument("--frames", default=None, metavar="A:B", help="half-open frame range to process")
    add_common_run_args(p)
    p.set_defaults(func=handler)


def load_params(path: str | None):
    from schlieren.pipeline.stages import RunConfig, config_from_dict
    from schlieren.storage.params_io import read_params
    from schlieren.workers.cli import CLIError

    if path is None:
        return RunConfig()
    from schlieren.pipeline.params import ParamsError

    data = read_params(path)
    try:
        return config_from_dict(data)
    except ParamsError as exc:
        where = f", field {exc.field}" if exc.field else ""
        raise CLIError(f"file {path}{where}: {exc.message}") from None


@contextlib.contextmanager
def client_for(args):
    """Yield a Dask client (or None for the serial loop) according to the CLI flags."""
    if args.serial or (args.workers is not None and args.workers <= 1 and args.scheduler is None):
        yield None, None
        return
    from schlieren.workers.cli import CLIError
    from schlieren.workers.cluster import ClusterOptions, connect_error, open_client

    opts = ClusterOptions(workers=args.workers if args.scheduler is None else None,
                          scheduler=args.scheduler, tls_dir=args.tls)
    with contextlib.ExitStack() as stack:
        try:  # a missing --tls, a wrong CA, a wrong address: one line, not a traceback
            client, info = stack.enter_context(open_client(opts))
        except (ValueError, OSError, TimeoutError) as exc:
            raise CLIError(connect_error(opts, exc)) from None
        yield client, info


def execute(session: str, out: str, frames, args, *, console=None):
    """Run a session with progress bars; returns the RunSummary."""
    from schlieren.storage.session import load_session
    from schlieren.workers.progress import StageProgress
    from schlieren.workers.run import run_session

    cfg = load_params(getattr(args, "params", None))
    # validate everything before a cluster is even started
    loaded = load_session(session, frames=frames)
    check_out(out)
    with open_run_log(getattr(args, "log", None), loaded.name) as run_log, client_for(args) as (client, info):
        link = None
        if client is not None:
            from schlieren.workers.cluster import dashboard_line, dashboard_link

            link = dashboard_link(client)
            line = dashboard_line(client)  # names the port asked for when it was taken
            if line:
                print(line, file=sys.stderr)
        with StageProgress(enabled=not args.no_progress, console=console) as prog:
            summary = run_session(loaded, out, client=client, frames=frames,
                                  serial=client is None, config=cfg, report=args.report,
                                  on_receipt=fan_out(prog.receipt, run_log.receipt),
                                  on_failure=fan_out(prog.failure, run_log.failure),
                                  on_plan=prog.plan, frames_per_task=args.frames_per_task,
                                  overwrite=getattr(args, "overwrite", False),
                                  verify=bool(getattr(args, "verify", False)), keep=getattr(args, "keep", None))
            log_finished(run_log, summary)
        summary.dashboard = link
    return summary


def check_out(out: str) -> None:
    """Refuse an ``--out`` that exists and is no result store (a file, a folder of other
    things) before any cluster starts; a URL is checked when the store is opened."""
    from schlieren.storage import location
    from schlieren.storage.store import check_store_target

    if not location.is_url(location.normalize(out)):
        check_store_target(out)


def open_run_log(path, session_name: str):
    """The ``--log`` file (a no-op log without a path); an unwritable path is a CLI error."""
    from schlieren.workers.cli import CLIError
    from schlieren.workers.monitoring import RunLog

    try:
        return RunLog(path, session=session_name)
    except OSError as exc:
        raise CLIError(f"--log {path}: cannot write it: {exc.strerror or exc}") from None


def log_finished(run_log, summary) -> None:
    """The closing line of ``--log``: counts, wall time and executor of the run."""
    run_log.finished(store=summary.store, executor=summary.executor, tasks=summary.tasks,
                     steps=summary.steps_computed, skipped=summary.skipped, seconds=round(summary.seconds, 3),
                     failed=len(summary.root_failures()),
                     not_run=len(summary.failures) - len(summary.root_failures()))


def print_summary(summary, *, stream=None) -> None:
    stream = stream or sys.stderr
    roots = summary.root_failures()
    check = getattr(summary, "integrity", None)
    if check is not None and check.problems:
        print(f"verify: {check.summary()}:", file=stream)
        for line in check.lines(10):
            print(f"  - {line}", file=stream)
    bad = getattr(summary, "bad_frames", None) or []
    if bad:
        shown = "; ".join(f"{cam} frame {f} ({', '.join(why)})" for cam, f, why in bad[:20])
        more = f"; and {len(bad) - 20} more" if len(bad) > 20 else ""
        print(f"excluded from the reconstruction: {shown}{more}", file=stream)
    # steps: one stage at one camera and frame (what a completion marker records); a task
    # computes one step or several frames of one camera, so only steps add up across runs
    print(f"store: {summary.store}  ({summary.steps_computed} steps computed in {summary.tasks} "
          f"task{'' if summary.tasks == 1 else 's'}, {summary.skipped} already complete; "
          f"{summary.seconds:.1f} s, {summary.executor} executor)", file=stream)
    if summary.failures:
        print(f"FAILED: {len(roots)} task(s) failed, {len(summary.failures) - len(roots)} not run "
              f"because of them; every completed chunk is kept, rerun to resume:", file=stream)
        for key, msg in list(roots.items())[:20]:
            print(f"  - {msg}", file=stream)
        if len(roots) > 20:
            print(f"  ... and {len(roots) - 20} more", file=stream)


def handler(args) -> int:
    frames = parse_frames(args.frames)
    summary = execute(args.session, args.out, frames, args)
    print_summary(summary)
    return 0 if summary.ok else 1
