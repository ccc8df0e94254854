"""A Ctrl-C that is never lost.

SIGINT normally raises KeyboardInterrupt wherever the main thread happens to be. Raised
while Python runs a garbage-collection callback (distributed installs one) it is printed
as "Exception ignored" and dropped, and the run went on to the end. :class:`watch`
(entered by ``schlieren``'s ``main``) keeps Python's behaviour and also remembers the
signal; the executors' loops call :func:`check` between tasks, so a dropped interrupt
still stops the run at the next task boundary, with the usual one-line message.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading

__all__ = ["watch", "check", "seen"]

_SEEN = threading.Event()
_EVER = threading.Event()  # a watched Ctrl-C arrived in this process (never cleared: the callback
# that :class:`_SyncCancelAfterCtrlC` silences may run on distributed's loop thread after the run)


def seen() -> bool:
    """Whether a watched Ctrl-C arrived."""
    return _SEEN.is_set()


def check() -> None:
    """Raise KeyboardInterrupt if a watched Ctrl-C arrived (dropped on its way or not)."""
    if _SEEN.is_set():
        raise KeyboardInterrupt


class _SyncCancelAfterCtrlC(logging.Filter):
    """Closing noise after a watched Ctrl-C, in this process: distributed's ``sync``
    schedules a ``cancel`` callback when a Ctrl-C interrupts its wait; if the interrupt lands
    before the future it cancels exists, that callback raises NameError and tornado logs the
    traceback; and the in-process scheduler's batched stream to a worker the Ctrl-C is closing
    logs "Batched Comm Closed" with its CommClosedError traceback (races in distributed: each
    failed one CI run of the Ctrl-C test, tests/workers/test_diagnostics.py). After a watched
    Ctrl-C these records are noise: the caller prints its one line and every completed chunk
    is kept."""

    MESSAGES = ("sync.<locals>.cancel", "Batched Comm Closed")
    LOGGERS = ("tornado.application", "distributed.batched")

    def filter(self, record: logging.LogRecord) -> bool:
        return not (_EVER.is_set() and any(m in record.getMessage() for m in self.MESSAGES))


_SYNC_CANCEL_FILTER = _SyncCancelAfterCtrlC()


class watch:
    """Context manager: SIGINT raises KeyboardInterrupt and is remembered (:func:`check`).

    Only installed from the main thread over Python's own handler (an embedding program's
    handler is left alone). A remembered interrupt dropped in an "unraisable" context is not
    printed as a traceback (the caller prints its one line), nor is distributed's failed
    ``cancel`` callback after it (:class:`_SyncCancelAfterCtrlC`).
    """

    def __init__(self):
        self._previous = None
        self._hook = None

    def __enter__(self) -> "watch":
        _SEEN.clear()
        for name in _SyncCancelAfterCtrlC.LOGGERS:
            logging.getLogger(name).addFilter(_SYNC_CANCEL_FILTER)  # once: a set
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._previous = signal.signal(signal.SIGINT, _handler)
            self._hook = sys.unraisablehook
            sys.unraisablehook = self._unraisable
        return self

    def _unraisable(self, unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt) and _SEEN.is_set():
            return
        self._hook(unraisable)

    def __exit__(self, *exc) -> bool:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            sys.unraisablehook = self._hook
        _SEEN.clear()
        return False


def _handler(signum, frame) -> None:
    _SEEN.set()
    _EVER.set()
    raise KeyboardInterrupt
