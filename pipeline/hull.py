"""Visual hull of the flow from per-camera masks (paper sec. 4 "Visual hull generation", sec. 5).

A voxel survives if its footprint touches the mask of every camera that sees it (beyond the
paper, optionally but for ``max_misses`` cameras, or but for a camera whose mask disagrees with
the others' consensus in that frame: ``outlier_ratio``). The test is conservative: a voxel
is kept by a camera if the distance (in flow-grid pixels) from its projected centre to the
nearest mask pixel is at most the radius of its projected bounding sphere plus half a pixel
diagonal (plus ``margin_px``). Voxels seen by
fewer than ``min_views`` cameras are carved (nothing can be reconstructed there).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid
from schlieren.pipeline.params import param, parameters

__all__ = ["HullParams", "HullProjection", "hull_projection", "visual_hull", "lone_rejections"]


@parameters
class HullParams:
    """Parameters of :func:`visual_hull`."""

    margin_px: float = param(
        0.0, unit="flow cells", ge=0, le=100,
        help="Extra tolerance added to every voxel's projected radius.")
    min_views: int = param(
        1, unit="cameras", ge=1, le=1000,
        help="A voxel seen by fewer cameras (projected inside the flow grid, in front of the camera) is "
             "carved.")
    max_misses: int = param(
        0, unit="cameras", ge=0, le=1000,
        help="A voxel is carved when more than this many of the cameras that see it put it outside their "
             "mask: 0 is the paper's strict intersection; 1 may suit many cameras with ragged masks from "
             "lossy video.",
        see="benchmarks/results/realistic_hull_misses1.md", tuned=True)
    outlier_ratio: float = param(
        3.0, unit="1", ge=0, le=1000,
        help="With `max_misses` 0, a camera whose mask alone rejects more than this many times as many voxels as "
             "the median camera's (voxels all others keep) disagrees with the rig's consensus in that frame, and the "
             "voxels only it rejects are kept; masks that agree keep the strict intersection exactly (0 disables).",
        see="benchmarks/results/lab_hull.md", tuned=True)


@dataclass(frozen=True)
class HullProjection:
    """Where every voxel centre of a grid falls in each camera's flow grid, and how close to
    a mask pixel it must come (:func:`hull_projection`): everything :func:`visual_hull`
    needs that does not depend on the masks, so the hulls of a sequence share it.

    Attributes
    ----------
    pixel : ndarray, shape (C, N) int32
        Flat flow-grid index of the pixel nearest to each voxel's projection; -1 where the
        voxel does not project inside the flow grid, in front of the camera.
    tol : ndarray, shape (C, N) float32
        The voxel's projected bounding-sphere radius plus half a pixel diagonal plus
        ``margin_px`` (flow pixels).
    """

    pixel: np.ndarray
    tol: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.pixel.nbytes + self.tol.nbytes)


def _project_voxels(cam: Camera, X: np.ndarray, grid: Grid, flow_grid: FlowGrid,
                    params: HullParams) -> tuple[np.ndarray, np.ndarray]:
    """One camera's ``(pixel, tol)`` rows of :class:`HullProjection` for the voxel centres ``X``."""
    h_rows, h_cols = flow_grid.shape
    f = flow_grid.factor
    pixel = np.full(len(X), -1, np.int32)
    tol = np.zeros(len(X), np.float32)
    uv = cam.project(X)
    depth = (X @ cam.R.T + cam.t)[:, 2]
    col = (uv[:, 0] - (f - 1) / 2.0) / f
    row = (uv[:, 1] - (f - 1) / 2.0) / f
    finite = np.isfinite(col) & np.isfinite(row) & (depth > 0)
    inside = finite & (col >= -0.5) & (col <= h_cols - 0.5) & (row >= -0.5) & (row <= h_rows - 0.5)
    ri = np.clip(np.rint(row[inside]).astype(np.int64), 0, h_rows - 1)
    ci = np.clip(np.rint(col[inside]).astype(np.int64), 0, h_cols - 1)
    pixel[inside] = ri * h_cols + ci
    # Projected radius of the voxel's bounding sphere (pinhole scale; distortion is close
    # to 1 near the volume), in flow pixels, plus the rounding to a pixel centre.
    rad_world = 0.5 * np.sqrt(3.0) * grid.voxel_size
    fpx = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    tol[inside] = rad_world * fpx / depth[inside] / f + np.sqrt(0.5) + params.margin_px
    return pixel, tol


def hull_projection(cameras: list[Camera], grid: Grid, flow_grid: FlowGrid, *,
                    params: HullParams = HullParams()) -> HullProjection:
    """The mask-independent part of :func:`visual_hull` for every voxel of the grid. 8 bytes
    per voxel and camera."""
    X = grid.centres().reshape(-1, 3)
    rows = [_project_voxels(cam, X, grid, flow_grid, params) for cam in cameras]
    return HullProjection(np.stack([r[0] for r in rows]).reshape(len(cameras), len(X)),
                          np.stack([r[1] for r in rows]).reshape(len(cameras), len(X)))


