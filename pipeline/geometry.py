"""Plain geometric data types shared by every stage: cameras, volume grid, flow grid.

Conventions (user documentation: docs/session.md):

* World frame right-handed, ``z`` up, metres.
* Camera: OpenCV pinhole with distortion, ``x_cam = R @ x_world + t``.
* Image pixel coordinates ``(u, v)`` = (column, row), pixel *centres* at integer
  coordinates (OpenCV convention); image arrays are indexed ``[row, column]``.
* Volume arrays are indexed ``[z, y, x]``; ``Grid.origin`` is the world position of the
  centre of voxel ``[0, 0, 0]`` as ``(x, y, z)``.

Nothing here touches files, dask or zarr.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["Camera", "Grid", "FlowGrid", "Medium", "rodrigues", "pixel_footprint", "auto_voxel_size"]


def rodrigues(rvec) -> np.ndarray:
    """Rotation matrix from an OpenCV rotation vector (axis * angle, radians)."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return R


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera with its background plane and rolling shutter.

    Parameters
    ----------
    name : str
    K : ndarray, shape (3, 3)
        Intrinsic matrix (pixels).
    dist : ndarray, shape (k,)
        OpenCV distortion coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
    R : ndarray, shape (3, 3)
        World -> camera rotation.
    t : ndarray, shape (3,)
        World -> camera translation (metres).
    image_size : tuple of int
        ``(width, height)`` in pixels.
    bg_point, bg_normal : ndarray, shape (3,)
        A point on the background plane and its unit normal (world).
    line_time : float
        Seconds between the exposure starts of successive rows (0 = global shutter).
    time_offset : float or None
        Session-clock time at which row 0 of frame 0 starts (None until synchronised).
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple[int, int]
    bg_point: np.ndarray
    bg_normal: np.ndarray
    line_time: float = 0.0
    time_offset: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=np.float64).ravel())
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))
        n = np.asarray(self.bg_normal, dtype=np.float64).reshape(3)
        object.__setattr__(self, "bg_normal", n / np.linalg.norm(n))
        object.__setattr__(self, "bg_point", np.asarray(self.bg_point, dtype=np.float64).reshape(3))
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))

    # -- basic geometry -------------------------------------------------------------
    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    @property
    def optical_axis(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    @staticmethod
    def background_from_distance(R, t, distance: float) -> tuple[np.ndarray, np.ndarray]:
        """Plane perpendicular to the optical axis at ``distance`` in front of the camera."""
        R = np.asarray(R, dtype=np.float64)
        C = -R.T @ np.asarray(t, dtype=np.float64)
        axis = R[2]
        return C + distance * axis, -axis

    def with_time_offset(self, offset: float) -> "Camera":
        return Camera(self.name, self.K, self.dist, self.R, self.t, self.image_size,
                      self.bg_point, self.bg_normal, self.line_time, float(offset))

    # -- projection -----------------------------------------------------------------
    def project(self, X: np.ndarray) -> np.ndarray:
        """Project world points to distorted pixel coordinates.

        Parameters
        ----------
        X : ndarray, shape (..., 3)

        Returns
        -------
        uv : ndarray, shape (..., 2)
            ``(u, v)`` = (column, row). Points behind the camera give NaN.
        """
        X = np.asarray(X, dtype=np.float64)
        shp = X.shape[:-1]
        Xc = X.reshape(-1, 3) @ self.R.T + self.t
        behind = Xc[:, 2] <= 0
        if self.has_distortion:
            uv, _ = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
            uv = uv.reshape(-1, 2)
        else:
            z = np.where(behind, 1.0, Xc[:, 2])
            xn = Xc[:, :2] / z[:, None]
            uv = xn @ self.K[:2, :2].T + self.K[:2, 2]
        uv = uv.astype(np.float64)
        uv[behind] = np.nan
        return uv.reshape(*shp, 2)

    def normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates of pixel positions.

        Parameters
        ----------
        uv : ndarray, shape (..., 2)

        Returns
        -------
        xy : ndarray, shape (..., 2), such that the ray direction in camera frame is (x, y, 1).
        """
        uv = np.asarray(uv, dtype=np.float64)
        shp = uv.shape[:-1]
        flat = uv.reshape(-1, 2)
        if self.has_distortion:
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            src = flat.reshape(-1, 1, 2)
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
                xy = cv2.undistortPointsIter(src, self.K, self.dist, None, None, crit)
            else:  # OpenCV 5 takes the criteria in undistortPoints
                xy = cv2.undistortPoints(src, self.K, self.dist, None, None, None, crit)
            xy = xy.reshape(-1, 2).astype(np.float64)
            # Polish with fixed-point steps on the forward model: OpenCV's iteration stops
            # early for strong distortion; a few corrections make the round trip exact.
            Kinv2 = np.linalg.inv(self.K[:2, :2])
            for _ in range(3):
                pts = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
                uv_hat, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                              self.K, self.dist)
                xy = xy + (flat - uv_hat.reshape(-1, 2)) @ Kinv2.T
        else:
            Kinv = np.linalg.inv(self.K)
            xy = flat @ Kinv[:2, :2].T + Kinv[:2, 2]
        return xy.reshape(*shp, 2)

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rays through pixel positions (distortion removed).

        Returns
        -------
        origin : ndarray, shape (3,)
            The optical centre.
        direction : ndarray, shape (..., 3)
            Unit directions in world coordinates.
        """
        xy = self.normalized(uv)
        d_cam = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        d = d_cam @ self.R  # R^T applied to row vectors
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return self.center, d

    def pixel_grid(self, factor: int = 1) -> np.ndarray:
        """Pixel centres of the image, or of the flow grid for a downsampling ``factor``.

        Returns
        -------
        uv : ndarray, shape (H // factor, W // factor, 2)
        """
        fg = FlowGrid(self.image_size, factor)
        return fg.pixel_centres()

    # -- background -----------------------------------------------------------------
    def intersect_background(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Points where rays ``origin + s * direction`` meet the background plane.

        Parameters
        ----------
        origin : ndarray, shape (3,) or (..., 3)
        direction : ndarray, shape (..., 3)

        Returns
        -------
        points : ndarray, shape (..., 3); NaN where the ray is parallel or points away.
        """
        origin = np.asarray(origin, dtype=np.float64)
        direction = np.asarray(direction, dtype=np.float64)
        denom = direction @ self.bg_normal
        num = (self.bg_point - origin) @ self.bg_normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = num / denom
        s = np.where((np.abs(denom) > 1e-15) & (s > 0), s, np.nan)
        return origin + s[..., None] * direction

    def background_distance(self) -> float:
        """Signed distance of the camera centre in front of its background plane."""
        return float((self.center - self.bg_point) @ self.bg_normal)


@dataclass(frozen=True)
class FlowGrid:
    """The coarse grid on which deflections are stored (area-downsampled image pixels).

    Flow pixel ``(i, j)`` covers image rows ``f*i .. f*i+f-1`` and columns
    ``f*j .. f*j+f-1``; its centre is at image coordinate ``f*j + (f-1)/2``.
    """

    image_size: tuple[int, int]
    factor: int = 3

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, columns)`` of the flow grid."""
        w, h = self.image_size
        return h // self.factor, w // self.factor

    def pixel_centres(self) -> np.ndarray:
        """Image-pixel coordinates ``(u, v)`` of the flow-grid cell centres, shape (rows, cols, 2)."""
        rows, cols = self.shape
        f = self.factor
        u = f * np.arange(cols, dtype=np.float64) + (f - 1) / 2.0
        v = f * np.arange(rows, dtype=np.float64) + (f - 1) / 2.0
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def row_of_cell(self) -> np.ndarray:
        """Image row at the centre of each flow-grid row, shape (rows,)."""
        return self.factor * np.arange(self.shape[0], dtype=np.float64) + (self.factor - 1) / 2.0


@dataclass(frozen=True)
class Grid:
    """Regular reconstruction grid; arrays are indexed ``[z, y, x]``.

    Parameters
    ----------
    vmin, vmax : ndarray, shape (3,)
        Box corners (x, y, z), metres.
    voxel_size : float
        Edge length of a voxel, metres.
    """

    vmin: tuple[float, float, float]
    vmax: tuple[float, float, float]
    voxel_size: float

    def __post_init__(self):
        object.__setattr__(self, "vmin", tuple(float(v) for v in self.vmin))
        object.__setattr__(self, "vmax", tuple(float(v) for v in self.vmax))
        object.__setattr__(self, "voxel_size", float(self.voxel_size))

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        ext = np.asarray(self.vmax) - np.asarray(self.vmin)
        return tuple(int(round(e / self.voxel_size)) for e in ext)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape ``(nz, ny, nx)``."""
        nx, ny, nz = self.shape_xyz
        return nz, ny, nx

    @property
    def origin(self) -> np.ndarray:
        """World ``(x, y, z)`` of the centre of voxel ``[0, 0, 0]``."""
        return np.asarray(self.vmin) + 0.5 * self.voxel_size

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.vmin) + np.asarray(self.vmax))

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel-centre coordinates along x, y, z (each 1-D)."""
        o = self.origin
        nx, ny, nz = self.shape_xyz
        h = self.voxel_size
        return (o[0] + h * np.arange(nx), o[1] + h * np.arange(ny), o[2] + h * np.arange(nz))

    def centres(self) -> np.ndarray:
        """World coordinates of every voxel centre, shape (nz, ny, nx, 3) as (x, y, z)."""
        x, y, z = self.axes()
        zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
        return np.stack([xx, yy, zz], axis=-1)

    def corners(self) -> np.ndarray:
        """The 8 box corners, shape (8, 3)."""
        a, b = np.asarray(self.vmin), np.asarray(self.vmax)
        return np.array([[x, y, z] for x in (a[0], b[0]) for y in (a[1], b[1]) for z in (a[2], b[2])])

    def world_to_index(self, X: np.ndarray) -> np.ndarray:
        """Continuous voxel index ``(ix, iy, iz)`` of world points (voxel centres are integers)."""
        return (np.asarray(X, dtype=np.float64) - self.origin) / self.voxel_size

    def to_attrs(self) -> dict:
        return {"origin": [float(v) for v in self.origin], "voxel_size": [self.voxel_size] * 3}


@dataclass(frozen=True)
class Medium:
    """Ambient medium used for derived quantities (SPEC ``medium``)."""

    n_ambient: float = 1.00029
    T_ambient: float = 293.15
    p_ambient: float = 101325.0
    gladstone_dale: float = 2.26e-4

    @property
    def refractivity_ambient(self) -> float:
        return self.n_ambient - 1.0


#: :func:`auto_voxel_size` defaults (chosen on the realistic family's tune cases, see
#: benchmarks/results/realistic.md): image pixels per voxel edge at the volume centre, the
#: largest grid, and the largest projection matrix (ray-voxel crossings) it may imply.
AUTO_PX_PER_VOXEL = 2.0
AUTO_MAX_VOXELS = 4_000_000
AUTO_MAX_CROSSINGS = 2.0e8


def pixel_footprint(camera: Camera, point) -> float:
    """Metres per image pixel at ``point`` (x, y, z): its distance from the camera over the focal length."""
    d = float(np.linalg.norm(np.asarray(point, dtype=np.float64) - camera.center))
    f = 0.5 * float(camera.K[0, 0] + camera.K[1, 1])
    return d / f


def auto_voxel_size(cameras, vmin, vmax, *, px_per_voxel: float = AUTO_PX_PER_VOXEL,
                    max_voxels: int = AUTO_MAX_VOXELS, max_crossings: float = AUTO_MAX_CROSSINGS,
                    flow_factor: int = 3) -> tuple[float, dict]:
    """The reconstruction voxel from the cameras' pixel footprint at the volume.

    A voxel should span about ``px_per_voxel`` image pixels (the median footprint over the
    cameras at the box centre): finer voxels than the flow can resolve only add unknowns,
    coarser ones throw away the resolution the cameras have (docs/tuning.md, "Voxel and
    flow grid"). Two budgets bound
    it from below: at most ``max_voxels`` voxels in the box, and at most ``max_crossings``
    ray-voxel crossings (flow-grid rays of every camera times the voxels across the box),
    which sets the size of the projection matrix (about 4 bytes x 2 per crossing). The
    result is rounded up to 0.05 mm.

    Returns
    -------
    voxel : float
        Metres.
    info : dict
        ``footprint`` (m/px), ``px_per_voxel`` (achieved), ``limited_by``
        (``"footprint"``, ``"voxels"`` or ``"matrix"``).
    """
    lo = np.asarray(vmin, dtype=np.float64)
    hi = np.asarray(vmax, dtype=np.float64)
    ext = hi - lo
    centre = 0.5 * (lo + hi)
    fp = float(np.median([pixel_footprint(c, centre) for c in cameras]))
    candidates = {"footprint": px_per_voxel * fp,
                  "voxels": float(np.prod(ext) / max(max_voxels, 1)) ** (1.0 / 3.0)}
    rays = sum((int(c.width) // flow_factor) * (int(c.height) // flow_factor) for c in cameras)
    chord = float(np.mean(ext))
    candidates["matrix"] = rays * chord / max_crossings
    limited_by = max(candidates, key=candidates.get)
    v = candidates[limited_by]
    v = float(np.ceil(v / 5e-5 - 1e-9) * 5e-5)
    return v, {"footprint": fp, "px_per_voxel": v / fp, "limited_by": limited_by}
