"""Monitoring helpers: log formats, task receipts, performance reports.

Two formats, one per destination: on a console (the CLI's stderr, a local cluster's
workers' stderr) plain lines ``LEVEL logger: message`` (:class:`PlainFormatter`); in
files (``--log``, a cluster's worker log folder) one JSON object per line
(:class:`JsonFormatter`), carrying the task context fields (session, stage, camera,
frame, index, key, seconds, iterations, residual, ...) when they are passed in ``extra``. :func:`log_receipt` turns a task's small receipt
dict into such a line. :func:`performance_report_cm` wraps
``distributed.performance_report`` so callers can write ``with performance_report_cm(path):``
whether or not a report was asked for.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import math
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, TextIO

log = logging.getLogger(__name__)

RECEIPT_LOGGER = "schlieren.receipts"

#: Context fields copied from a record's ``extra`` into the JSON object, in this order.
CONTEXT_FIELDS: tuple[str, ...] = (
    "session",
    "stage",
    "key",
    "index",
    "camera",
    "frame",
    "seconds",
    "cpu_seconds",
    "iterations",
    "residual",
    "status",
    "worker",
    "error",
)

# Attributes every LogRecord has; anything else on a record came from ``extra``.
_RECORD_ATTRS = frozenset(vars(logging.LogRecord("x", logging.INFO, "x", 0, "x", None, None))) | {
    "message",
    "asctime",
    "taskName",
}


def _jsonable(value: Any) -> Any:
    """Plain JSON value for numpy scalars, paths, tuples; NaN/inf become strings."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    item = getattr(value, "item", None)  # numpy scalar / 0-d array
    if callable(item) and getattr(value, "ndim", 0) == 0:
        try:
            return _jsonable(item())
        except (TypeError, ValueError):
            pass
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return str(value)


class PlainFormatter(logging.Formatter):
    """``LEVEL logger: message``, plus what a task receipt is about (``-v``): stage, camera,
    frame, seconds and the stage's own numbers, instead of a bare "task receipt"."""

    FIELDS = ("camera", "frame", "seconds", "iterations", "residual", "voxels", "fraction", "max_px", "error")

    def __init__(self, fmt: str = "%(levelname)s %(name)s: %(message)s"):
        super().__init__(fmt)

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        stage = getattr(record, "stage", None)
        if stage is None:
            return text
        parts = [f"stage {stage}"]
        for name in self.FIELDS:
            v = getattr(record, name, None)
            if v is None:
                continue
            if isinstance(v, float):
                v = f"{v:.4g}" + (" s" if name == "seconds" else "")
            parts.append(f"{name} {v}")
        return f"{text}: " + ", ".join(parts)


class JsonFormatter(logging.Formatter):
    """Format a log record as one JSON object on one line.

    The object has ``time`` (UTC, ISO 8601), ``level``, ``logger``, ``message``, then the
    :data:`CONTEXT_FIELDS` found on the record (from ``logger.info(..., extra={...})``),
    then any other ``extra`` fields, then ``exc_info`` text if an exception is attached.
    """

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": _dt.datetime.fromtimestamp(record.created, _dt.timezone.utc).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for name in CONTEXT_FIELDS:
            if hasattr(record, name):
                out[name] = _jsonable(getattr(record, name))
        for name, value in vars(record).items():
            if name not in _RECORD_ATTRS and name not in out and not name.startswith("_"):
                out[name] = _jsonable(value)
        if record.exc_info:
            out["exc_info"] = self.formatException(record.exc_info)
        return json.dumps(out, separators=(",", ":"), sort_keys=False)


_HANDLER_MARK = "_schlieren_json_handler"


def configure_json_logging(
    logger_name: str = "schlieren",
    *,
    level: int | str = logging.INFO,
    stream: TextIO | None = None,
    path: str | os.PathLike[str] | None = None,
) -> logging.Handler:
    """Attach one JSON-lines handler to ``logger_name`` (idempotent).

    Writes to ``path`` (appending) when given, else to ``stream`` (default stderr). A
    handler attached earlier by this function to the same logger is replaced, so calling
    it again (e.g. when a worker plugin is re-registered) never duplicates lines. The
    logger stops propagating to the root logger so lines are not printed twice.

    Returns
    -------
    logging.Handler
        The handler now attached.
    """
    logger = logging.getLogger(logger_name)
    for h in list(logger.handlers):
        if getattr(h, _HANDLER_MARK, False):
            logger.removeHandler(h)
            h.close()
    handler: logging.Handler
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(path, mode="a", encoding="utf-8")
    else:
        handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    setattr(handler, _HANDLER_MARK, True)
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    return handler