def _distance_to_mask(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance (flow pixels) from every pixel centre to the nearest mask pixel
    centre, float32 (OpenCV's exact transform, faster than scipy's; docs/tuning.md, "Speed")."""
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def visual_hull(masks: np.ndarray, cameras: list[Camera], grid: Grid, flow_grid: FlowGrid, *,
                params: HullParams = HullParams(), projection: HullProjection | None = None) -> np.ndarray:
    """Carve the voxels whose projection falls outside the mask of any camera that sees them
    (of more than ``params.max_misses`` cameras; with ``params.outlier_ratio``, a voxel only an
    outlier camera rejects is kept: :func:`lone_rejections`).

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
    projection : HullProjection, optional
        :func:`hull_projection` of these cameras, grid, flow grid and ``params`` (the same
        for every frame; a sequence computes it once). Without it, each camera projects
        only the voxels every earlier camera kept.

    Returns
    -------
    hull : ndarray, shape (nz, ny, nx) bool
    """
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3 or masks.shape[0] != len(cameras) or masks.shape[1:] != flow_grid.shape:
        raise ValueError(f"masks {masks.shape} must be (len(cameras), *flow_grid.shape) = "
                         f"({len(cameras)}, {flow_grid.shape})")
    n_vox = int(np.prod(grid.shape))
    if projection is not None and projection.pixel.shape != (len(cameras), n_vox):
        raise ValueError(f"projection {projection.pixel.shape} is not of {len(cameras)} cameras x {n_vox} voxels")
    limit = params.max_misses + (1 if params.outlier_ratio > 0 else 0)
    cand, views, misses, who = _carve(masks, cameras, grid, flow_grid, params, projection, limit)
    if params.outlier_ratio > 0:
        cand = cand[(misses[cand] <= params.max_misses) | _forgiven(cand, misses, who, params, len(cameras))]
    keep = np.zeros(n_vox, bool)
    keep[cand] = True
    keep &= views >= params.min_views
    return keep.reshape(grid.shape)


def lone_rejections(masks: np.ndarray, cameras: list[Camera], grid: Grid, flow_grid: FlowGrid, *,
                    params: HullParams = HullParams(), projection: HullProjection | None = None) -> np.ndarray:
    """How many voxels each camera's mask alone rejects (every other camera that sees them keeps
    them): the counts ``outlier_ratio`` compares with the median camera's.

    Returns
    -------
    counts : ndarray, shape (C,) int
    """
    _, _, misses, who = _carve(np.asarray(masks, bool), cameras, grid, flow_grid, params, projection, 1)
    return np.bincount(who[misses == 1], minlength=len(cameras))


def _carve(masks, cameras, grid, flow_grid, params, projection, limit):
    """The voxels that no more than ``limit`` cameras put outside their masks, with every voxel's
    count of cameras that see it, of cameras that reject it and the last camera that did."""
    # Only the voxels every earlier camera kept (rejected by at most ``limit``) are tested (the
    # result is the same: a carved voxel stays carved), so the later cameras look up (or
    # project) a hull-sized set instead of the whole grid.
    n_vox = int(np.prod(grid.shape))
    cand = np.arange(n_vox)
    views = np.zeros(n_vox, np.int32)
    misses = np.zeros(n_vox, np.int32) if limit > 0 else None
    who = np.full(n_vox, -1, np.int32) if limit > 0 else None
    X = grid.centres().reshape(-1, 3) if projection is None else None
    for c, cam in enumerate(cameras):
        if cand.size == 0:  # everything carved already
            break
        if projection is not None:
            pix, tol = projection.pixel[c, cand], projection.tol[c, cand]
        else:
            pix, tol = _project_voxels(cam, X[cand], grid, flow_grid, params)
        inside = pix >= 0
        views[cand] += inside
        if not masks[c].any():  # rejects every voxel it sees
            ok = ~inside
        else:
            dist = _distance_to_mask(masks[c]).ravel()
            ok = np.ones(len(cand), bool)
            ok[inside] = dist[pix[inside]] <= tol[inside]
        if misses is not None:  # carved only once more than ``limit`` cameras rejected it
            misses[cand[~ok]] += 1
            who[cand[~ok]] = c
            ok |= misses[cand] <= limit
        cand = cand[ok]
    if misses is None:
        misses = np.zeros(n_vox, np.int32)
    return cand, views, misses, who


def _forgiven(cand, misses, who, params: HullParams, n_cameras: int) -> np.ndarray:
    """Which of ``cand`` (voxels rejected by at most ``max_misses + 1`` cameras) only outlier
    cameras' masks carve beyond ``max_misses``: a camera is an outlier when the voxels it alone
    rejects (every other camera keeps them) exceed ``outlier_ratio`` times the median camera's
    count, and at least one voxel."""
    extra = misses[cand] == params.max_misses + 1
    alone = np.bincount(who[cand[extra]], minlength=n_cameras) if params.max_misses == 0 else \
        np.zeros(n_cameras, np.int64)
    outlier = alone > params.outlier_ratio * max(float(np.median(alone)), 1.0)
    return extra & outlier[np.maximum(who[cand], 0)]
