"""Per-stage progress bars in the terminal (rich), fed by task receipts."""

from __future__ import annotations

import logging
import sys

from schlieren.pipeline.stages import STAGES

log = logging.getLogger(__name__)

__all__ = ["StageProgress"]


class StageProgress:
    """A rich progress bar per stage; a no-op when disabled or not on a terminal."""

    def __init__(self, *, enabled: bool = True, console=None):
        self.enabled = enabled and (console is not None or sys.stderr.isatty())
        self._console = console
        self._progress = None
        self._bars: dict[str, int] = {}
        self.failed = 0

    def __enter__(self):
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._progress = Progress(TextColumn("{task.description:<11}"), BarColumn(),
                                      MofNCompleteColumn(), TimeElapsedColumn(),
                                      console=self._console or Console(stderr=True), transient=False)
            self._progress.__enter__()
        return self

    def __exit__(self, *exc):
        if self._progress is not None:
            self._progress.__exit__(*exc)
        return False

    def plan(self, plan) -> None:
        counts = {s.name: 0 for s in STAGES}
        for t in plan.tasks:
            counts[t.stage] = counts.get(t.stage, 0) + len(t.indices)
        if self._progress is None:
            return
        for name, n in counts.items():
            if n:
                self._bars[name] = self._progress.add_task(name, total=n)

    def receipt(self, r: dict) -> None:
        log.debug("receipt %s", r)
        if self._progress is not None and r["stage"] in self._bars:
            self._progress.advance(self._bars[r["stage"]])

    def failure(self, key: str, message: str) -> None:
        self.failed += 1
        if not message.startswith("not run:"):
            log.error("%s", message)
