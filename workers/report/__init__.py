"""The HTML report of a result store, and the figures and volume renderings it shows.

* :mod:`.make` - the commands' glue: default output folders, :func:`make_report`,
  :func:`generate_export`.
* :mod:`.build` - :func:`build_report`: reads via :mod:`schlieren.storage.report`, computes
  via :mod:`schlieren.pipeline`, writes via storage; the page's tables.
* :mod:`.sections`, :mod:`.residual_section` - the page's figure sections and its
  re-projection residuals.
* :mod:`.figures` - camera-plane figures (deflection colour coding, quiver plots, paper
  Figure 4; residuals; timings); :mod:`.volume_figures` - slices, the hull, a rendering
  with its colour bar.
* :mod:`.volume_render` - emission-absorption ray marching of the refractivity (paper
  Figures 1 and 8), its numba kernel in :mod:`._kernels`.

Drawing lives here, beside the report that uses it, not in the kernel layer
(:mod:`schlieren.pipeline`): matplotlib on the Agg canvas, never ``pyplot``.
"""

from schlieren.workers.report.build import build_report
from schlieren.workers.report.make import default_export_dir, default_report_dir, generate_export, make_report
from schlieren.workers.report.residual_section import MAX_RESIDUAL_FRAMES
from schlieren.workers.report.sections import STRIP_FRAMES

__all__ = ["default_report_dir", "default_export_dir", "make_report", "generate_export", "build_report",
           "MAX_RESIDUAL_FRAMES", "STRIP_FRAMES"]
