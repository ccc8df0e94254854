"""Argument parsers shared by the subcommands (not a subcommand: the leading underscore
keeps it out of the CLI's discovery)."""

from __future__ import annotations

import argparse


def frame_range(text: str, flag: str = "--frames") -> tuple[int, int]:
    """``"A:B"`` -> ``(A, B)``, a non-empty half-open range starting at 0 or later."""
    from schlieren.workers.cli import CLIError

    try:
        a, b = text.split(":")
        a, b = int(a), int(b)
    except ValueError:
        raise CLIError(f"{flag} {text!r}: expected A:B with integers, e.g. 0:30") from None
    if a < 0 or b <= a:
        raise CLIError(f"{flag} {text!r}: the range must be non-empty and start at 0 or later")
    return a, b


def image_size(minimum: int = 16):
    """An argparse ``type`` for ``WIDTHxHEIGHT`` with both sides at least ``minimum``."""

    def parse(text: str) -> tuple[int, int]:
        try:
            w, h = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, not {text!r}") from None
        if w < minimum or h < minimum:
            raise argparse.ArgumentTypeError(f"size must be at least {minimum}x{minimum}")
        return w, h

    return parse


def int_at_least(low: int):
    """An argparse ``type`` for an integer of at least ``low``."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, not {text!r}") from None
        if n < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, not {n}")
        return n

    return parse


#: An argparse ``type`` for an integer of at least 1.
positive_int = int_at_least(1)
