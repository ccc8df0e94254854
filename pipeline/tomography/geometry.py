"""Per-session tomography geometry: rays, ``d_in``, ``X_c`` and the projection matrix.

Computed once per session (cameras, grid and flow grid fixed) and reused by every frame;
per frame only the hull restriction and the right-hand sides change (paper sec. 5).
The workers build it (or load it with :func:`load_geometry` from arrays written by
storage) and cache it per process keyed by :func:`content_hash`; it is never shipped
through the task graph.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid
from schlieren.pipeline.tomography.projection import build_projection, prune_rows
from schlieren.pipeline.tomography.params import TomoParams

__all__ = ["TomoGeometry", "build_geometry", "content_hash", "save_geometry", "load_geometry",
           "GEOMETRY_VERSION"]

log = logging.getLogger(__name__)

#: Bumped whenever the meaning of the stored arrays changes (part of the content hash).
GEOMETRY_VERSION = 1


@dataclass(frozen=True, eq=False)
class TomoGeometry:
    """Everything about the rays that does not change from frame to frame.

    Attributes
    ----------
    grid : Grid
    flow_shape : tuple of int
        ``(C, h, w)``: cameras and flow-grid rows and columns; rays are numbered in
        this C order (``ray = (c * h + i) * w + j``).
    centers : ndarray, shape (C, 3)
        Camera optical centres (world, metres).
    rot : ndarray, shape (C, 3, 3)
        World -> camera rotations.
    bg_point, bg_normal : ndarray, shape (C, 3)
        Background planes.
    xy : ndarray, shape (C, h, w, 2)
        Undistorted normalised image coordinates of the flow-grid pixel centres.
    jac : ndarray, shape (C, h, w, 2, 2)
        ``d xy / d (u, v)`` at those pixels (1/pixel): linearises the undistortion for
        the sub-pixel to few-pixel deflections.
    d_in : ndarray, shape (C, h, w, 3)
        Unit undeflected ray directions (world).
    x_c : ndarray, shape (C, h, w, 3)
        Point of each undeflected ray closest to the volume centre (metres).
    S : scipy.sparse.csr_matrix, shape (C*h*w, nz*ny*nx)
        Line integrals of the normalised basis functions along the straight rays
        (metres); float32 data.
    step : float
        Sampling step (voxels) used for ``S``.
    key : str
        :func:`content_hash` of the inputs.
    """

    grid: Grid
    flow_shape: tuple[int, int, int]
    centers: np.ndarray
    rot: np.ndarray
    bg_point: np.ndarray
    bg_normal: np.ndarray
    xy: np.ndarray
    jac: np.ndarray
    d_in: np.ndarray
    x_c: np.ndarray
    S: sp.csr_matrix
    step: float
    key: str

    @property
    def n_rays(self) -> int:
        return int(np.prod(self.flow_shape))

    @property
    def nbytes(self) -> int:
        arrs = [self.xy, self.jac, self.d_in, self.x_c, self.S.data, self.S.indices, self.S.indptr]
        return int(sum(a.nbytes for a in arrs))


def content_hash(cameras: list[Camera], grid: Grid, flow_grid: FlowGrid, params: TomoParams) -> str:
    """SHA-256 over everything the geometry depends on (cameras, grid, flow grid, step, prune)."""
    h = hashlib.sha256()
    h.update(f"schlieren-tomo-geometry/{GEOMETRY_VERSION}".encode())
    for cam in cameras:
        for arr in (cam.K, cam.dist, cam.R, cam.t, cam.bg_point, cam.bg_normal):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        h.update(repr(tuple(cam.image_size)).encode())
    h.update(repr((grid.vmin, grid.vmax, grid.voxel_size)).encode())
    h.update(repr((tuple(flow_grid.image_size), int(flow_grid.factor))).encode())
    h.update(repr(float(params.step)).encode())
    if params.prune > 0:  # (absent when 0: the caches of unpruned geometries keep their keys)
        h.update(repr(("prune", float(params.prune))).encode())
    return h.hexdigest()


def _undistort_jacobian(cam: Camera, uv: np.ndarray, xy: np.ndarray, eps: float = 0.5) -> np.ndarray:
    """Central-difference Jacobian of ``cam.normalized`` at ``uv`` (shape (..., 2, 2))."""
    if not cam.has_distortion:
        Kinv = np.linalg.inv(cam.K)[:2, :2]
        return np.broadcast_to(Kinv, uv.shape[:-1] + (2, 2)).copy()
    jac = np.empty(uv.shape[:-1] + (2, 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = eps
        jac[..., :, k] = (cam.normalized(uv + e) - cam.normalized(uv - e)) / (2 * eps)
    return jac


def build_geometry(cameras: list[Camera], grid: Grid, flow_grid: FlowGrid, *,
                   params: TomoParams = TomoParams()) -> TomoGeometry:
    """Rays of every flow-grid pixel of every camera and the full-grid projection matrix.

    Parameters
    ----------
    cameras : list of Camera
        Calibrated cameras (distortion is removed through ``Camera.rays``).
    grid : Grid
        Reconstruction grid; basis functions sit at the voxel centres.
    flow_grid : FlowGrid
        The deflection grid, the same for every camera.
    params : TomoParams
        Only ``step`` (sampling step in voxels) matters here.

    Returns
    -------
    TomoGeometry
    """
    rows, cols = flow_grid.shape
    uv = flow_grid.pixel_centres()
    C = len(cameras)
    xy = np.empty((C, rows, cols, 2))
    jac = np.empty((C, rows, cols, 2, 2))
    d_in = np.empty((C, rows, cols, 3))
    x_c = np.empty((C, rows, cols, 3))
    centre = np.asarray(grid.center, dtype=np.float64)
    for c, cam in enumerate(cameras):
        xy[c] = cam.normalized(uv)
        jac[c] = _undistort_jacobian(cam, uv, xy[c])
        d = np.concatenate([xy[c], np.ones((rows, cols, 1))], axis=-1) @ cam.R
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d_in[c] = d
        o = cam.center
        s = (centre - o) @ d.reshape(-1, 3).T
        x_c[c] = o + s.reshape(rows, cols, 1) * d
    origins = np.repeat(np.stack([cam.center for cam in cameras]), rows * cols, axis=0)
    S = build_projection(origins, d_in.reshape(-1, 3), grid.shape, grid.origin, grid.voxel_size,
                         step=params.step)
    if params.prune > 0:
        S = prune_rows(S, params.prune)
    log.info("tomography geometry: %d rays, grid %s, S nnz %d (%.1f MB)", S.shape[0], grid.shape,
             S.nnz, (S.data.nbytes + S.indices.nbytes + S.indptr.nbytes) / 1e6)
    return TomoGeometry(
        grid=grid,
        flow_shape=(C, rows, cols),
        centers=np.stack([cam.center for cam in cameras]),
        rot=np.stack([cam.R for cam in cameras]),
        bg_point=np.stack([cam.bg_point for cam in cameras]),
        bg_normal=np.stack([cam.bg_normal for cam in cameras]),
        xy=xy, jac=jac, d_in=d_in, x_c=x_c, S=S, step=float(params.step),
        key=content_hash(cameras, grid, flow_grid, params),
    )


def save_geometry(geom: TomoGeometry) -> dict[str, np.ndarray]:
    """Plain arrays for storage (each can be written as ``.npy`` and memory-mapped)."""
    g = geom.grid
    return {
        "grid": np.array([*g.vmin, *g.vmax, g.voxel_size], dtype=np.float64),
        "flow_shape": np.array(geom.flow_shape, dtype=np.int64),
        "centers": geom.centers, "rot": geom.rot,
        "bg_point": geom.bg_point, "bg_normal": geom.bg_normal,
        "xy": geom.xy, "jac": geom.jac, "d_in": geom.d_in, "x_c": geom.x_c,
        "S_indptr": geom.S.indptr, "S_indices": geom.S.indices, "S_data": geom.S.data,
        "S_shape": np.array(geom.S.shape, dtype=np.int64),
        "step": np.array(geom.step, dtype=np.float64),
        "key": np.array(geom.key),
    }


def load_geometry(arrays: dict[str, np.ndarray]) -> TomoGeometry:
    """Inverse of :func:`save_geometry` (arrays may be read-only memory maps)."""
    gv = np.asarray(arrays["grid"], dtype=np.float64)
    grid = Grid(tuple(gv[:3]), tuple(gv[3:6]), float(gv[6]))
    shape = tuple(int(v) for v in arrays["S_shape"])
    S = sp.csr_matrix((arrays["S_data"], arrays["S_indices"], arrays["S_indptr"]), shape=shape,
                      copy=False)
    return TomoGeometry(
        grid=grid,
        flow_shape=tuple(int(v) for v in arrays["flow_shape"]),
        centers=np.asarray(arrays["centers"]), rot=np.asarray(arrays["rot"]),
        bg_point=np.asarray(arrays["bg_point"]), bg_normal=np.asarray(arrays["bg_normal"]),
        xy=np.asarray(arrays["xy"]), jac=np.asarray(arrays["jac"]),
        d_in=np.asarray(arrays["d_in"]), x_c=np.asarray(arrays["x_c"]), S=S,
        step=float(arrays["step"]), key=str(arrays["key"]),
    )
