"""Visual hull of the flow from per-camera masks (paper sec. 4 "Visual hull generation", sec. 5).

A voxel survives if its footprint touches the mask of every camera that sees it. The
test is conservative: a voxel is kept by a camera if the distance (in flow-grid pixels)
from its projected centre to the nearest mask pixel is at most the radius of its
projected bounding sphere plus half a pixel diagonal (plus ``margin_px``). Voxels seen by
fewer than ``min_views`` cameras are carved (nothing can be reconstructed there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid
from schlieren.pipeline.params import param

__all__ = ["HullParams", "visual_hull"]


@dataclass(frozen=True)
class HullParams:
    """Parameters of :func:`visual_hull`.

    Attributes
    ----------
    margin_px : float
        Extra tolerance, flow-grid pixels, added to every voxel's projected radius.
    min_views : int
        A voxel seen (projected inside the flow grid, in front of the camera) by fewer
        cameras is carved.
    """

    margin_px: float = param(0.0, unit="flow cells", ge=0, le=100)
    min_views: int = param(1, unit="cameras", ge=1, le=1000)


def visual_hull(masks: np.ndarray, cameras: list[Camera], grid: Grid, flow_grid: FlowGrid, *,
                params: HullParams = HullParams()) -> np.ndarray:
    """Carve the voxels whose projection falls outside the mask of any camera that sees them.

    Parameters
    ----------
    masks : ndarray, shape (C, h, w) bool
        Conservative flow masks on the flow grid, one per camera.
    cameras : list of Camera
        The C calibrated cameras (distortion included via ``Camera.project``).
    grid : Grid
        Reconstruction grid.
    flow_grid : FlowGrid
        Maps image pixels to mask pixels (``(h, w) == flow_grid.shape``).
    params : HullParams

    Returns
    -------
    hull : ndarray, shape (nz, ny, nx) bool
    """
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3 or masks.shape[0] != len(cameras) or masks.shape[1:] != flow_grid.shape:
        raise ValueError(f"masks {masks.shape} must be (len(cameras), *flow_grid.shape) = "
                         f"({len(cameras)}, {flow_grid.shape})")
    X = grid.centres().reshape(-1, 3)
    h_rows, h_cols = flow_grid.shape
    f = flow_grid.factor
    # Only the voxels every earlier camera kept are tested (the result is the same: a
    # carved voxel stays carved, and a kept voxel has been seen by all earlier cameras),
    # so the later cameras project a hull-sized set instead of the whole grid.
    cand = np.arange(len(X))
    views = np.zeros(len(X), np.int32)
    rad_world = 0.5 * np.sqrt(3.0) * grid.voxel_size
    for c, cam in enumerate(cameras):
        if cand.size == 0:  # everything carved already
            break
        Xk = X[cand]
        uv = cam.project(Xk)
        depth = (Xk @ cam.R.T + cam.t)[:, 2]
        col = (uv[:, 0] - (f - 1) / 2.0) / f
        row = (uv[:, 1] - (f - 1) / 2.0) / f
        finite = np.isfinite(col) & np.isfinite(row) & (depth > 0)
        inside = finite & (col >= -0.5) & (col <= h_cols - 0.5) & (row >= -0.5) & (row <= h_rows - 0.5)
        views[cand] += inside
        if not masks[c].any():
            cand = cand[~inside]
            continue
        # Distance (flow pixels) from every pixel centre to the nearest mask pixel centre.
        dist = ndi.distance_transform_edt(~masks[c])
        ri = np.clip(np.rint(row[inside]).astype(np.int64), 0, h_rows - 1)
        ci = np.clip(np.rint(col[inside]).astype(np.int64), 0, h_cols - 1)
        # Projected radius of the voxel's bounding sphere (pinhole scale; distortion is
        # close to 1 near the volume), in flow pixels, plus the rounding to a pixel centre.
        fpx = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        r_px = rad_world * fpx / depth[inside] / f
        tol = r_px + np.sqrt(0.5) + params.margin_px
        ok = np.ones(len(cand), bool)
        ok[inside] = dist[ri, ci] <= tol
        cand = cand[ok]
    keep = np.zeros(len(X), bool)
    keep[cand] = True
    keep &= views >= params.min_views
    return keep.reshape(grid.shape)
