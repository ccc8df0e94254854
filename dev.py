#!/usr/bin/env python3
"""Bootstrap and run: needs only Python 3.11+.

    python3 dev.py demo [ARGS...]   # make .venv, install schlieren, run `schlieren demo`
    python3 dev.py test [ARGS...]   # same venv, run the default test suite (pytest)
    python3 dev.py schlieren ARGS   # any other schlieren command inside the venv

The virtual environment lives in .venv beside this file and is (re)installed whenever
pyproject.toml changes.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
STAMP = VENV / ".schlieren-installed"


def _digest() -> str:
    return hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()


def ensure_env() -> None:
    if sys.version_info < (3, 11):
        sys.exit(f"schlieren needs Python 3.11 or newer (this is {sys.version.split()[0]})")
    if not (BIN / "python").exists():
        print("dev.py: creating .venv", file=sys.stderr)
        venv.EnvBuilder(with_pip=True).create(VENV)
    if STAMP.exists() and STAMP.read_text() == _digest():
        return
    print("dev.py: installing schlieren and its dependencies into .venv", file=sys.stderr)
    pip = [str(BIN / "python"), "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.check_call(pip + ["install", "--upgrade", "pip"])
    subprocess.check_call(pip + ["install", "-e", f"{ROOT}[test,cluster,bench]"])
    STAMP.write_text(_digest())


def main(argv: list[str]) -> int:
    if not argv or argv[0] in {"-h", "--help"}:
        print(__doc__)
        return 0
    ensure_env()
    cmd, rest = argv[0], argv[1:]
    env = dict(os.environ)
    if cmd == "test":
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
