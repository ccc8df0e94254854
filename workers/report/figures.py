"""Report figures of the camera plane: deflection colour coding, quiver plots, residuals, timings.

Pure functions: arrays in, RGB ``uint8`` arrays or matplotlib :class:`~matplotlib.figure.Figure`
objects out (built on the Agg canvas, never through ``pyplot``, so no global state and no
display). Nothing here writes files: :mod:`schlieren.storage.report` saves what the report
builder (:mod:`schlieren.workers.report.build`) draws with these.

* :func:`flow_to_rgb`: the optical-flow colour wheel of Baker et al. (2011, the Middlebury
  benchmark), as in the paper's Figure 4 (top centre): hue = direction, saturation =
  magnitude.
* :func:`quiver_figure`, :func:`deflection_figure`: the paper's Figure 4 (camera image,
  colour coding, quiver plot; integrated deflections, threshold and mask).
* :func:`residual_figure`: measured against re-projected deflections of one camera frame.
* :func:`timings_figure`: wall-clock seconds per stage.
* :func:`figure_to_rgb`: the pixels of a figure.

Volume slices, the hull and the rendering's colour bar are in
:mod:`schlieren.workers.report.volume_figures`; the volume renderer itself in
:mod:`schlieren.workers.report.volume_render`.
"""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

__all__ = [
    "flow_to_rgb",
    "flow_wheel",
    "figure_to_rgb",
    "quiver_figure",
    "deflection_figure",
    "residual_figure",
    "timings_figure",
]


# ---------------------------------------------------------------------------------------
# Optical-flow colour coding
# ---------------------------------------------------------------------------------------

def _colour_wheel() -> np.ndarray:
    """The 55 hues of the Middlebury flow colour wheel, shape (55, 3), values 0..1.

    Segments (Baker et al. 2011): red-yellow 15, yellow-green 6, green-cyan 4,
    cyan-blue 11, blue-magenta 13, magenta-red 6; each ramps one channel linearly.
    """
    segments = [(15, 0, 1, +1), (6, 1, 0, -1), (4, 1, 2, +1), (11, 2, 1, -1), (13, 2, 0, +1),
                (6, 0, 2, -1)]
    # (length, the channel at full, the channel that ramps, ramp direction)
    rows = []
    for length, full, ramp, sign in segments:
        frac = np.floor(255.0 * np.arange(length) / length) / 255.0
        seg = np.zeros((length, 3))
        seg[:, full] = 1.0
        seg[:, ramp] = frac if sign > 0 else 1.0 - frac
        rows.append(seg)
    return np.concatenate(rows, axis=0)


_WHEEL = _colour_wheel()


def flow_to_rgb(flow: np.ndarray, *, max_magnitude: float | None = None) -> np.ndarray:
    """Colour-code a 2-D deflection field (Baker et al. 2011 colour wheel).

    Parameters
    ----------
    flow : ndarray, shape (H, W, 2)
        Deflections in pixels, component 0 = u (image x, right), 1 = v (image y, down).
    max_magnitude : float, optional
        Magnitude (pixels) shown fully saturated; larger vectors are saturated and darkened
        to 75 %. Defaults to the largest finite magnitude in ``flow``.

    Returns
    -------
    rgb : ndarray, shape (H, W, 3), uint8
        White for zero flow; hue gives the direction (right = red, down = yellow-orange,
        left = cyan-blue, up = blue-violet), saturation the magnitude. NaN pixels are black.
    """
    flow = np.asarray(flow, dtype=np.float64)
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise ValueError(f"flow must have shape (H, W, 2), got {flow.shape}")
    u, v = flow[..., 0], flow[..., 1]
    bad = ~(np.isfinite(u) & np.isfinite(v))
    u = np.where(bad, 0.0, u)
    v = np.where(bad, 0.0, v)
    mag = np.hypot(u, v)
    if max_magnitude is None:
        max_magnitude = float(mag.max()) if mag.size else 0.0
    if not max_magnitude > 0:
        max_magnitude = 1.0
    rad = mag / max_magnitude
    ncols = len(_WHEEL)
    angle = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    # the full circle maps onto [0, ncols) and the last hue blends into the first, so the
    # wheel has no seam at +-pi (the reference code's (ncols - 1) leaves a jump there)
    fk = (angle + 1.0) / 2.0 * ncols
    k0 = np.floor(fk).astype(np.int64) % ncols
    k1 = (k0 + 1) % ncols
    f = (fk - np.floor(fk))[..., None]
    col = (1.0 - f) * _WHEEL[k0] + f * _WHEEL[k1]
    inside = (rad <= 1.0)[..., None]
    col = np.where(inside, 1.0 - rad[..., None] * (1.0 - col), 0.75 * col)
    col[bad] = 0.0
    return np.clip(np.round(255.0 * col), 0, 255).astype(np.uint8)


