"""The files of the HTML report: what it reads from a result store, and how it is written.

No computation happens here: :mod:`schlieren.workers.report.build` asks a
:class:`ReportReader` for plain data (arrays, attributes, completion markers, the
:class:`~schlieren.pipeline.geometry.Grid`, the cameras and the medium), makes the
figures (:mod:`schlieren.workers.report.figures`) and residuals (:mod:`schlieren.pipeline.residuals`), and hands finished RGB images,
HTML sections and summary numbers to a :class:`ReportWriter`.

The reader tolerates a partial run: a missing array, a frame whose completion marker
``status/<stage>`` is unset, or a chunk left at its NaN fill value reads as ``None``.

Layout of the output folder::

    index.html
    figures/deflection_<camera>.png     paper Figure 4 for the shown frame
    figures/hull.png                    visual hull
    figures/slices_<quantity>.png       refractivity / temperature / density / |grad n|
    figures/render.png                  volume rendering of the shown frame, with colour bar
    figures/render_views.png            the same frame from four sides
    figures/render_strip.png            a row of frames (paper Figure 8)
    figures/render_<frame>.png          one rendering per frame
    figures/render.gif                  the renderings as an animation
    figures/residual_<camera>.png       measured vs re-projected deflections
    figures/timings.png                 per-stage wall-clock times
    summary.json                        the numbers on the page (residual RMS, what is missing)

:mod:`.reader` holds the reading side (:class:`ReportReader`, and the store helpers the
exports share: :func:`open_result`, :func:`volume_grid`, :func:`frame_range`), :mod:`.writer`
the writing side (:class:`ReportWriter`, :class:`ReportPage` and the HTML helpers).
"""

from schlieren.storage.layout import STORE_FORMAT
from schlieren.storage.report.reader import (
    EXPECTED_ARRAYS,
    VOLUME_ARRAYS,
    ReportReader,
    cameras_from_session,
    first_frame,
    frame_range,
    medium_from_session,
    open_result,
    volume_grid,
)
from schlieren.storage.report.writer import ReportPage, ReportWriter, fmt_number, html_img, html_table, safe_name

__all__ = ["ReportReader", "ReportWriter", "ReportPage", "html_img", "html_table", "fmt_number", "safe_name",
           "open_result", "volume_grid", "cameras_from_session", "medium_from_session", "frame_range", "first_frame",
           "EXPECTED_ARRAYS", "VOLUME_ARRAYS", "STORE_FORMAT"]
