"""Tomography rays per flow cell: one ray per block of flow cells when the cells oversample the voxels.

A flow cell spans ``flow.factor`` image pixels (paper sec. 4: the flow is computed at full
resolution, then downsampled); at the volume a voxel spans ``voxel / footprint`` pixels
(:func:`schlieren.pipeline.geometry.pixel_footprint`). When a voxel edge spans several
flow cells (paper scale, 16 cameras at 1440x1080 with 2.5 mm voxels: 2.7-3.0 cells),
neighbouring rays cross the same basis functions almost alike: the projection of sec. 5
holds several times the rows its unknowns can use, and every product of the solve pays for
them. The tomography then takes one ray per ``b x b`` block of flow cells: the ray through
the block's centre, whose measurement is the mean of the block's cells (the flow averaged
over the block, as the downsampling averages the pixels of a cell).

``b`` is the largest integer that leaves at least :data:`MIN_RAYS_PER_VOXEL` rays per
voxel edge in each camera: a linear basis on the voxel grid needs one sample per voxel
edge (its Nyquist rate), and the margin keeps the rays finer than the basis. The sessions
whose cells are coarser than that (every realistic-family rig, Table 1's 480x360 rigs)
keep one ray per cell, as in the paper.

The flow-window model (:func:`~schlieren.pipeline.flow.measurement_sigma`) sees the block
mean as one more average: a Gaussian of ``sigma`` cells followed by the mean of ``b``
cells one cell apart has the variance ``sigma^2 + (b^2 - 1) / 12`` cells^2
(:func:`binned_sigma`, in units of the block).
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.geometry import FlowGrid, Grid, pixel_footprint
from schlieren.pipeline.tomography._binning_kernels import _bin_kernel

__all__ = ["MIN_RAYS_PER_VOXEL", "MIN_CELLS_PER_VOXEL", "auto_flow_factor", "cells_per_voxel", "ray_binning",
           "ray_grid", "bin_cells", "bin_quiet", "binned_sigma"]

#: Rays per voxel edge the automatic binning keeps at least (per camera, at the box centre).
MIN_RAYS_PER_VOXEL = 1.25


def cells_per_voxel(cameras, grid: Grid, flow_grid: FlowGrid) -> float:
    """Flow cells per voxel edge at the box centre (median over the cameras)."""
    centre = np.asarray(grid.center, dtype=np.float64)
    px = [grid.voxel_size / pixel_footprint(cam, centre) for cam in cameras]
    return float(np.median(px)) / float(flow_grid.factor)


#: Flow cells per voxel edge the automatic flow grid (``flow.auto_factor``) keeps at least:
#: one sample per voxel edge, the linear basis's Nyquist rate.
MIN_CELLS_PER_VOXEL = 1.0


def auto_flow_factor(cameras, grid: Grid, largest: int) -> int:
    """The flow grid's factor for a run with ``flow.auto_factor``: the largest integer up to
    ``largest`` that leaves at least :data:`MIN_CELLS_PER_VOXEL` flow cells per voxel edge
    (:func:`cells_per_voxel`), at least 1.

    The flow is computed at full resolution and area-averaged onto the flow grid (paper
    sec. 4); each cell gives one tomography ray. Where a voxel spans only two or three
    pixels (the realistic family's 640x480 and 960x720 rigs: 2.0-2.6 px), factor 3 leaves
    fewer rays than voxel edges and the basis functions between them are seen by no ray of
    that camera; factor 2 restores a ray per edge. Where cells are plentiful (paper scale,
    8.2 px per voxel) the factor stays at ``largest`` and the tomography bins its rays
    (:func:`ray_binning`).
    """
    largest = int(largest)
    if not cameras or largest <= 1:
        return max(1, largest)
    px = cells_per_voxel(cameras, grid, FlowGrid(tuple(cameras[0].image_size), 1))
    return max(1, min(largest, int(np.floor(px / MIN_CELLS_PER_VOXEL + 1e-9))))


def ray_binning(cameras, grid: Grid, flow_grid: FlowGrid, requested: int = 0) -> int:
    """Flow cells per tomography ray along each image axis.

    ``requested`` > 0 is used as given (1 = a ray per flow cell, the paper); 0 chooses the
    largest ``b`` with at least :data:`MIN_RAYS_PER_VOXEL` rays per voxel edge (1 when the
    cells are not finer than that).
    """
    if int(requested) > 0:
        return int(requested)
    if not cameras:
        return 1
    return max(1, int(np.floor(cells_per_voxel(cameras, grid, flow_grid) / MIN_RAYS_PER_VOXEL + 1e-9)))


def ray_grid(flow_grid: FlowGrid, b: int) -> FlowGrid:
    """The grid of the tomography's rays: blocks of ``b x b`` flow cells (``factor * b`` pixels).

    Its shape is the flow grid's divided by ``b`` (rounded down: the last partial block of
    a row or column is left out), and each ray's image point is the centre of its block's
    cells (``FlowGrid.pixel_centres`` of the coarser grid).
    """
    if int(b) < 1:
        raise ValueError(f"ray binning must be at least 1, got {b}")
    return FlowGrid(tuple(flow_grid.image_size), int(flow_grid.factor) * int(b))


def _blocks(a: np.ndarray, b: int) -> np.ndarray:
    """``a`` (C, h, w, ...) as (C, h // b, b, w // b, b, ...) (the partial edge blocks cut off)."""
    C, h, w = a.shape[:3]
    hb, wb = h // b, w // b
    return a[:, :hb * b, :wb * b].reshape((C, hb, b, wb, b) + a.shape[3:])


def bin_cells(a: np.ndarray, b: int, *, min_valid: float = 0.5) -> np.ndarray:
    """Block means of per-cell measurements (flows or right-hand sides) on the ray grid.

    Parameters
    ----------
    a : ndarray, shape (C, h, w, k)
        Per flow cell; NaN marks an invalid cell (``deflection_stage``'s invalid pixels,
        an excluded frame).
    b : int
        Cells per block edge (1 returns ``a`` unchanged).
    min_valid : float
        A block with fewer than this fraction of finite cells (all ``k`` components finite)
        is NaN (an invalid ray, dropped from the solve); otherwise the mean of its finite
        cells.

    Returns
    -------
    ndarray, shape (C, h // b, w // b, k), float64
    """
    a = np.asarray(a)
    if int(b) == 1:
        return a
    b = int(b)
    C, h, w = a.shape[:3]
    flat = np.ascontiguousarray(a.reshape(C, h, w, -1))
    out = np.empty((C, h // b, w // b, flat.shape[-1]), np.float64)
    # one pass in a compiled kernel (the numpy version made four float64 temporaries of
    # the whole stack; docs/tuning.md, "Speed")
    _bin_kernel(flat, b, float(min_valid) * b * b, out)
    return out.reshape((C, h // b, w // b) + a.shape[3:])


def bin_quiet(quiet: np.ndarray, b: int) -> np.ndarray:
    """Rays whose whole block of cells is quiet (e.g. outside every flow mask), (C, h // b, w // b)."""
    quiet = np.asarray(quiet, dtype=bool)
    if int(b) == 1:
        return quiet
    return _blocks(quiet, int(b)).all(axis=(2, 4))


def binned_sigma(sigma, b: int) -> np.ndarray:
    """Width of the flow averaging in units of the ray grid: ``sqrt(sigma^2 + (b^2 - 1) / 12) / b``
    for a Gaussian of ``sigma`` flow cells followed by the block mean (0 stays 0: no model)."""
    s = np.asarray(sigma, dtype=np.float64)
    if int(b) == 1:
        return s
    return np.where(s > 0, np.sqrt(s * s + (b * b - 1) / 12.0) / b, 0.0)
