"""Glue for the result-viewing commands: report and export of a finished (or partial) run.

Both read the store directly (no Dask needed: the figures are small and the per-camera
forward operators are built once); these functions only choose default output paths and
log, so that ``schlieren report``, ``schlieren export`` and ``schlieren demo`` share them.
The report itself is built by :func:`schlieren.workers.report.build.build_report`
(reads via :mod:`schlieren.storage.report`, computes via :mod:`schlieren.pipeline` and
draws with the figure modules beside it).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from schlieren.storage import location
from schlieren.storage.export import ExportResult, export
from schlieren.workers.report.build import build_report

__all__ = ["default_report_dir", "default_export_dir", "make_report", "generate_export", "build_report"]

log = logging.getLogger(__name__)


def _stem(store) -> Path:
    """``/data/run.zarr`` -> ``/data/run``; a store at a URL -> ``./run`` (outputs are local files)."""
    loc = location.normalize(store)
    store = Path(location.basename(loc)).resolve() if location.is_url(loc) else Path(loc).resolve()
    return store.with_suffix("") if store.suffix else store


def default_report_dir(store: str | os.PathLike) -> Path:
    """``run.zarr`` -> ``run_report/`` beside the store."""
    s = _stem(Path(store))
    return s.with_name(s.name + "_report")


def default_export_dir(store: str | os.PathLike, format: str) -> Path:
    """``run.zarr`` -> ``run_<format>/`` beside the store."""
    s = _stem(Path(store))
    return s.with_name(f"{s.name}_{format}")


def make_report(store: str | os.PathLike, out_dir: str | os.PathLike | None = None, *,
                evaluation: dict | None = None, frames: tuple[int, int] | None = None,
                max_cameras: int | None = None) -> Path:
    """Write the HTML report of ``store``; returns the path of ``index.html``.

    Parameters
    ----------
    store : path
        The result store.
    out_dir : path, optional
        Default: :func:`default_report_dir`.
    evaluation : dict, optional
        :func:`schlieren.workers.evaluate.evaluate` output, shown as an accuracy table.
    frames : (a, b), optional
        Half-open range of store frames.
    max_cameras : int, optional
        Per-camera figures for the first cameras only.
    """
    out = Path(out_dir) if out_dir is not None else default_report_dir(store)
    index = build_report(store, out, frames=frames, max_cameras=max_cameras, evaluation=evaluation)
    log.info("report of %s: %s", store, index)
    return index


def generate_export(store: str | os.PathLike, out_dir: str | os.PathLike | None = None, *, format: str = "vti",
                    quantity: str = "refractivity", frames: tuple[int, int] | None = None) -> ExportResult:
    """Export one quantity of ``store``; returns what was written."""
    out = Path(out_dir) if out_dir is not None else default_export_dir(store, format)
    res = export(store, out, format=format, quantity=quantity, frames=frames)
    log.info("exported %s of %s to %s (%d files)", quantity, store, out, len(res.files))
    return res