def configure_worker_logging(
    logger_name: str = "schlieren",
    *,
    level: int | str = logging.INFO,
    path: str | os.PathLike[str] | None = None,
    stream: TextIO | None = None,
) -> logging.Handler:
    """A worker process's logging: JSON lines appended to ``path`` (a log folder's file),
    else plain lines (:class:`PlainFormatter`) on ``stream`` (default stderr, which for a
    local cluster is the user's console). Idempotent like :func:`configure_json_logging`."""
    if path is not None:
        return configure_json_logging(logger_name, level=level, path=path)
    handler = configure_json_logging(logger_name, level=level, stream=stream)
    handler.setFormatter(PlainFormatter())
    return handler


def log_receipt(
    receipt: Mapping[str, Any],
    *,
    logger: logging.Logger | None = None,
    level: int = logging.INFO,
    message: str = "task receipt",
) -> None:
    """Log a task's receipt as one structured line.

    Parameters
    ----------
    receipt : mapping
        The small dict a task returns: e.g. ``stage``, ``index``, ``camera``, ``frame``,
        ``seconds``, ``iterations``, ``residual``, ``key``. Keys that clash with
        ``LogRecord`` attributes (``name``, ``msg``, ...) are prefixed with ``receipt_``.
    logger : logging.Logger, optional
        Defaults to the ``schlieren.receipts`` logger.
    level : int
        Logging level; failed receipts (``status == "failed"`` or an ``error`` entry) are
        logged at ERROR regardless.
    """
    lg = logger if logger is not None else logging.getLogger(RECEIPT_LOGGER)
    failed = receipt.get("status") == "failed" or bool(receipt.get("error"))
    lg.log(logging.ERROR if failed else level, message, extra=_extra(receipt))


def _extra(fields: Mapping[str, Any]) -> dict[str, Any]:
    """``fields`` as a ``LogRecord`` ``extra``: JSON-able, clashing names prefixed ``receipt_``."""
    extra: dict[str, Any] = {}
    for k, v in fields.items():
        name = str(k)
        if name in _RECORD_ATTRS:
            name = f"receipt_{name}"
        extra[name] = _jsonable(v)
    return extra


class RunLog:
    """The JSON-lines log of one run (``--log FILE``), written by the client process.

    One line per task receipt (stage, index, camera, frame, seconds, cpu_seconds, worker,
    and the stage's own fields such as tomography's iterations and residual), one ERROR
    line per failed or not-run task, and a closing ``run finished`` line. The receipts
    come back to the client in every mode (local, external scheduler, batch cluster,
    serial loop), so this one file covers them all; lines are appended.
    """

    def __init__(self, path: str | os.PathLike[str] | None, *, session: str | None = None):
        self.path = None if path is None else Path(path)
        self.session = session
        self._logger: logging.Logger | None = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            lg = logging.Logger("schlieren.run", logging.INFO)  # standalone: no parent, no global state
            handler = logging.FileHandler(self.path, mode="a", encoding="utf-8")
            handler.setFormatter(JsonFormatter())
            lg.addHandler(handler)
            self._logger = lg

    def _context(self, fields: Mapping[str, Any]) -> dict[str, Any]:
        return {"session": self.session, **fields} if self.session else dict(fields)

    def receipt(self, receipt: Mapping[str, Any]) -> None:
        if self._logger is not None:
            log_receipt(self._context(receipt), logger=self._logger)

    def failure(self, key: str, message: str) -> None:
        if self._logger is not None:
            log_receipt(self._context({"stage": key.split("-", 1)[0], "key": key, "status": "failed",
                                       "error": message}), logger=self._logger, message="task failed")

    def finished(self, **fields: Any) -> None:
        if self._logger is not None:
            self._logger.info("run finished", extra=_extra(self._context(fields)))

    def close(self) -> None:
        if self._logger is not None:
            for h in list(self._logger.handlers):
                self._logger.removeHandler(h)
                h.close()
            self._logger = None

    def __enter__(self) -> "RunLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def performance_report_cm(path: str | os.PathLike[str] | None, *, stacklevel: int = 1) -> Iterator[Path | None]:
    """Write a Dask performance report (HTML) of everything computed inside the block.

    Needs a current ``distributed.Client`` (the default client). With ``path=None``
    this does nothing. The parent directory is created.

    Yields
    ------
    Path or None
        The report path.
    """
    if path is None:
        yield None
        return
    from distributed import performance_report

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with performance_report(filename=os.fspath(p), stacklevel=stacklevel + 1, mode="inline"):  # offline-readable
        yield p
    log.info("performance report written to %s", p)
