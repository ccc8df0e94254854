"""Pictures of the results: deflection colour coding, quiver plots, slices, volume renderings.

Pure functions: arrays in, RGB ``uint8`` arrays or matplotlib :class:`~matplotlib.figure.Figure`
objects out (built on the Agg canvas, never through ``pyplot``, so no global state and no
display). Nothing here writes files: :mod:`schlieren.storage.report` saves what these return.

* :func:`flow_to_rgb`: the optical-flow colour wheel of Baker et al. (2011, the Middlebury
  benchmark), as in the paper's Figure 4 (top centre): hue = direction, saturation =
  magnitude.
* :func:`quiver_figure`, :func:`deflection_figure`: the paper's Figure 4 (camera image,
  colour coding, quiver plot; integrated deflections, threshold and mask).
* :func:`slice_figure`, :func:`orthoslices_figure`: axis-aligned slices of a volume in world
  units with a colour bar.
* :func:`render_volume`, :func:`animation_frames`: emission-absorption ray marching of the
  refractivity (the paper's Figures 1 and 8): an orthographic camera orbits the box (z up),
  samples are trilinear, the transfer function acts on the refractivity deficit
  ``r_ambient - r`` so hot (less dense) gas glows, compositing is front to back with early
  ray termination.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import matplotlib
import numba as nb
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from schlieren.pipeline.geometry import Grid

__all__ = [
    "flow_to_rgb",
    "flow_wheel",
    "figure_to_rgb",
    "quiver_figure",
    "deflection_figure",
    "residual_figure",
    "slice_figure",
    "orthoslices_figure",
    "hull_figure",
    "timings_figure",
    "TransferFunction",
    "view_basis",
    "render_volume",
    "fit_image_size",
    "render_figure",
    "animation_frames",
]

log = logging.getLogger(__name__)

MM = 1e3  # world metres -> millimetres on figure axes


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
    ax = axes[0, 0]
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
    ax = axes[0, 1]
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
    ax = axes[0, 2]
    _, ex = _draw_quiver(ax, image, flow, step=step)
    ax.set_title(f"quiver plot (arrows x{ex:.3g})")
    if nrows == 2:
        ax = axes[1, 0]
        if potential is not None:
            lim = _robust_max(potential)
            im = ax.imshow(potential, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
            fig.colorbar(im, ax=ax, label=f"integrated deflection ({potential_units})", shrink=0.85)
            ax.set_title("Poisson-integrated deflections")
        else:
            ax.set_axis_off()
            ax.set_title("potential: not in the store")
        ax = axes[1, 1]
        if potential is not None and threshold is not None:
            ax.imshow(np.abs(np.asarray(potential)) > threshold, cmap="gray", interpolation="nearest")
            ax.set_title(f"thresholded (|potential| > {threshold:.3g})")
        else:  # no threshold stored: the deflection magnitude instead
            im = ax.imshow(mag, cmap="magma", vmin=0.0, vmax=max_magnitude, interpolation="nearest")
            fig.colorbar(im, ax=ax, label="|deflection| (px)", shrink=0.85)
            ax.set_title("deflection magnitude")
        ax = axes[1, 2]
        if mask is not None:
            ax.imshow(np.asarray(mask, dtype=bool), cmap="gray", interpolation="nearest")
            ax.set_title(f"mask ({100.0 * np.mean(mask):.1f} % of pixels)")
        else:
            ax.set_axis_off()
            ax.set_title("mask: not in the store")
        for ax in axes[1]:
            if ax.axison:
                ax.set_xlabel("u (flow cell)")
                ax.set_ylabel("v (flow cell)")
    if title:
        fig.suptitle(title)
    return fig


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


_AXES = {"x": 2, "y": 1, "z": 0}  # world axis -> array axis of (nz, ny, nx)


def _slice(volume: np.ndarray, grid: Grid, axis: str, index: int):
    """2-D slice normal to a world axis with its world extent (mm) and axis names."""
    if axis not in _AXES:
        raise ValueError(f"axis must be one of 'x', 'y', 'z', got {axis!r}")
    volume = np.asarray(volume)
    if volume.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {volume.shape} does not match grid {grid.shape}")
    n = volume.shape[_AXES[axis]]
    if not 0 <= index < n:
        raise IndexError(f"slice index {index} outside 0..{n - 1} along {axis}")
    lo = np.asarray(grid.vmin) * MM
    nx, ny, nz = grid.shape_xyz
    hi = lo + np.asarray([nx, ny, nz]) * grid.voxel_size * MM
    coord = (grid.axes()["xyz".index(axis)][index])
    if axis == "z":
        img, names, ext = volume[index], ("x", "y"), (lo[0], hi[0], lo[1], hi[1])
    elif axis == "y":
        img, names, ext = volume[:, index, :], ("x", "z"), (lo[0], hi[0], lo[2], hi[2])
    else:
        img, names, ext = volume[:, :, index], ("y", "z"), (lo[1], hi[1], lo[2], hi[2])
    return img, names, ext, coord


def _draw_slice(fig, ax, volume, grid, *, axis, index, label, units, cmap, vmin, vmax,
                colorbar=True):
    img, names, ext, coord = _slice(volume, grid, axis, index)
    im = ax.imshow(img, origin="lower", extent=ext, cmap=cmap, vmin=vmin, vmax=vmax,
                   interpolation="nearest", aspect="equal")
    ax.set_xlabel(f"{names[0]} (mm)")
    ax.set_ylabel(f"{names[1]} (mm)")
    ax.set_title(f"{axis} = {coord * MM:.1f} mm")
    if colorbar:
        fig.colorbar(im, ax=ax, label=f"{label} ({units})", shrink=0.9)
    return im


def slice_figure(volume: np.ndarray, grid: Grid, *, axis: str = "y", index: int | None = None,
                 label: str = "refractivity", units: str = "1", cmap: str = "viridis",
                 vmin: float | None = None, vmax: float | None = None) -> Figure:
    """One axis-aligned slice of a volume in world coordinates with a colour bar.

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
        Any scalar quantity on ``grid``.
    grid : Grid
    axis : {"x", "y", "z"}
        The world axis normal to the slice (``"y"``: an x-z slice, z up).
    index : int, optional
        Voxel index along ``axis`` (default: the middle).
    label, units : str
        Colour bar label, e.g. ``"temperature"``, ``"K"``.
    cmap : str
    vmin, vmax : float, optional
        Colour range (default: the slice's range).

    Returns
    -------
    Figure
        Axes in millimetres with the voxel extents (``vmin .. vmax`` of the box).
    """
    ax_idx = _AXES.get(axis)
    if index is None and ax_idx is not None:
        index = np.asarray(volume).shape[ax_idx] // 2
    fig = _new_figure(5.6, 5.0)
    ax = fig.add_subplot()
    _draw_slice(fig, ax, volume, grid, axis=axis, index=int(index), label=label, units=units,
                cmap=cmap, vmin=vmin, vmax=vmax)
    return fig


def orthoslices_figure(volume: np.ndarray, grid: Grid, *, index: tuple[int, int, int] | None = None,
                       label: str = "refractivity", units: str = "1", cmap: str = "viridis",
                       vmin: float | None = None, vmax: float | None = None,
                       vectors: np.ndarray | None = None, vector_step: int | None = None,
                       title: str | None = None) -> Figure:
    """Three orthogonal slices (x-y at a height, x-z and y-z) through one voxel.

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
    grid : Grid
    index : (iz, iy, ix), optional
        The voxel the slices pass through (default: the box centre).
    label, units, cmap, vmin, vmax, title
        As in :func:`slice_figure`; one colour range and colour bar for all three.
    vectors : ndarray, shape (nz, ny, nx, 3), optional
        A vector field (components x, y, z), e.g. ``grad n``: its in-plane components are
        drawn as arrows on each slice (paper Figure 1, centre right), all panels with one
        arrow scale (the 99th-percentile in-plane length spans 0.9 arrow spacings).
    vector_step : int, optional
        Arrow spacing in voxels (default: about 14 arrows along the longest edge).

    Returns
    -------
    Figure
    """
    volume = np.asarray(volume)
    if index is None:
        index = tuple(n // 2 for n in volume.shape)
    finite = volume[np.isfinite(volume)]
    if vmin is None:
        vmin = float(finite.min()) if finite.size else 0.0
    if vmax is None:
        vmax = float(finite.max()) if finite.size else 1.0
    nx, ny, nz = grid.shape_xyz
    # width ratios follow the physical extents so that each panel keeps aspect 1
    fig = _new_figure(15.0, 5.4)
    axes = fig.subplots(1, 3, width_ratios=[nx / ny, nx / nz, ny / nz])
    im = None
    for ax, axis in zip(axes, ("z", "y", "x")):
        im = _draw_slice(fig, ax, volume, grid, axis=axis, index=int(index[_AXES[axis]]), label=label,
                         units=units, cmap=cmap, vmin=vmin, vmax=vmax, colorbar=False)
    fig.colorbar(im, ax=list(axes), label=f"{label} ({units})", shrink=0.9)
    if vectors is not None:
        _draw_vector_slices(axes, np.asarray(vectors, dtype=np.float64), grid, index, vector_step)
    if title:
        fig.suptitle(title)
    return fig


_IN_PLANE = {"z": (0, 1), "y": (0, 2), "x": (1, 2)}  # slice normal -> (horizontal, vertical) components


def _draw_vector_slices(axes, vectors, grid: Grid, index, step):
    if vectors.shape != tuple(grid.shape) + (3,):
        raise ValueError(f"vectors must have shape {tuple(grid.shape) + (3,)}, got {vectors.shape}")
    if step is None:
        step = max(1, max(grid.shape) // 14)
    xs, ys, zs = (a * MM for a in grid.axes())
    coords = {"x": xs, "y": ys, "z": zs}
    planes = {}
    for axis in ("z", "y", "x"):
        k = int(index[_AXES[axis]])
        sl = [slice(None)] * 3
        sl[_AXES[axis]] = k
        v = vectors[tuple(sl)]  # 2-D (rows = vertical axis, cols = horizontal axis) x 3
        hc, vc = _IN_PLANE[axis]
        planes[axis] = (v[::step, ::step, hc], v[::step, ::step, vc])
    lengths = np.concatenate([np.hypot(a, b).ravel() for a, b in planes.values()])
    lengths = lengths[np.isfinite(lengths)]
    ref = float(np.percentile(lengths, 99)) if lengths.size else 0.0
    scale = (0.9 * step * grid.voxel_size * MM / ref) if ref > 0 else 1.0  # mm per vector unit
    for ax, axis in zip(axes, ("z", "y", "x")):
        h_name, v_name = {"z": ("x", "y"), "y": ("x", "z"), "x": ("y", "z")}[axis]
        X, Y = np.meshgrid(coords[h_name][::step], coords[v_name][::step])
        U, V = planes[axis]
        ax.quiver(X, Y, U, V, angles="xy", scale_units="xy", scale=1.0 / scale, color="w",
                  edgecolor="k", linewidth=0.3, width=0.005)


def hull_figure(hull: np.ndarray, grid: Grid, *, title: str | None = None) -> Figure:
    """The visual hull: a ray-marched view and its silhouettes along z, y and x.

    Parameters
    ----------
    hull : ndarray, shape (nz, ny, nx), bool
    grid : Grid

    Returns
    -------
    Figure
        Left: emission-absorption rendering of the hull voxels (azimuth 35 deg, elevation
        20 deg); then the fraction of hull voxels along each world axis in millimetre axes.
    """
    hull = np.asarray(hull, dtype=bool)
    fig = _new_figure(16.0, 4.8)
    axes = fig.subplots(1, 4)
    occupancy = hull.astype(np.float64)
    tf = TransferFunction(r_ambient=0.0, scale=-1.0, optical_depth=6.0, cmap="Blues",
                          gamma=1.0)
    img = render_volume(occupancy, grid, azimuth_deg=35.0, elevation_deg=20.0,
                        image_size=(320, 320), transfer=tf, background=(255, 255, 255))
    axes[0].imshow(img)
    axes[0].set_axis_off()
    axes[0].set_title(f"visual hull ({int(hull.sum())} voxels, {100 * hull.mean():.1f} %)")
    lo = np.asarray(grid.vmin) * MM
    nx, ny, nz = grid.shape_xyz
    hi = lo + np.asarray([nx, ny, nz]) * grid.voxel_size * MM
    views = [
        (hull.mean(axis=0), "x", "y", (lo[0], hi[0], lo[1], hi[1]), "seen along z"),
        (hull.mean(axis=1), "x", "z", (lo[0], hi[0], lo[2], hi[2]), "seen along y"),
        (hull.mean(axis=2), "y", "z", (lo[1], hi[1], lo[2], hi[2]), "seen along x"),
    ]
    im = None
    for ax, (img2, a, b, ext, name) in zip(axes[1:], views):
        im = ax.imshow(img2, origin="lower", extent=ext, cmap="Blues", vmin=0.0, vmax=1.0,
                       interpolation="nearest")
        ax.set_xlabel(f"{a} (mm)")
        ax.set_ylabel(f"{b} (mm)")
        ax.set_title(name)
    fig.colorbar(im, ax=list(axes[1:]), label="fraction of voxels in the hull (1)", shrink=0.9)
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


# ---------------------------------------------------------------------------------------
# Volume rendering (emission-absorption ray marching)
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TransferFunction:
    """Maps refractivity to emitted colour and extinction (paper Figures 1 and 8).

    The signal is ``s = clip((r_ambient - r) / scale, 0, 1)``: 0 for ambient air, 1 for
    the hottest gas shown. Colour is ``cmap(s)``; extinction per metre is
    ``optical_depth / L * s**gamma`` with ``L`` the longest edge of the box, so a ray
    crossing the whole box through gas at full signal accumulates ``optical_depth``.

    Parameters
    ----------
    r_ambient : float
        Refractivity ``n - 1`` of the surrounding air.
    scale : float
        Refractivity deficit shown at full signal (same units as refractivity). A negative
        scale shows excesses instead (``r - r_ambient``), e.g. cold gas or a 0/1 mask.
    optical_depth : float
        Dimensionless, see above.
    cmap : str
        A matplotlib colour map name.
    gamma : float
        Opacity ramp exponent (> 1 hides faint gas).
    """

    r_ambient: float
    scale: float
    optical_depth: float = 16.0
    cmap: str = "inferno"
    gamma: float = 1.0

    def tables(self, n: int = 1024) -> tuple[np.ndarray, np.ndarray]:
        """Colour (n, 3) in 0..1 and extinction-per-metre factor (n,) at ``s = k / (n - 1)``."""
        s = np.linspace(0.0, 1.0, n)
        rgb = np.asarray(matplotlib.colormaps[self.cmap](s))[:, :3]
        return rgb.astype(np.float64), s ** self.gamma


def view_basis(azimuth_deg: float, elevation_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Viewing direction, image right and image up (world unit vectors), z up.

    The eye sits at azimuth ``azimuth_deg`` (from +x towards +y) and elevation
    ``elevation_deg`` above the x-y plane and looks at the box centre.
    """
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    eye = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    d = -eye
    right = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down: keep x to the right
        right = np.array([-np.sin(az), np.cos(az), 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, d)
    return d, right, up / np.linalg.norm(up)


@nb.njit(cache=True, parallel=True)
def _march(vol, ro, rd, step, t0, t1, r_amb, inv_scale, lut_rgb, lut_alpha, bg, t_min):
    """Front-to-back emission-absorption compositing along rays in voxel-index space.

    vol (nz, ny, nx); ro (N, 3) ray origins and rd (3,) direction as (ix, iy, iz) index
    coordinates; t0, t1 (N,) entry/exit parameters; step in index units; lut_alpha holds
    the opacity of one step for each signal level.
    """
    nz, ny, nx = vol.shape
    n = ro.shape[0]
    nl = lut_rgb.shape[0]
    out = np.empty((n, 3), np.float64)
    for p in nb.prange(n):  # rays are independent
        cr = 0.0
        cg = 0.0
        cb = 0.0
        T = 1.0
        t = t0[p] + 0.5 * step
        while t < t1[p]:
            x = min(max(ro[p, 0] + t * rd[0], 0.0), nx - 1.0)
            y = min(max(ro[p, 1] + t * rd[1], 0.0), ny - 1.0)
            z = min(max(ro[p, 2] + t * rd[2], 0.0), nz - 1.0)
            ix = min(int(x), nx - 2) if nx > 1 else 0
            iy = min(int(y), ny - 2) if ny > 1 else 0
            iz = min(int(z), nz - 2) if nz > 1 else 0
            fx = x - ix
            fy = y - iy
            fz = z - iz
            jx = ix + 1 if nx > 1 else ix
            jy = iy + 1 if ny > 1 else iy
            jz = iz + 1 if nz > 1 else iz
            c00 = vol[iz, iy, ix] * (1 - fx) + vol[iz, iy, jx] * fx
            c01 = vol[iz, jy, ix] * (1 - fx) + vol[iz, jy, jx] * fx
            c10 = vol[jz, iy, ix] * (1 - fx) + vol[jz, iy, jx] * fx
            c11 = vol[jz, jy, ix] * (1 - fx) + vol[jz, jy, jx] * fx
            c0 = c00 * (1 - fy) + c01 * fy
            c1 = c10 * (1 - fy) + c11 * fy
            val = c0 * (1 - fz) + c1 * fz
            s = (r_amb - val) * inv_scale
            if s > 0.0:
                if s > 1.0:
                    s = 1.0
                k = int(s * (nl - 1) + 0.5)
                a = lut_alpha[k]
                if a > 0.0:
                    w = T * a
                    cr += w * lut_rgb[k, 0]
                    cg += w * lut_rgb[k, 1]
                    cb += w * lut_rgb[k, 2]
                    T *= 1.0 - a
                    if T < t_min:
                        T = 0.0
                        break
            t += step
        out[p, 0] = cr + T * bg[0]
        out[p, 1] = cg + T * bg[1]
        out[p, 2] = cb + T * bg[2]
    return out


def _box_edges() -> list[tuple[int, int]]:
    edges = []
    for a in range(8):
        for b in range(a + 1, 8):
            if bin(a ^ b).count("1") == 1:
                edges.append((a, b))
    return edges


def _view_extent(lo, hi, right, up):
    """Centre, bounding radius and projected width/height (metres) of the box in the view."""
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rel = corners - centre
    ext_w = 2.0 * float(np.max(np.abs(rel @ right)))
    ext_h = 2.0 * float(np.max(np.abs(rel @ up)))
    return centre, radius, (ext_w, ext_h)


def fit_image_size(grid: Grid, *, azimuth_deg: float = 30.0, elevation_deg: float = 15.0,
                   long_side: int = 480) -> tuple[int, int]:
    """``(width, height)`` in pixels whose aspect matches the box as seen from the view.

    Parameters
    ----------
    grid : Grid
    azimuth_deg, elevation_deg : float
        The view of :func:`render_volume`.
    long_side : int
        Pixels along the longer image side.
    """
    h = grid.voxel_size
    lo = np.asarray(grid.vmin, dtype=np.float64)
    hi = lo + h * np.asarray(grid.shape_xyz, dtype=np.float64)
    _, right, up = view_basis(azimuth_deg, elevation_deg)
    _, _, (ext_w, ext_h) = _view_extent(lo, hi, right, up)
    if ext_w >= ext_h:
        return int(long_side), max(16, int(round(long_side * ext_h / ext_w)))
    return max(16, int(round(long_side * ext_w / ext_h))), int(long_side)


def render_volume(refractivity: np.ndarray, grid: Grid, *, azimuth_deg: float = 30.0,
                  elevation_deg: float = 15.0, image_size: tuple[int, int] | None = None,
                  transfer: TransferFunction | None = None, step: float = 0.5,
                  background: tuple[int, int, int] = (0, 0, 0), draw_box: bool = True,
                  min_transmittance: float = 1e-3) -> np.ndarray:
    """Emission-absorption volume rendering of a refractivity field (paper Figures 1, 8).

    An orthographic camera looks at the box centre from ``(azimuth, elevation)`` with
    world z up; the projected box fills the image (a margin of 4 % on each side). Each
    pixel's ray is clipped to the box, sampled every ``step`` voxels with trilinear interpolation of the
    refractivity, and composited front to back
    ``C += T * alpha(s) * rgb(s); T *= 1 - alpha(s)``, with
    ``alpha(s) = 1 - exp(-sigma(s) * step * h)`` from the :class:`TransferFunction`;
    rays stop once ``T < min_transmittance``.

    Parameters
    ----------
    refractivity : ndarray, shape (nz, ny, nx)
        ``n - 1`` on ``grid`` (any scalar works with a suitable transfer function).
    grid : Grid
    azimuth_deg, elevation_deg : float
        Eye direction, degrees (azimuth from +x towards +y, elevation above x-y).
    image_size : (width, height), optional
        Pixels of the result (default: :func:`fit_image_size`, 480 on the long side).
    transfer : TransferFunction, optional
        Default: ambient = the volume's median, scale = its largest deficit.
    step : float
        Sampling step in voxels.
    background : (r, g, b)
        Colour behind the volume, 0..255.
    draw_box : bool
        Draw the box edges (grey) and an x/y/z axis triad at the lower-left corner.
    min_transmittance : float
        Early ray termination threshold.

    Returns
    -------
    rgb : ndarray, shape (height, width, 3), uint8
    """
    vol = np.ascontiguousarray(refractivity, dtype=np.float64)
    if vol.shape != tuple(grid.shape):
        raise ValueError(f"volume shape {vol.shape} does not match grid {grid.shape}")
    if transfer is None:
        amb = float(np.median(vol))
        deficit = float(np.max(amb - vol))
        transfer = TransferFunction(r_ambient=amb, scale=deficit if deficit > 0 else 1.0)
    if transfer.scale == 0:
        raise ValueError("transfer.scale must be non-zero")
    h = grid.voxel_size
    nx, ny, nz = grid.shape_xyz
    lo = np.asarray(grid.vmin, dtype=np.float64)
    hi = lo + h * np.array([nx, ny, nz], dtype=np.float64)
    d, right, up = view_basis(azimuth_deg, elevation_deg)
    centre, radius, (ext_w, ext_h) = _view_extent(lo, hi, right, up)
    if image_size is None:
        image_size = fit_image_size(grid, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg)
    W, H = int(image_size[0]), int(image_size[1])
    pix = 1.08 * max(ext_w / W, ext_h / H)  # metres per pixel: the projected box fills the image
    jj, ii = np.meshgrid(np.arange(W) - (W - 1) / 2.0, np.arange(H) - (H - 1) / 2.0)
    plane = (centre + jj[..., None] * pix * right - ii[..., None] * pix * up).reshape(-1, 3)
    origins = plane - 1.05 * radius * d
    # index space: voxel centres at integers, box faces at -0.5 and n - 0.5
    ro = (origins - np.asarray(grid.origin)) / h
    rd = d / h  # index units per metre of arc length
    box_lo = np.full(3, -0.5)
    box_hi = np.array([nx, ny, nz], dtype=np.float64) - 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(rd != 0, 1.0 / np.where(rd != 0, rd, 1.0), np.inf)
        ta = (box_lo - ro) * inv
        tb = (box_hi - ro) * inv
    par = rd == 0
    inside = (ro >= box_lo) & (ro <= box_hi)
    tmin = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    tmax = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    t0 = np.maximum(tmin.max(axis=1), 0.0)  # metres along the ray
    t1 = tmax.min(axis=1)
    rgb_lut, s_gamma = transfer.tables()
    box_len = float(np.max(hi - lo))
    sigma = transfer.optical_depth / box_len * s_gamma  # 1/m
    ds = step * h
    alpha_lut = 1.0 - np.exp(-sigma * ds)
    bg = np.asarray(background, dtype=np.float64) / 255.0
    # march in world arc length: index point = ro + t * rd, step of ds metres
    out = _march(vol, np.ascontiguousarray(ro), np.ascontiguousarray(rd), ds, t0, t1,
                 float(transfer.r_ambient), 1.0 / float(transfer.scale), rgb_lut, alpha_lut, bg,
                 float(min_transmittance))
    img = np.clip(np.round(255.0 * out), 0, 255).astype(np.uint8).reshape(H, W, 3)
    if draw_box:
        img = _draw_box(img, lo, hi, centre, right, up, pix)
    return img


def _to_image(X, centre, right, up, pix, W, H):
    rel = np.asarray(X) - centre
    return np.stack([rel @ right / pix + (W - 1) / 2.0, -(rel @ up) / pix + (H - 1) / 2.0], axis=-1)


def _draw_box(img, lo, hi, centre, right, up, pix):
    H, W = img.shape[:2]
    img = np.ascontiguousarray(img.copy())
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv = _to_image(corners, centre, right, up, pix, W, H)
    sh = 4  # fixed-point sub-pixel bits of cv2.line
    for a, b in _box_edges():
        p = tuple(int(round(c * (1 << sh))) for c in uv[a])
        q = tuple(int(round(c * (1 << sh))) for c in uv[b])
        cv2.line(img, p, q, (110, 110, 110), 1, cv2.LINE_AA, sh)
    # axis triad in the lower-left corner
    L = 0.08 * min(W, H)
    o = np.array([0.12 * min(W, H), H - 0.12 * min(W, H)])
    for k, (name, col) in enumerate((("x", (230, 80, 80)), ("y", (80, 200, 80)), ("z", (90, 140, 255)))):
        e = np.zeros(3)
        e[k] = 1.0
        v2 = np.array([e @ right, -(e @ up)])
        tip = o + L * v2
        cv2.line(img, tuple(int(round(c)) for c in o), tuple(int(round(c)) for c in tip), col, 2, cv2.LINE_AA)
        cv2.putText(img, name, tuple(int(round(c)) for c in tip + 4 * v2 + np.array([-4, 4])),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1, cv2.LINE_AA)
    return img


def render_figure(image: np.ndarray, transfer: TransferFunction, *, title: str | None = None,
                  signal_label: str = "refractivity deficit r$_{amb}$ - r",
                  signal_scale: float = 1e-6, signal_units: str = "10$^{-6}$") -> Figure:
    """A rendered image with the colour bar of its transfer function.

    Parameters
    ----------
    image : ndarray, shape (H, W, 3), uint8
        From :func:`render_volume`.
    transfer : TransferFunction
        The one used to render; the colour bar spans ``0 .. scale``.
    signal_scale : float
        Colour-bar tick unit (default 1e-6, labelled ``signal_units``).
    """
    fig = _new_figure(6.0, 6.0 * image.shape[0] / image.shape[1] + 0.6)
    ax = fig.add_subplot()
    ax.imshow(image)
    ax.set_axis_off()
    sm = ScalarMappable(norm=Normalize(0.0, abs(transfer.scale) / signal_scale), cmap=transfer.cmap)
    fig.colorbar(sm, ax=ax, label=f"{signal_label} ({signal_units})", shrink=0.8)
    if title:
        ax.set_title(title)
    return fig


def animation_frames(volumes: np.ndarray, grid: Grid, *, r_ambient: float, times: np.ndarray | None = None,
                     azimuth_deg: float = 30.0, elevation_deg: float = 15.0,
                     image_size: tuple[int, int] | None = None, scale: float | None = None,
                     transfer: TransferFunction | None = None) -> list[np.ndarray]:
    """Volume renderings of a time series with one transfer function, time-stamped.

    Parameters
    ----------
    volumes : ndarray, shape (F, nz, ny, nx) or a sequence of (nz, ny, nx)
        Refractivity per frame.
    grid : Grid
    r_ambient : float
        Ambient refractivity.
    times : ndarray, shape (F,), optional
        Seconds, stamped on each frame.
    azimuth_deg, elevation_deg, image_size
        As in :func:`render_volume`.
    scale : float, optional
        Full-signal deficit (default: the largest deficit over all frames, so brightness is
        comparable between frames).
    transfer : TransferFunction, optional
        Overrides ``r_ambient`` / ``scale``.

    Returns
    -------
    list of ndarray, each (H, W, 3) uint8
    """
    if transfer is None:
        if scale is None:
            scale = max(float(np.nanmax(r_ambient - np.asarray(v, dtype=np.float64))) for v in volumes)
            if not scale > 0:
                scale = 1.0
        transfer = TransferFunction(r_ambient=r_ambient, scale=scale)
    frames = []
    for k, vol in enumerate(volumes):
        img = render_volume(vol, grid, azimuth_deg=azimuth_deg, elevation_deg=elevation_deg,
                            image_size=image_size, transfer=transfer)
        if times is not None:
            img = np.ascontiguousarray(img)
            cv2.putText(img, f"t = {float(times[k]):.4f} s", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                        (230, 230, 230), 1, cv2.LINE_AA)
        frames.append(img)
    return frames
