"""CPU per stage of the serial run, A/B between revisions, alternated (the session target's
per-stage comparison on a loaded machine, where wall times say little).

    python benchmarks/stage_cpu_ab.py [--revs 1c689b8,WORKTREE] [--repeats 2] [--session DIR] [--out NAME]

Each revision (a git revision, or ``WORKTREE`` for this checkout as installed) runs
``schlieren run --serial --log`` on the session of ``benchmarks/session.py`` (16 cameras x
1440x1080, rendered once into ``benchmarks/cache/session-16x1440x1080-f8``; ``--session``
takes another) in a child process; the revisions alternate, ``--repeats`` times, so the
machine's load hits them alike. A revision other than the worktree is extracted with
``git archive`` into a temporary folder and imported ahead of the installed package
(``PYTHONPATH``: the ``schlieren`` package assembled from its ``workers/toplevel``,
``pipeline``, ``storage`` and ``workers`` folders); its first run compiles its numba
kernels, so the first repeat of every revision is a warm-up and is not counted unless it
is the only one. The task receipts' CPU (``cpu_seconds``, the task thread's) is summed per
stage and divided by the processed frames.

Writes ``benchmarks/results/<NAME>.json`` and ``.md`` (default ``stage_cpu_ab``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
DEFAULT_SESSION = HERE / "cache" / "session-16x1440x1080-f8"
WORKTREE = "WORKTREE"


def overlay(rev: str, into: Path) -> Path:
    """``rev`` extracted into ``into/src`` and its ``schlieren`` package assembled in ``into/pkg``."""
    src, pkg = into / "src", into / "pkg" / "schlieren"
    src.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    with tempfile.TemporaryFile() as f:
        f.write(archive)
        f.seek(0)
        with tarfile.open(fileobj=f) as tar:
            tar.extractall(src, filter="data")
    pkg.mkdir(parents=True)
    for f in (src / "workers" / "toplevel").iterdir():
        (pkg / f.name).symlink_to(f)
    for name in ("pipeline", "storage", "workers"):
        (pkg / name).symlink_to(src / name)
    return into / "pkg"


def run(session: Path, work: Path, name: str, path: Path | None) -> dict:
    """One serial run; CPU seconds per stage from its receipts, and its wall seconds."""
    out, log = work / f"{name}.zarr", work / f"{name}.jsonl"
    for p in (out, Path(f"{out}.cache")):
        shutil.rmtree(p, ignore_errors=True)
    log.unlink(missing_ok=True)
    env = dict(os.environ)
    if path is not None:
        env["PYTHONPATH"] = str(path)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "schlieren.workers.cli", "run", str(session), "--out", str(out),
                    "--serial", "--log", str(log), "--no-progress"], check=True, env=env, cwd=work)
    wall = time.perf_counter() - t0
    cpu: dict[str, float] = {}
    for line in log.read_text().splitlines():
        d = json.loads(line)
        if d.get("message") == "task receipt":
            cpu[d["stage"]] = cpu.get(d["stage"], 0.0) + float(d.get("cpu_seconds") or 0.0)
    return {"wall": wall, "cpu": cpu, "load": os.getloadavg()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--revs", default=f"1c689b8,{WORKTREE}")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--session", type=Path, default=DEFAULT_SESSION)
    ap.add_argument("--out", default="stage_cpu_ab")
    a = ap.parse_args(argv)
    revs = a.revs.split(",")
    from schlieren.storage.session import load_session

    s = load_session(a.session / "session.yaml")
    frames = s.frames[1] - s.frames[0]
    runs: dict[str, list] = {r: [] for r in revs}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        paths = {r: None if r == WORKTREE else overlay(r, tmp / f"rev-{i}") for i, r in enumerate(revs)}
        for k in range(a.repeats):
            for i, r in enumerate(revs):
                res = run(a.session, tmp, f"run-{i}", paths[r])
                runs[r].append(res)
                print(f"{r} repeat {k}: wall {res['wall']:.1f} s, load {res['load'][0]:.1f}", file=sys.stderr)
    counted = {r: v[1:] if len(v) > 1 else v for r, v in runs.items()}
    stages = list(dict.fromkeys(st for v in runs.values() for x in v for st in x["cpu"]))
    mean = {r: {st: sum(x["cpu"].get(st, 0.0) for x in v) / len(v) / frames for st in stages}
            for r, v in counted.items()}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{a.out}.json").write_text(json.dumps({"session": str(a.session), "frames": frames,
                                                      "revs": revs, "runs": runs, "cpu_per_step": mean}, indent=1))
    loads = [x["load"][0] for v in runs.values() for x in v]
    lines = [f"# CPU per stage of the serial run, A/B ({' vs '.join(revs)})", "",
             f"Command: `python benchmarks/stage_cpu_ab.py --revs {a.revs} --repeats {a.repeats}`", "",
             f"Session `{a.session.name}` ({frames} processed frames). Task-thread CPU seconds per time step, "
             f"the mean of the counted repeats (the first of {a.repeats} is a warm-up when there are more); "
             f"the revisions alternated, 1-minute load {min(loads):.1f}-{max(loads):.1f} (2 cores): "
             "upper bounds, compare the columns, not with other days.", "",
             "| stage | " + " | ".join(revs) + " |", "| --- |" + " ---: |" * len(revs)]
    for st in stages + ["total"]:
        vals = [sum(mean[r].values()) if st == "total" else mean[r][st] for r in revs]
        lines.append(f"| {st} | " + " | ".join(f"{v:.3f}" for v in vals) + " |")
    (RESULTS / f"{a.out}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