def flow_wheel(size: int = 101) -> np.ndarray:
    """The colour key of :func:`flow_to_rgb`: a disc whose rim is the saturated wheel.

    Returns
    -------
    rgb : ndarray, shape (size, size, 3), uint8; white outside the disc.
    """
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    flow = np.stack([(xx - c) / c, (yy - c) / c], axis=-1)
    rgb = flow_to_rgb(flow, max_magnitude=1.0)
    rgb[np.hypot(*np.moveaxis(flow, -1, 0)) > 1.0] = 255
    return rgb


# ---------------------------------------------------------------------------------------
# Figures (Agg canvas, no pyplot)
# ---------------------------------------------------------------------------------------

def _new_figure(width_in: float, height_in: float, dpi: int = 100) -> Figure:
    fig = Figure(figsize=(width_in, height_in), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def figure_to_rgb(fig: Figure) -> np.ndarray:
    """Draw a figure on its Agg canvas and return the pixels, shape (H, W, 3) uint8."""
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _flow_positions(image_shape, flow_shape) -> tuple[np.ndarray, np.ndarray, int]:
    """Image coordinates of flow-grid cell centres (``FlowGrid`` convention) and the factor.

    The factor is the integer ``f`` with ``flow columns = image width // f`` (the image may
    have a remainder of fewer than ``f`` pixels that no cell covers).
    """
    h_img, w_img = image_shape[:2]
    rows, cols = flow_shape[:2]
    factor = max(1, int(round(w_img / cols)))
    u = factor * np.arange(cols) + (factor - 1.0) / 2.0
    v = factor * np.arange(rows) + (factor - 1.0) / 2.0
    return u, v, factor


def _draw_quiver(ax, image, flow, *, step: int, exaggeration: float | None = None,
                 colour: str = "#ffcc00"):
    flow = np.asarray(flow, dtype=np.float64)
    if image is None:
        image = np.zeros(flow.shape[:2])
    image = np.asarray(image)
    u_pos, v_pos, factor = _flow_positions(image.shape, flow.shape)
    step = max(int(step), 1)
    sel_r = np.arange(step // 2, flow.shape[0], step)
    sel_c = np.arange(step // 2, flow.shape[1], step)
    U = flow[np.ix_(sel_r, sel_c)][..., 0]
    V = flow[np.ix_(sel_r, sel_c)][..., 1]
    X, Y = np.meshgrid(u_pos[sel_c], v_pos[sel_r])
    mag = np.hypot(U, V)
    finite = np.isfinite(mag)
    if exaggeration is None:
        ref = float(np.percentile(mag[finite], 99)) if finite.any() else 0.0
        spacing = step * factor
        exaggeration = 0.9 * spacing / ref if ref > 0 else 1.0
    # a low-contrast background so that the arrows stand out against a noise pattern
    img = np.asarray(image, dtype=np.float64)
    finite_img = img[np.isfinite(img)]
    lo, hi = (np.percentile(finite_img, [1, 99]) if finite_img.size else (0.0, 1.0))
    img = np.clip((img - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
    ax.imshow(0.3 + 0.35 * img, cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
    # angles="xy" + scale_units="xy" with scale=1/exaggeration: an arrow spans
    # exaggeration * delta image pixels, pointing along +u right, +v down (image axes).
    q = ax.quiver(X, Y, U, V, angles="xy", scale_units="xy", scale=1.0 / exaggeration,
                  color=colour, width=0.006, headwidth=3.5, headlength=4.0, edgecolor="k",
                  linewidth=0.4)
    ax.set_xlim(-0.5, image.shape[1] - 0.5)
    ax.set_ylim(image.shape[0] - 0.5, -0.5)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    return q, exaggeration


def quiver_figure(image: np.ndarray | None, flow: np.ndarray, *, step: int = 8,
                  exaggeration: float | None = None, title: str | None = None) -> Figure:
    """Quiver plot of deflections over the camera image (paper Figure 4, top right).

    Parameters
    ----------
    image : ndarray, shape (H, W) or None
        Camera frame (grey levels, any range) at full resolution; ``None`` draws on black.
    flow : ndarray, shape (h, w, 2)
        Deflections in image pixels on the flow grid (``FlowGrid`` cells of
        ``factor = W / w`` image pixels; arrows start at the cell centres).
    step : int
        Draw every ``step``-th flow-grid cell in each direction.
    exaggeration : float, optional
        Arrow length / deflection. Defaults to a value that makes the 99th-percentile
        arrow 0.9 of the arrow spacing (BOS deflections are sub-pixel).
    title : str, optional

    Returns
    -------
    Figure
        One axes in image pixel coordinates; the title states the exaggeration.
    """
    fig = _new_figure(6.4, 5.2)
    ax = fig.add_subplot()
    _, ex = _draw_quiver(ax, image, flow, step=step, exaggeration=exaggeration)
    ax.set_title((title + "\n" if title else "") + f"deflections (arrows x{ex:.3g})")
    return fig


def _robust_max(values: np.ndarray, q: float = 99.5) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 1.0
    m = float(np.percentile(np.abs(v), q))
    return m if m > 0 else (float(np.abs(v).max()) or 1.0)


def deflection_figure(image: np.ndarray | None, flow: np.ndarray, *, mask: np.ndarray | None = None,
                      potential: np.ndarray | None = None, threshold: float | None = None,
                      step: int = 8, max_magnitude: float | None = None,
                      potential_units: str = "px$^2$", title: str | None = None) -> Figure:
    """The paper's Figure 4 for one camera frame.

    Top row: camera image, colour-coded deflections (with the colour key and the
    saturation magnitude), quiver plot. Bottom row (what is given): Poisson-integrated
    deflections (``potential``), the thresholded potential, the final mask.

    Parameters
    ----------
    image : ndarray, shape (H, W) or None
        Camera frame at full resolution (None: the deflection magnitude is shown instead).
    flow : ndarray, shape (h, w, 2)
        Deflections, image pixels, on the flow grid.
    mask : ndarray, shape (h, w), bool, optional
    potential : ndarray, shape (h, w), optional
        Integrated deflections (pixel x pixel).
    threshold : float, optional
        Mask threshold on ``|potential|`` (same units; the masks stage smooths first).
    step : int
        Quiver subsampling on the flow grid.
    max_magnitude : float, optional
        Saturation of the colour coding, pixels (default: 99.5th percentile).
    potential_units : str
        Units of ``potential`` and ``threshold`` for the labels.
    title : str, optional

    Returns
    -------
    Figure
    """
    flow = np.asarray(flow, dtype=np.float64)
    mag = np.hypot(flow[..., 0], flow[..., 1])
    if max_magnitude is None:
        max_magnitude = _robust_max(mag)
    nrows = 2 if (potential is not None or mask is not None) else 1
    fig = _new_figure(15.0, 4.6 * nrows)
    axes = fig.subplots(nrows, 3, squeeze=False)
    _draw_camera_row(fig, axes[0], image, flow, mag, max_magnitude=max_magnitude, step=step)
    if nrows == 2:
        _draw_integration_row(fig, axes[1], mag, mask=mask, potential=potential, threshold=threshold,
                              max_magnitude=max_magnitude, potential_units=potential_units)
    if title:
        fig.suptitle(title)
    return fig


def _draw_camera_row(fig, axes, image, flow, mag, *, max_magnitude: float, step: int):
    """Figure 4's top row: camera frame (or |deflection|), colour coding with its key, quiver plot."""
    ax = axes[0]
    if image is not None:
        ax.imshow(image, cmap="gray", interpolation="nearest")
        ax.set_title("camera frame")
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    else:
        h_img, w_img = flow.shape[:2]
        im = ax.imshow(mag, cmap="magma", interpolation="nearest")
        fig.colorbar(im, ax=ax, label="|deflection| (px)", shrink=0.85)
        ax.set_title("deflection magnitude (camera frame not available)")
        ax.set_xlabel("u (flow cell)")
        ax.set_ylabel("v (flow cell)")
    ax = axes[1]
    extent = None
    if image is not None:  # the area the flow cells cover, in image pixels
        f = _flow_positions(np.asarray(image).shape, flow.shape)[2]
        extent = (-0.5, f * flow.shape[1] - 0.5, f * flow.shape[0] - 0.5, -0.5)
    ax.imshow(flow_to_rgb(flow, max_magnitude=max_magnitude), interpolation="nearest", extent=extent)
    ax.set_title(f"deflection colour coding (saturated at {max_magnitude:.3g} px)")
    ax.set_xlabel("u (px)" if extent else "u (flow cell)")
    ax.set_ylabel("v (px)" if extent else "v (flow cell)")
    inset = ax.inset_axes([0.76, 0.02, 0.22, 0.22])
    inset.imshow(flow_wheel(101), interpolation="bilinear")
    inset.set_axis_off()
    ax = axes[2]
    _, ex = _draw_quiver(ax, image, flow, step=step)
    ax.set_title(f"quiver plot (arrows x{ex:.3g})")


def _draw_integration_row(fig, axes, mag, *, mask, potential, threshold, max_magnitude: float,
                          potential_units: str):
    """Figure 4's bottom row: Poisson-integrated deflections, their threshold, the mask."""
    ax = axes[0]
    if potential is not None:
        lim = _robust_max(potential)
        im = ax.imshow(potential, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        fig.colorbar(im, ax=ax, label=f"integrated deflection ({potential_units})", shrink=0.85)
        ax.set_title("Poisson-integrated deflections")
    else:
        ax.set_axis_off()
        ax.set_title("potential: not in the store")
    ax = axes[1]
    if potential is not None and threshold is not None:
        ax.imshow(np.abs(np.asarray(potential)) > threshold, cmap="gray", interpolation="nearest")
        ax.set_title(f"thresholded (|potential| > {threshold:.3g})")
    else:  # no threshold stored: the deflection magnitude instead
        im = ax.imshow(mag, cmap="magma", vmin=0.0, vmax=max_magnitude, interpolation="nearest")
        fig.colorbar(im, ax=ax, label="|deflection| (px)", shrink=0.85)
        ax.set_title("deflection magnitude")
    ax = axes[2]
    if mask is not None:
        ax.imshow(np.asarray(mask, dtype=bool), cmap="gray", interpolation="nearest")
        ax.set_title(f"mask ({100.0 * np.mean(mask):.1f} % of pixels)")
    else:
        ax.set_axis_off()
        ax.set_title("mask: not in the store")
    for ax in axes:
        if ax.axison:
            ax.set_xlabel("u (flow cell)")
            ax.set_ylabel("v (flow cell)")


def residual_figure(measured: np.ndarray, predicted: np.ndarray, *, mask: np.ndarray | None = None,
                    title: str | None = None) -> Figure:
    """Measured vs re-projected deflections of one camera frame, and the residual.

    Parameters
    ----------
    measured, predicted : ndarray, shape (h, w, 2)
        Deflections in image pixels on the flow grid.
    mask : ndarray, shape (h, w), bool, optional
        Outlined on the residual panel.
    title : str, optional

    Returns
    -------
    Figure
        Three panels: both colour codings (same saturation) and ``|measured - predicted|``
        in pixels with a colour bar.
    """
    measured = np.asarray(measured, dtype=np.float64)
    predicted = np.asarray(predicted, dtype=np.float64)
    lim = _robust_max(np.hypot(measured[..., 0], measured[..., 1]))
    res = np.hypot(*np.moveaxis(measured - predicted, -1, 0))
    fig = _new_figure(15.0, 4.4)
    axes = fig.subplots(1, 3)
    axes[0].imshow(flow_to_rgb(measured, max_magnitude=lim), interpolation="nearest")
    axes[0].set_title(f"measured (saturated at {lim:.3g} px)")
    axes[1].imshow(flow_to_rgb(predicted, max_magnitude=lim), interpolation="nearest")
    axes[1].set_title("re-projected reconstruction")
    im = axes[2].imshow(res, cmap="viridis", vmin=0.0, vmax=lim, interpolation="nearest")
    if mask is not None and np.any(mask) and not np.all(mask):
        axes[2].contour(np.asarray(mask, dtype=float), levels=[0.5], colors="w", linewidths=0.8)
    fig.colorbar(im, ax=axes[2], label="|measured - predicted| (px)", shrink=0.85)
    finite = np.isfinite(res)
    rms = float(np.sqrt(np.mean(res[finite] ** 2))) if finite.any() else float("nan")
    axes[2].set_title(f"residual (RMS {rms:.3g} px)")
    for ax in axes:
        ax.set_xlabel("u (flow cell)")
        ax.set_ylabel("v (flow cell)")
    if title:
        fig.suptitle(title)
    return fig


def timings_figure(stage_seconds: dict[str, float]) -> Figure:
    """Horizontal bar chart of wall-clock seconds per stage.

    Parameters
    ----------
    stage_seconds : dict
        Stage name -> seconds, in pipeline order.
    """
    names = list(stage_seconds)
    secs = [float(stage_seconds[k]) for k in names]
    fig = _new_figure(7.0, 0.3 * max(len(names), 1) + 1.2)
    ax = fig.add_subplot()
    ax.barh(np.arange(len(names)), secs, color="#4c72b0")
    ax.set_yticks(np.arange(len(names)), labels=names)
    ax.invert_yaxis()
    ax.set_xlabel("wall-clock time (s)")
    ax.set_title("per-stage timings")
    return fig
