"""Small helpers the report's sections share: lenient dict access, figure hand-off, finite numbers."""

from __future__ import annotations

import math

from schlieren.storage.report import ReportWriter
from schlieren.workers.report.figures import figure_to_rgb


def _get(d: dict, key: str, default=None):
    return d.get(key, default) if isinstance(d, dict) else default


def _figure(writer: ReportWriter, name: str, fig) -> str:
    """Draw a Matplotlib figure to RGB, hand it to the writer, free it; returns the relative link."""
    rgb = figure_to_rgb(fig)
    fig.clear()
    return writer.image(name, rgb)


def _finite(x) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None
