"""The ``schlieren`` command line.

Every module in :mod:`schlieren.workers.commands` contributes one subcommand by defining
``add_parser(subparsers)``, which creates its parser and sets ``func`` to a handler
``handler(args) -> int`` (the exit code). Handlers raise :class:`CLIError` (or any
error with a one-line message listed in ``USER_ERRORS``) for bad input: the CLI prints
that line, without a traceback, and exits non-zero.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from schlieren.workers import commands as _commands
from schlieren.workers.monitoring import PlainFormatter

log = logging.getLogger("schlieren")


class CLIError(Exception):
    """An error whose message is meant for the user as it is (one line)."""


def _user_error_types() -> tuple[type[BaseException], ...]:
    types: list[type[BaseException]] = [CLIError]
    try:  # the session/store errors are defined in storage; they carry file/camera/field
        from schlieren.storage.errors import SchlierenInputError

        types.append(SchlierenInputError)
    except ImportError:
        pass
    return tuple(types)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="schlieren",
        description="Time-resolved 3D Background Oriented Schlieren tomography.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{_commands.__name__}.{info.name}")
        add = getattr(module, "add_parser", None)
        if add is not None:
            add(sub)
    return parser


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (safe under test capture)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):  # StreamHandler.__init__ assigns it; we always look it up
        pass


def _configure_logging(verbose: int) -> None:
    logger = logging.getLogger("schlieren")
    logger.setLevel(logging.WARNING - 10 * min(verbose, 2))
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        h = _StderrHandler()
        h.setFormatter(PlainFormatter())
        logger.addHandler(h)
    logger.propagate = False


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse printed the usage error (or --help): return its code
        return exc.code if isinstance(exc.code, int) else 2
    _configure_logging(args.verbose)
    from schlieren.workers import interrupts

    try:
        with interrupts.watch():  # a Ctrl-C dropped on its way still stops the run (interrupts.check)
            return int(args.func(args) or 0)
    except _user_error_types() as exc:
        print(f"schlieren {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a read-only folder: one line, not a traceback
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        print(f"schlieren {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"schlieren {args.command}: interrupted; completed chunks are kept", file=sys.stderr)
        return 130
    finally:
        _settle_zarr()


def _settle_zarr() -> None:
    """No zarr operation left running when the process exits (storage/inflight.py)."""
    if "zarr" in sys.modules:
        from schlieren.storage.inflight import settle

        settle(timeout=10.0)


if __name__ == "__main__":  # pragma: no cover
    # run the imported module, not this __main__ copy, so CLIError is one class everywhere
    from schlieren.workers.cli import main as _main

    sys.exit(_main())
