#!/usr/bin/env python3
"""Bootstrap and run: needs only Python 3.11+.

    python3 dev.py demo [ARGS...]   # make .venv, install schlieren, run `schlieren demo`
    python3 dev.py test [ARGS...]   # same venv, run the test suite (pytest): both tiers, as CI does
    python3 dev.py test --fast      # only the fast tier: no Dask clusters, S3 server, browser or SLURM
    python3 dev.py schlieren ARGS   # any other schlieren command inside the venv

The virtual environment lives in .venv beside this file and is (re)installed whenever
pyproject.toml (or the pinned versions) change; `demo` installs the runtime only, `test` adds
the test extras. On CPython 3.11 / Linux the versions are pinned by deploy/constraints-dev.txt
(the environment CI runs; SCHLIEREN_UNPINNED=1 resolves afresh).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
STAMP = VENV / ".schlieren-installed"


#: Exact versions of the test environment (CPython 3.11 on Linux, where CI runs).
CONSTRAINTS = ROOT / "deploy" / "constraints-dev.txt"


def _pinned() -> bool:
    """Install with :data:`CONSTRAINTS`: on the platform they were resolved for, unless
    SCHLIEREN_UNPINNED is set (to resolve afresh, e.g. when regenerating them)."""
    return (sys.version_info[:2] == (3, 11) and sys.platform.startswith("linux") and CONSTRAINTS.exists()
            and not os.environ.get("SCHLIEREN_UNPINNED"))


def _digest() -> str:
    h = hashlib.sha256((ROOT / "pyproject.toml").read_bytes())
    if _pinned():
        h.update(CONSTRAINTS.read_bytes())
    return h.hexdigest()


#: Extras per command: the demo needs only the runtime; the tests also need the test,
#: cluster (dask-jobqueue) and bench (PhiFlow, imageio-ffmpeg) extras.
EXTRAS = {"demo": (), "schlieren": ("test", "cluster", "bench"), "test": ("test", "cluster", "bench")}


def ensure_env(extras=("test", "cluster", "bench")) -> None:
    if sys.version_info < (3, 11):
        sys.exit(f"schlieren needs Python 3.11 or newer (this is {sys.version.split()[0]})")
    if not (BIN / "python").exists():
        print("dev.py: creating .venv", file=sys.stderr)
        venv.EnvBuilder(with_pip=True).create(VENV)
    have: set[str] = set()
    if STAMP.exists():
        digest, _, names = STAMP.read_text().partition("\n")
        if digest == _digest():
            have = set(names.split(",")) - {""}
            if set(extras) <= have:
                return
    want = sorted(have | set(extras))
    short = _short_of_space()
    if short:
        print(f"dev.py: warning: {short}", file=sys.stderr)
    print("dev.py: installing schlieren" + (f" with {', '.join(want)}" if want else "") + " into .venv",
          file=sys.stderr)
    pip = [str(BIN / "python"), "-m", "pip", "--disable-pip-version-check", "-q", "--retries", "10"]
    _pip(pip + ["install", "--upgrade", "pip"])
    spec = f"{ROOT}[{','.join(want)}]" if want else str(ROOT)
    _pip(pip + ["install"] + (["-c", str(CONSTRAINTS)] if _pinned() else []) + ["-e", spec])
    STAMP.write_text(_digest() + "\n" + ",".join(want))


#: Free space the install needs: the environment with every extra is about 2 GB, plus
#: pip's downloads and build folder.
INSTALL_BYTES = 3 * 2 ** 30


def _short_of_space() -> str | None:
    """Which of the install's folders (the checkout, the temporary folder) has less than
    :data:`INSTALL_BYTES` free, as a sentence; None if both have enough."""
    for where in (ROOT, Path(tempfile.gettempdir())):
        try:
            free = shutil.disk_usage(where).free
        except OSError:
            continue
        if free < INSTALL_BYTES:
            return (f"{where} has {free / 2 ** 30:.1f} GiB free; installing schlieren's environment "
                    f"needs about {INSTALL_BYTES / 2 ** 30:.0f} GiB (free some space, or point TMPDIR elsewhere)")
    return None


def _pip(cmd: list[str], attempts: int = 4) -> None:
    """Run a pip command, again after a failure: a download cut short by the network
    (pip gives up after a few resumes) is the usual cause, and what pip already fetched
    stays in its cache. A full disk is not retried: the failure names the folder."""
    for k in range(1, attempts + 1):
        if subprocess.call(cmd) == 0:
            return
        short = _short_of_space()
        if short:
            sys.exit(f"dev.py: `{' '.join(cmd[3:])}` failed: {short}")
        if k < attempts:
            print(f"dev.py: pip failed (attempt {k} of {attempts}); trying again in {10 * k} s", file=sys.stderr)
            time.sleep(10 * k)
    sys.exit(f"dev.py: `{' '.join(cmd[3:])}` failed {attempts} times; see pip's messages above")


def main(argv: list[str]) -> int:
    if not argv or argv[0] in {"-h", "--help"}:
        print(__doc__)
        return 0
    cmd, rest = argv[0], argv[1:]
    ensure_env(EXTRAS.get(cmd, EXTRAS["test"]))
    env = dict(os.environ)
    if cmd == "test":
        if rest[:1] == ["--fast"]:
            rest = ["-q", "-m", "not slow and not system"] + rest[1:]
        args = [str(BIN / "python"), "-m", "pytest"] + (rest or ["-q", "-m", "not slow"])
    elif cmd == "demo":
        args = [str(BIN / "schlieren"), "demo"] + rest
    elif cmd == "schlieren":
        args = [str(BIN / "schlieren")] + rest
    else:
        print(f"dev.py: unknown command {cmd!r} (demo, test, schlieren)", file=sys.stderr)
        return 2
    return subprocess.call(args, cwd=ROOT, env=env)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
