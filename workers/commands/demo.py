"""``schlieren demo``: synthesise a small capture, reconstruct it, evaluate it, report it."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from types import SimpleNamespace

DEFAULTS = dict(cameras=8, ring="half", phantom="plume", frames=4, size=(480, 360), flow_factor=3,
                voxel_size=None)


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="synthesise a small capture, reconstruct, evaluate and report it",
                       description="Makes a small synthetic capture (8 cameras on a half ring, a rising "
                                   "buoyant plume, a few frames), runs the whole pipeline on a local "
                                   "cluster, evaluates it against its ground truth and writes the report.")
    p.add_argument("--out", default="demo-out", help="folder for the session, store and report (default demo-out)")
    from schlieren.workers.commands._args import int_at_least, positive_int

    p.add_argument("--workers", type=positive_int, default=2, help="local worker processes (1 = serial loop)")
    p.add_argument("--cameras", type=int_at_least(2), default=DEFAULTS["cameras"])
    p.add_argument("--frames", type=positive_int, default=DEFAULTS["frames"])
    p.add_argument("--size", default="480x360", help="image size WxH (default 480x360)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.workers.cli import CLIError
    from schlieren.workers.commands._args import image_size
    from schlieren.workers.commands.run import execute, print_summary
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.report import make_report
    from schlieren.workers.synth import synthesize

    try:
        w, h = image_size(16)(args.size)
    except argparse.ArgumentTypeError as exc:
        raise CLIError(f"--size {args.size!r}: {exc}, e.g. 480x360") from None
    out = Path(args.out)
    session_dir = out / "session"
    store = out / "result.zarr"
    t0 = time.time()
    if not (session_dir / "session.yaml").exists():
        print(f"demo: synthesising {args.cameras} cameras x {args.frames} frames at {w}x{h} "
              f"into {session_dir}", file=sys.stderr)
        synthesize(session_dir, cameras=args.cameras, ring="half", phantom="plume",
                   frames=args.frames, size=(w, h), seed=args.seed)
    else:
        _check_reusable(session_dir, args.cameras, args.frames, (w, h))
        print(f"demo: reusing the synthetic session in {session_dir}", file=sys.stderr)
    run_args = SimpleNamespace(serial=args.workers <= 1, workers=args.workers, scheduler=None,
                               tls=None, report=None, log=None, params=None, no_progress=args.no_progress,
                               frames_per_task=None)
    summary = execute(str(session_dir), str(store), None, run_args)
    print_summary(summary)
    if not summary.ok:
        return 1
    truth = session_dir / "truth.zarr"
    result = evaluate(store, truth)
    report = make_report(store, out / "report", evaluation=result)
    overall = result["overall"]
    print(f"demo: PSNR {overall['psnr']:.2f} dB, relative RMS {100 * overall['rms']:.2f} % "
          f"over {len(result['frames'])} frames ({time.time() - t0:.0f} s)")
    print(f"demo: report {report}")
    return 0


def _check_reusable(session_dir: Path, cameras: int, frames: int, size: tuple[int, int]) -> None:
    """Refuse to reuse a demo session made with other ``--cameras``, ``--frames`` or ``--size``."""
    from schlieren.storage.session import load_session
    from schlieren.workers.cli import CLIError

    have = load_session(session_dir)
    a, b = have.frames
    got = (len(have.cameras), b - a, tuple(have.cameras[0].image_size))
    if got != (cameras, frames, tuple(size)):
        raise CLIError(
            f"{session_dir} holds a demo session of {got[0]} cameras x {got[1]} frames at "
            f"{got[2][0]}x{got[2][1]}, not the {cameras} x {frames} at {size[0]}x{size[1]} asked for; "
            f"give another --out or delete that folder")
