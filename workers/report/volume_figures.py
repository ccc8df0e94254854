"""Report figures of the volume: axis-aligned slices in world units, the visual hull, a
rendering with its colour bar.

Pure functions: arrays in, matplotlib :class:`~matplotlib.figure.Figure` objects out (Agg
canvas, never ``pyplot``; :func:`schlieren.workers.report.figures.figure_to_rgb` gives
their pixels).

* :func:`slice_figure`, :func:`orthoslices_figure`: axis-aligned slices of a volume in world
  units with a colour bar, optionally with the in-plane arrows of a vector field (paper
  Figure 1, centre right).
* :func:`hull_figure`: the visual hull rendered and seen along each axis.
* :func:`render_figure`: a :func:`~schlieren.workers.report.volume_render.render_volume`
  image with the colour bar of its transfer function.
"""

from __future__ import annotations

import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from schlieren.pipeline.geometry import Grid
from schlieren.workers.report.figures import _new_figure
from schlieren.workers.report.volume_render import TransferFunction, render_volume

__all__ = [
    "slice_figure",
    "orthoslices_figure",
    "hull_figure",
    "render_figure",
]

MM = 1e3  # world metres -> millimetres on figure axes


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
