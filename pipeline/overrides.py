"""The values a run takes in place of requested parameters, and where each comes from.

A run replaces some parameters by values derived from the session: the medium's
refractive index (``tomography.n_ambient``, ``direct.n_ambient``), the flow grid's factor
(``flow.factor`` with ``flow.auto_factor``), each camera's LK window (``flow.window`` with
``flow.window_per_voxel``) and the tomography's ray binning (``tomography.ray_binning`` 0);
the capture stage chooses each camera's pre-smoothing (``flow.presmooth: auto``) from its
reference;
a manifest without ``volume.voxel_size`` leaves the voxel to the cameras. The
regularisation stage chooses two more from the data on the middle frame: the weight
(``tomography.reg_weight`` with ``reg_choice: discrepancy``) and the widths of the
modelled flow averaging (``tomography.flow_window``, with ``model_flow_window``).

Each replacement is an :class:`Override`; the run logs its :meth:`~Override.line`
(``flow.window 17 -> 9 px from window_per_voxel 3.8 x 2.04 px per voxel``) and stores its
:meth:`~Override.record` in the store's root attribute ``derived`` (docs/store.md). The
parameters concerned say so where they are declared (``param(derived=...)``), and
``schlieren params`` and docs/parameters.md print it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from schlieren.pipeline.flow import camera_window, px_per_voxel
from schlieren.pipeline.flow.focus import AUTO
from schlieren.pipeline.geometry import FlowGrid, auto_voxel_size
from schlieren.pipeline.stages import RunConfig, bind_flow_factor, bind_medium
from schlieren.pipeline.tomography.binning import cells_per_voxel, ray_binning

__all__ = ["Override", "bind_run", "session_overrides", "regularisation_overrides", "presmooth_override",
           "records"]


@dataclass(frozen=True)
class Override:
    """A parameter the run replaced by a derived value.

    Attributes
    ----------
    path : str
        The parameter's dotted name (``flow.window``), or the manifest field
        (``volume.voxel_size``); ``tomography.flow_window`` names the regularisation
        stage's widths of the modelled flow averaging (stored ``flow_window``).
    requested : Any
        The value asked for (None: none given).
    effective : Any
        The value used: one number, or a list in camera order.
    unit : str
    source : str
        What it was derived from, in words.
    """

    path: str
    requested: Any
    effective: Any
    unit: str
    source: str

    def line(self) -> str:
        """One log line: ``flow.window 17 -> 9 px from window_per_voxel 3.8 x 2.04 px per voxel``
        (numbers to 6 significant digits, more where 6 would show two different values alike)."""
        unit = f" {self.unit}" if self.unit and self.unit != "1" else ""
        digits = 6
        while digits < 17 and self.requested != self.effective and \
                _show(self.requested, digits) == _show(self.effective, digits):
            digits += 1
        each = " per camera" if isinstance(self.effective, (list, tuple)) and len(set(self.effective)) > 1 else ""
        return (f"{self.path} {_show(self.requested, digits)} -> {_show(self.effective, digits)}{unit}{each} "
                f"from {self.source}")

    def record(self) -> dict:
        """The JSON-able entry of the store attribute ``derived``."""
        return {"requested": self.requested, "effective": self.effective, "unit": self.unit, "from": self.source}


def _show(v: Any, digits: int = 6) -> str:
    if v is None:
        return "(not given)"
    if isinstance(v, (list, tuple)):
        vals = sorted(set(v))
        lo, hi = _show(vals[0], digits), _show(vals[-1], digits)
        return lo if len(vals) == 1 else f"{lo}..{hi}"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _span(values, fmt: str = ".2f") -> str:
    """``2.04`` or ``2.04..2.62``: the range of per-camera values."""
    lo, hi = float(np.min(values)), float(np.max(values))
    return format(lo, fmt) if format(lo, fmt) == format(hi, fmt) else f"{lo:{fmt}}..{hi:{fmt}}"


def bind_run(config: RunConfig, cameras, grid, n_ambient: float) -> tuple[RunConfig, list[Override]]:
    """The configuration a run on ``cameras`` and ``grid`` takes (:func:`~schlieren.pipeline.stages.
    bind_medium`, :func:`~schlieren.pipeline.stages.bind_flow_factor`) and every
    :class:`Override` of it known before the run: the medium's ``n_ambient``, the flow
    grid's factor, the cameras' LK windows and the ray binning."""
    cfg = bind_flow_factor(bind_medium(config, n_ambient), cameras, grid)
    out = [Override(f"{g}.n_ambient", getattr(config, g).n_ambient, getattr(cfg, g).n_ambient, "1",
                    "the session's medium.n_ambient") for g in ("tomography", "direct")]
    if config.flow.auto_factor:
        def cells(factor: int) -> float:
            return cells_per_voxel(cameras, grid, FlowGrid(cameras[0].image_size, factor))

        kept = "" if cfg.flow.factor == config.flow.factor else \
            f"; {config.flow.factor} would leave {cells(config.flow.factor):.2f}"
        out.append(Override("flow.factor", config.flow.factor, cfg.flow.factor, "px per flow cell",
                            f"auto_factor ({cells(cfg.flow.factor):.2f} flow cells per voxel edge{kept})"))
    fp = cfg.flow
    if fp.window_per_voxel > 0:
        windows = [camera_window(c, grid, window=fp.window, window_per_voxel=fp.window_per_voxel) for c in cameras]
        px = [px_per_voxel(c, grid) for c in cameras]
        out.append(Override("flow.window", fp.window, windows, "px",
                            f"window_per_voxel {fp.window_per_voxel:g} x {_span(px)} px per voxel"))
    if config.tomography.ray_binning == 0:
        fg = FlowGrid(cameras[0].image_size, cfg.flow_factor)
        b = ray_binning(cameras, grid, fg, 0)
        out.append(Override("tomography.ray_binning", 0, b, "flow cells",
                            f"{cells_per_voxel(cameras, grid, fg):.2f} flow cells per voxel edge (at least "
                            "1.25 rays per voxel edge)"))
    return cfg, out


def session_overrides(cameras, grid, *, voxel_size_given: bool) -> list[Override]:
    """The session's own derived value: the voxel from the cameras' pixel footprint
    (:func:`~schlieren.pipeline.geometry.auto_voxel_size`) when the manifest gives none."""
    if voxel_size_given:
        return []
    _, info = auto_voxel_size(cameras, grid.vmin, grid.vmax)
    return [Override("volume.voxel_size", None, float(grid.voxel_size), "m",
                     f"the cameras' pixel footprint ({info['px_per_voxel']:.2f} px per voxel, limited by "
                     f"{info['limited_by']})")]


def regularisation_overrides(config: RunConfig, reg_weight: float, flow_window, noise=None,
                             frame: int | None = None) -> list[Override]:
    """The values the regularisation stage chose (stored ``reg_weight`` and ``flow_window``)
    as overrides of ``config`` (the run's bound configuration): the weight with
    ``reg_choice: discrepancy``, the per-camera widths with ``model_flow_window``."""
    t = config.tomography
    out = []
    if t.reg_choice == "discrepancy":
        measured = noise is not None and np.all(np.isfinite(noise)) and np.any(np.asarray(noise) != 0)
        where = f" on frame {frame}" if frame is not None else ""
        source = (f"the discrepancy principle{where} (reg_tau {t.reg_tau:g})" if measured else
                  "no noise measurable outside the masks: the requested weight")
        out.append(Override("tomography.reg_weight", t.reg_weight, float(reg_weight), "1", source))
    if t.model_flow_window:
        out.append(Override("tomography.flow_window", None, [float(v) for v in np.asarray(flow_window)],
                            "flow cells", f"each camera's flow averaging (measurement_sigma of its flow.window) x "
                                          f"flow_window_scale {t.flow_window_scale:g}"))
    return out


def presmooth_override(config: RunConfig, presmooth) -> list[Override]:
    """The cameras' pre-smoothing the capture stage chose (stored ``presmooth``, camera
    order) as an override of ``config`` with ``flow.presmooth: auto``."""
    if config.flow.presmooth != AUTO:
        return []
    return [Override("flow.presmooth", AUTO, [float(v) for v in np.asarray(presmooth)], "px",
                     "the sharpness of each camera's reference (pipeline/flow/focus.py)")]


def records(overrides) -> dict:
    """``{path: record}`` of ``overrides`` (the store attribute ``derived``)."""
    return {o.path: o.record() for o in overrides}

