"""The report's output folder: figures, the HTML page and ``summary.json``.

:class:`ReportWriter` writes finished RGB images and animations under ``figures/`` and the
page (:class:`ReportPage`: sections of HTML built with :func:`html_img` and
:func:`html_table`) as ``index.html``, with the summary numbers beside it. No computation
happens here.
"""


from __future__ import annotations

import html
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------
# The page (HTML markup) and the files
# ---------------------------------------------------------------------------------------


def html_img(rel: str, alt: str, caption: str | None = None) -> str:
    """A linked ``<figure>`` for the image at relative path ``rel``."""
    cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
    return (f'<figure><a href="{html.escape(rel)}"><img src="{html.escape(rel)}" '
            f'alt="{html.escape(alt)}"></a>{cap}</figure>')


def html_table(header: list[str], rows: list[list], cls: str = "") -> str:
    """An HTML table; cells are escaped; no ``<thead>`` if every header cell is empty."""
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    head = f"<thead><tr>{h}</tr></thead>" if any(header) else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}">{head}<tbody>{body}</tbody></table>'


def fmt_number(x, digits: int = 4) -> str:
    """``x`` with ``digits`` significant digits; ``n/a`` if not finite; ``str(x)`` if not a number."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(x):
        return "n/a"
    return f"{x:.{digits}g}"


def safe_name(name: str) -> str:
    """``name`` with every character other than letters, digits, ``-`` and ``_`` replaced by ``_``."""
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1400px; padding: 0 1.5em;
       color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.6em; }
nav a { margin-right: 1em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
table { border-collapse: collapse; margin: 0.8em 0; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
table.num td:not(:first-child) { text-align: right; font-variant-numeric: tabular-nums; }
.missing { color: #a33; } pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }
"""


@dataclass
class ReportPage:
    """The report page being assembled: sections (HTML fragments), what is missing, summary numbers.

    Attributes
    ----------
    title : str
    sections : list of str
        ``<section>`` elements in page order.
    missing : list of str
        Listed at the top of the page and in ``summary.json``.
    summary : dict
        Written to ``summary.json`` (JSON-serialisable; numpy scalars are converted).
    anchors : list of (anchor, heading)
        The navigation bar.
    """

    title: str
    sections: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    anchors: list[tuple[str, str]] = field(default_factory=list)

    def add(self, heading: str, body: str, anchor: str) -> None:
        """Append a section titled ``heading`` (escaped) with HTML ``body``, linked as ``#anchor``."""
        self.anchors.append((anchor, heading.split(" (")[0]))
        self.sections.append(f'<section id="{anchor}"><h2>{html.escape(heading)}</h2>\n{body}\n</section>')

    def to_html(self) -> str:
        """The whole page as an HTML document."""
        missing = ""
        if self.missing:
            missing = ("<p class='missing'>Missing from the store (partial run?): "
                       + ", ".join(html.escape(m) for m in self.missing) + ".</p>")
        nav = " ".join(f'<a href="#{a}">{html.escape(t)}</a>' for a, t in self.anchors)
        return (
            "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head><body>\n"
            f"<h1>{html.escape(self.title)}</h1>\n<nav>{nav}</nav>\n{missing}\n"
            + "\n".join(self.sections) + "\n</body></html>\n")


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return None if not np.isfinite(o) else float(o)
    return str(o)


class ReportWriter:
    """Writes the report's files under ``out_dir``: ``figures/*.png``, ``figures/*.gif``,
    ``index.html`` and ``summary.json``.

    Creating the writer creates ``out_dir/figures`` and deletes the PNG and GIF files an
    earlier report left there, so the folder holds only this report's figures.

    Parameters
    ----------
    out_dir : path
        Created if needed; files in it are overwritten.
    """

    def __init__(self, out_dir: str | os.PathLike):
        self.out = Path(out_dir)
        self.figdir = self.out / "figures"
        self.figdir.mkdir(parents=True, exist_ok=True)
        for old in list(self.figdir.glob("*.png")) + list(self.figdir.glob("*.gif")):  # an earlier report's
            old.unlink()

    def _target(self, name: str) -> Path:
        if Path(name).name != name:
            raise ValueError(f"figure name must be a plain file name, got {name!r}")
        return self.figdir / name

    def image(self, name: str, rgb: np.ndarray) -> str:
        """Write ``figures/<name>`` (PNG) from an RGB(A) uint8 image; returns its relative link.

        Parameters
        ----------
        name : str
            File name ending in ``.png``.
        rgb : ndarray, shape (H, W, 3) or (H, W, 4), uint8
        """
        import imageio.v3 as iio

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[-1] not in (3, 4) or rgb.dtype != np.uint8:
            raise ValueError(f"expected an (H, W, 3|4) uint8 image, got {rgb.shape} {rgb.dtype}")
        iio.imwrite(self._target(name), rgb)
        return f"figures/{name}"

    def animation(self, name: str, frames: np.ndarray, *, fps: float) -> str:
        """Write ``figures/<name>`` as a looping GIF; returns its relative link.

        Parameters
        ----------
        frames : ndarray, shape (n, H, W, 3), uint8
        fps : float
            Frames per second (stored as a per-frame duration in whole milliseconds).
        """
        import imageio.v3 as iio

        frames = np.asarray(frames)
        if frames.ndim != 4 or frames.dtype != np.uint8:
            raise ValueError(f"expected (n, H, W, 3) uint8 frames, got {frames.shape} {frames.dtype}")
        iio.imwrite(self._target(name), frames, duration=int(1000 / fps), loop=0)
        return f"figures/{name}"

    def finish(self, page: ReportPage) -> Path:
        """Write ``index.html`` and ``summary.json`` (the page's summary plus the list of figures).

        Returns
        -------
        Path
            ``out_dir / "index.html"``.
        """
        index = self.out / "index.html"
        index.write_text(page.to_html(), encoding="utf-8")
        summary = dict(page.summary)
        summary["figures"] = sorted(str(p.relative_to(self.out)) for p in self.figdir.iterdir())
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default),
                                               encoding="utf-8")
        log.info("report written to %s", index)
        return index
