"""Multi-camera calibration from ChArUco board views (paper sec. 4: "calibrated with
standard techniques" [Zhang 1999]).

The steps, all on arrays (file reading lives in :mod:`schlieren.storage.calibration_io`):

1. :func:`detect_board` finds the ChArUco chessboard corners in one image.
2. :func:`calibrate_intrinsics` runs Zhang's planar calibration for one camera
   (``cv2.calibrateCamera``): ``K``, distortion and one board pose per view.
3. :func:`calibrate_rig` chains the board poses seen by several cameras in the same
   view into camera-to-camera poses, then refines every camera's intrinsics,
   distortion and pose and every board pose jointly by bundle adjustment
   (Levenberg-Marquardt on a Huber cost, block-structured finite-difference Jacobian),
   and finally expresses the rig in the world frame defined by one board view.
4. :func:`background_plane` fits each camera's background plane from views of a
   board laid on the background.

Conventions
-----------
*Views*: view ``i`` of every camera shows the same board pose (frame ``i`` of
synchronised videos, or the ``i``-th image of each camera's image list); a camera
may miss the board in some views (``None``). Cameras are linked through the views
they share.

*Board frame* (OpenCV): origin at the outer top-left corner of the printed board,
``x`` along its ``squares[0]`` columns, ``y`` down the ``squares[1]`` rows of the
printed image, ``z = x cross y`` into the board (away from a viewer of the face).

*World frame* (SPEC: right-handed, ``z`` up, metres): the board pose in view
``world_board_view`` defines it, with its origin at the centre of the board's
chessboard area, and

* ``world_board_orientation="flat"`` (board lying face-up on a horizontal table):
  ``x`` along the board's columns, ``z`` out of the printed face (up),
  ``y = z cross x``;
* ``world_board_orientation="upright"`` (board standing vertically, printed top
  edge up): ``x`` along the board's columns, ``z`` towards the printed top edge
  (up), ``y`` into the board, away from its face.

Cameras are returned as SPEC camera entries: ``x_cam = R @ x_world + t``.
"""

from __future__ import annotations

import functools
import logging
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

__all__ = [
    "BoardSpec",
    "BoardDetection",
    "BoardRenderer",
    "CalibrationError",
    "CalibrationParams",
    "IntrinsicCalibration",
    "CameraCalibration",
    "RigCalibration",
    "detect_board",
    "board_pose",
    "calibrate_intrinsics",
    "calibrate_rig",
    "background_plane",
    "world_from_board",
    "project_points",
]

log = logging.getLogger(__name__)

_N_DIST_FLAGS = {
    0: cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    2: cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    4: cv2.CALIB_FIX_K3,
    5: 0,
    8: cv2.CALIB_RATIONAL_MODEL,
}


class CalibrationError(ValueError):
    """The board views cannot calibrate a camera; ``camera`` names it (or is None)."""

    def __init__(self, message: str, *, camera: str | None = None):
        self.camera = camera
        super().__init__(message)


# ----------------------------------------------------------------------------------
# The board
# ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board.

    Parameters
    ----------
    squares : tuple of int
        ``(columns, rows)`` of chessboard squares, e.g. ``(10, 7)``.
    square_size : float
        Edge of a chessboard square, metres.
    marker_size : float
        Edge of an ArUco marker, metres (< ``square_size``).
    dictionary : str
        Name of the OpenCV predefined ArUco dictionary (``cv2.aruco.DICT_*``).
    legacy_pattern : bool
        Boards printed by OpenCV < 4.6 with an even number of rows use the legacy layout.
    """

    squares: tuple[int, int]
    square_size: float
    marker_size: float
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False

    def __post_init__(self):
        sq = tuple(int(s) for s in self.squares)
        object.__setattr__(self, "squares", sq)
        object.__setattr__(self, "square_size", float(self.square_size))
        object.__setattr__(self, "marker_size", float(self.marker_size))
        if len(sq) != 2 or min(sq) < 2:
            raise CalibrationError(f"board squares must be two integers >= 2, got {self.squares}")
        if not 0.0 < self.marker_size < self.square_size:
            raise CalibrationError(
                f"marker size {self.marker_size} m must be positive and smaller than the "
                f"square size {self.square_size} m")
        if not hasattr(cv2.aruco, self.dictionary):
            raise CalibrationError(f"unknown ArUco dictionary {self.dictionary!r} "
                                   "(expected a cv2.aruco.DICT_* name, e.g. DICT_5X5_100)")
        n_markers = (sq[0] * sq[1]) // 2
        dict_size = len(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList)
        if n_markers > dict_size:
            raise CalibrationError(f"a {sq[0]}x{sq[1]} board needs {n_markers} markers but "
                                   f"{self.dictionary} has only {dict_size}")

    @property
    def n_corners(self) -> int:
        """Number of inner chessboard corners."""
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    @property
    def corner_points(self) -> np.ndarray:
        """Board-frame coordinates of the inner corners by ChArUco id, shape (N, 3), metres."""
        nx = self.squares[0] - 1
        k = np.arange(self.n_corners)
        x = (k % nx + 1) * self.square_size
        y = (k // nx + 1) * self.square_size
        return np.stack([x, y, np.zeros_like(x)], axis=1)

    @property
    def centre(self) -> np.ndarray:
        """Board-frame coordinates of the centre of the chessboard area, shape (3,)."""
        return np.array([0.5 * self.squares[0] * self.square_size,
                         0.5 * self.squares[1] * self.square_size, 0.0])

    def cv_board(self) -> "cv2.aruco.CharucoBoard":
        """The OpenCV board object (cached per spec)."""
        return _cv_board(self)

    def texture(self, pixels_per_square: int, margin_squares: int = 1) -> np.ndarray:
        """Printable board image with a white margin, uint8, shape (H, W).

        Board coordinate ``(X, Y)`` (metres) lies at image coordinate
        ``((X / square_size + margin_squares) * pixels_per_square - 0.5, ...)``
        (pixel centres at integers).
        """
        pps, m = int(pixels_per_square), int(margin_squares)
        size = ((self.squares[0] + 2 * m) * pps, (self.squares[1] + 2 * m) * pps)
        return self.cv_board().generateImage(size, marginSize=m * pps, borderBits=1)


@functools.lru_cache(maxsize=16)
def _cv_board(spec: BoardSpec):
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard(spec.squares, spec.square_size, spec.marker_size, dictionary)
    board.setLegacyPattern(bool(spec.legacy_pattern))
    return board


@functools.lru_cache(maxsize=16)
def _detector(spec: BoardSpec):
    det_params = cv2.aruco.DetectorParameters()
    det_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(spec.cv_board(), cv2.aruco.CharucoParameters(), det_params)


@dataclass(frozen=True, eq=False)
class BoardDetection:
    """ChArUco corners found in one image.

    Attributes
    ----------
    ids : ndarray of int, shape (n,)
        Corner ids (rows of :attr:`BoardSpec.corner_points`).
    corners : ndarray, shape (n, 2)
        Pixel positions ``(u, v)`` of those corners (distorted image).
    n_markers : int
        ArUco markers decoded in the image (diagnostics).
    """

    ids: np.ndarray
    corners: np.ndarray
    n_markers: int = 0

    def __len__(self) -> int:
        return int(len(self.ids))


def _to_gray8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    f = img.astype(np.float64)
    if f.max() <= 1.0:  # float images in [0, 1]
        f = f * 255.0
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def detect_board(image: np.ndarray, board: BoardSpec) -> BoardDetection:
    """Detect the ChArUco corners of ``board`` in an image.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        Grey or BGR image (uint8, uint16 or float in [0, 1]); not modified.
    board : BoardSpec

    Returns
    -------
    BoardDetection
        Possibly empty (no corners found); ids sorted ascending.
    """
    gray = _to_gray8(image)
    ch_corners, ch_ids, _marker_corners, marker_ids = _detector(board).detectBoard(gray)
    n_markers = 0 if marker_ids is None else int(len(marker_ids))
    if ch_ids is None or len(ch_ids) == 0:
        return BoardDetection(np.zeros(0, dtype=np.int64), np.zeros((0, 2)), n_markers)
    ids = np.asarray(ch_ids, dtype=np.int64).ravel()
    corners = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(ids)
    return BoardDetection(ids[order], corners[order], n_markers)


def _usable(det: BoardDetection | None, board: BoardSpec, min_corners: int) -> bool:
    if det is None or len(det) < max(int(min_corners), 4):
        return False
    pts = board.corner_points[det.ids, :2]
    # Reject (near-)collinear corner sets: they do not fix a homography.
    centred = pts - pts.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return bool(s[1] > 0.5 * board.square_size)


# ----------------------------------------------------------------------------------
# Projection (OpenCV pinhole + distortion, vectorised for the bundle adjustment)
# ----------------------------------------------------------------------------------
def project_points(X_cam: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Project camera-frame points with OpenCV's distortion model.

    Parameters
    ----------
    X_cam : ndarray, shape (M, 3)
        Points in the camera frame, metres (z > 0).
    K : ndarray, shape (3, 3)
        Intrinsics (pixels); skew is honoured.
    dist : ndarray, shape (0,), (4,), (5,) or (8,)
        ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``.

    Returns
    -------
    uv : ndarray, shape (M, 2)
        Distorted pixel coordinates.
    """
    X = np.asarray(X_cam, dtype=np.float64)
    d = np.zeros(8)
    dd = np.asarray(dist, dtype=np.float64).ravel()
    d[: min(len(dd), 8)] = dd[:8]
    if len(dd) > 8 and np.any(dd[8:] != 0):
        raise CalibrationError("thin-prism/tilted distortion terms are not supported")
    x = X[:, 0] / X[:, 2]
    y = X[:, 1] / X[:, 2]
    return _distort_pixels(x, y, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d, skew=K[0, 1])


def _distort_pixels(x, y, fx, fy, cx, cy, d, skew=0.0):
    k1, k2, p1, p2, k3, k4, k5, k6 = (d[..., i] for i in range(8))
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + skew * yd + cx, fy * yd + cy], axis=-1)


def _pose_matrix(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def _mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    """Robust mean of 4x4 poses: chordal L2 mean rotation, median translation."""
    M = sum(T[:3, :3] for T in poses)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    t = np.median(np.stack([T[:3, 3] for T in poses]), axis=0)
    return _pose_matrix(R, t)


def board_pose(detection: BoardDetection, board: BoardSpec, *, K: np.ndarray,
               dist: np.ndarray) -> np.ndarray:
    """Board pose in the camera frame from one detection (IPPE + Levenberg-Marquardt).

    Parameters
    ----------
    detection : BoardDetection
        At least 4 non-collinear corners.
    board : BoardSpec
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (k,)

    Returns
    -------
    T : ndarray, shape (4, 4)
        ``x_cam = T[:3, :3] @ x_board + T[:3, 3]`` (metres).
    """
    obj = board.corner_points[detection.ids].astype(np.float64)
    img = detection.corners.astype(np.float64)
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("solvePnP failed on a board view")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    return _pose_matrix(R, tvec)


# ----------------------------------------------------------------------------------
# Single-camera intrinsics (Zhang)
# ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class IntrinsicCalibration:
    """One camera's intrinsics from ``cv2.calibrateCamera``.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (n_dist,)
    rms : float
        RMS reprojection error, pixels.
    poses : dict of int to ndarray (4, 4)
        Board -> camera pose for every view used.
    image_size : tuple of int
        ``(width, height)``.
    """

    K: np.ndarray
    dist: np.ndarray
    rms: float
    poses: dict
    image_size: tuple[int, int]


def _diagnose(name: str, detections, board: BoardSpec, min_corners: int, min_views: int,
              n_usable: int) -> CalibrationError:
    dets = [d for d in detections if d is not None]
    n_images = len(detections)
    n_markers = sum(d.n_markers for d in dets)
    n_corners = sum(len(d) for d in dets)
    if n_images == 0:
        msg = "no board images"
    elif n_markers == 0:
        msg = (f"no ArUco marker of {board.dictionary} found in any of its {n_images} images; "
               "check --dictionary, focus, exposure and that the board is in view")
    elif n_corners == 0:
        msg = (f"{n_markers} markers but no ChArUco corner found in its {n_images} images; "
               f"check --squares {board.squares[0]}x{board.squares[1]} and --legacy-pattern")
    else:
        msg = (f"only {n_usable} of its {n_images} images show the board with at least "
               f"{min_corners} non-collinear corners; at least {min_views} are needed")
    return CalibrationError(msg, camera=name)


def calibrate_intrinsics(detections, image_size, board: BoardSpec, *, n_dist: int = 5,
                         min_corners: int = 6, min_views: int = 4,
                         name: str | None = None) -> IntrinsicCalibration:
    """Zhang's planar calibration of one camera from its board detections.

    Parameters
    ----------
    detections : sequence of BoardDetection or None, length n_views
        One per view (None or too few corners: the view is skipped).
    image_size : tuple of int
        ``(width, height)`` in pixels.
    board : BoardSpec
    n_dist : {0, 2, 4, 5, 8}
        Distortion coefficients to estimate (OpenCV order k1 k2 p1 p2 k3 k4 k5 k6).
    min_corners : int
        Fewest corners for a view to count.
    min_views : int
        Fewest usable views; fewer raise :class:`CalibrationError` naming the camera.
    name : str, optional
        The camera's name, for error messages.

    Returns
    -------
    IntrinsicCalibration
    """
    if n_dist not in _N_DIST_FLAGS:
        raise CalibrationError(f"n_dist must be one of {sorted(_N_DIST_FLAGS)}, got {n_dist}")
    used = [i for i, d in enumerate(detections) if _usable(d, board, min_corners)]
    if len(used) < max(int(min_views), 3):
        raise _diagnose(name, detections, board, min_corners, min_views, len(used))
    W, H = int(image_size[0]), int(image_size[1])
    flags = _N_DIST_FLAGS[n_dist]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)

    def run(views, K=None, dist=None):
        obj = [board.corner_points[detections[i].ids].astype(np.float32) for i in views]
        img = [detections[i].corners.astype(np.float32).reshape(-1, 1, 2) for i in views]
        f = flags if K is None else flags | cv2.CALIB_USE_INTRINSIC_GUESS
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, (W, H), K, dist, flags=f, criteria=crit)
        errs = []
        for o, im, rv, tv in zip(obj, img, rvecs, tvecs):
            proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
            errs.append(float(np.sqrt(np.mean(np.sum((proj - im).reshape(-1, 2) ** 2, axis=1)))))
        return float(rms), K, dist, rvecs, tvecs, np.asarray(errs)

    # OpenCV's closed-form initialisation is fragile with views showing few corners:
    # initialise from the well-covered views; check every view against that camera by
    # its own pose (IPPE + LM) and drop those that do not fit (misdetections, motion
    # blur, pose ambiguity); refine over the rest from that guess.
    rich = [i for i in used if len(detections[i]) >= max(12, board.n_corners // 4)]
    if len(rich) < 3:
        rich = used
    rms, K, dist, rvecs, tvecs, errs = run(rich)
    pnp_err = []
    for i in used:
        try:
            T = board_pose(detections[i], board, K=K, dist=dist)
            proj = project_points(board.corner_points[detections[i].ids] @ T[:3, :3].T + T[:3, 3], K, dist)
            pnp_err.append(float(np.sqrt(np.mean(np.sum((proj - detections[i].corners) ** 2, axis=1)))))
        except (CalibrationError, cv2.error):
            pnp_err.append(np.inf)
    pnp_err = np.asarray(pnp_err)
    bad = ~(pnp_err <= max(1.0, 5.0 * float(np.median(pnp_err[np.isfinite(pnp_err)]))))
    if bad.any() and (~bad).sum() >= max(int(min_views), 3):
        log.warning("camera %s: ignoring %d view(s) that do not fit the others (RMS %s px): views %s",
                    name, int(bad.sum()), ", ".join(f"{e:.2f}" for e in pnp_err[bad]),
                    ", ".join(str(used[k]) for k in np.flatnonzero(bad)))
        used = [v for v, b in zip(used, bad) if not b]
    if used != rich:
        try:
            rms, K, dist, rvecs, tvecs, errs = run(used, K, dist)
        except cv2.error as exc:  # keep the initial calibration from the well-covered views
            log.warning("camera %s: refinement over all views failed (%s); using %d views",
                        name, str(exc).strip().splitlines()[-1], len(rich))
            used = rich
            rms, K, dist, rvecs, tvecs, errs = run(rich)
    d = np.asarray(dist, dtype=np.float64).ravel()
    dist = np.zeros(n_dist)
    dist[: min(n_dist, len(d))] = d[:n_dist]
    poses = {}
    for i, rv, tv in zip(used, rvecs, tvecs):
        R, _ = cv2.Rodrigues(rv)
        poses[i] = _pose_matrix(R, tv)
    log.info("camera %s: intrinsics from %d views, RMS %.3f px", name, len(used), rms)
    return IntrinsicCalibration(np.asarray(K, float), dist, float(rms), poses, (W, H))


# ----------------------------------------------------------------------------------
# Rig calibration
# ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationParams:
    """Parameters of :func:`calibrate_rig` (field names = its keyword names).

    Attributes
    ----------
    n_dist : int
        Distortion coefficients per camera (0, 2, 4, 5 or 8; OpenCV order).
    min_corners : int
        Fewest ChArUco corners for a view to count.
    min_views : int
        Fewest usable views per camera.
    world_board_view : int
        The view whose board pose defines the world frame.
    world_board_orientation : str
        ``"flat"`` (board lying face-up) or ``"upright"`` (standing, printed top up).
    robust_scale : float
        Huber loss scale of the bundle adjustment, pixels.
    max_iter : int
        Most Levenberg-Marquardt iterations of the bundle adjustment.
    """

    n_dist: int = 5
    min_corners: int = 6
    min_views: int = 4
    world_board_view: int = 0
    world_board_orientation: str = "flat"
    robust_scale: float = 1.0
    max_iter: int = 100


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """A calibrated camera, with the SPEC manifest field names.

    Attributes
    ----------
    name : str
    image_size : tuple of int
        ``(width, height)``.
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (n_dist,)
    R : ndarray, shape (3, 3)
        World -> camera rotation.
    t : ndarray, shape (3,)
        World -> camera translation, metres.
    rms : float
        RMS reprojection error after the joint refinement, pixels.
    n_views : int
        Board views used.
    n_points : int
        Corner observations used.
    rms_intrinsic : float
        RMS of the single-camera calibration, pixels.
    background : dict or None
        ``{"point": [..], "normal": [..]}`` or ``{"distance": d}`` (metres).
    """

    name: str
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    rms: float
    n_views: int
    n_points: int = 0
    rms_intrinsic: float = float("nan")
    background: dict | None = None

    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """The calibrated rig.

    Attributes
    ----------
    cameras : tuple of CameraCalibration
    board_poses : dict of int to ndarray (4, 4)
        Board -> world pose of every view seen by some camera.
    world_board_view : int
    world_board_orientation : str
    rms : float
        RMS reprojection error over all observations, pixels.
    """

    cameras: tuple
    board_poses: dict = field(default_factory=dict)
    world_board_view: int = 0
    world_board_orientation: str = "flat"
    rms: float = float("nan")

    def camera(self, name: str) -> CameraCalibration:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]


def world_from_board(board: BoardSpec, orientation: str = "flat") -> np.ndarray:
    """Board -> world pose for the world-frame convention (see module docstring).

    Parameters
    ----------
    board : BoardSpec
    orientation : {"flat", "upright"}

    Returns
    -------
    T : ndarray, shape (4, 4)
        ``x_world = T[:3, :3] @ x_board + T[:3, 3]``; the board centre maps to the origin.
    """
    if orientation == "flat":  # x = x_b, y = -y_b, z = -z_b (out of the printed face)
        F = np.diag([1.0, -1.0, -1.0])
    elif orientation == "upright":  # x = x_b, y = z_b (into the board), z = -y_b (up)
        F = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    else:
        raise CalibrationError(f"world_board_orientation must be 'flat' or 'upright', got {orientation!r}")
    return _pose_matrix(F, -F @ board.centre)


def _spanning_poses(names, intr, min_views_shared: int = 1):
    """Initial camera <- reference poses by chaining shared board views (BFS).

    Returns the reference camera's name and ``{name: T_cam<-ref}``; cameras that share
    no view with the connected set are missing from the dict.
    """
    views = {n: set(intr[n].poses) for n in names}
    # Reference: the camera sharing the most views with the others.
    ref = max(names, key=lambda n: (sum(len(views[n] & views[m]) for m in names if m != n), -names.index(n)))
    known = {ref: np.eye(4)}
    queue = deque([ref])
    while queue:
        k = queue.popleft()
        for c in names:
            if c in known:
                continue
            shared = sorted(views[c] & views[k])
            if len(shared) < min_views_shared:
                continue
            cands = [intr[c].poses[v] @ _inv(intr[k].poses[v]) @ known[k] for v in shared]
            known[c] = _mean_pose(cands)
            queue.append(c)
    return ref, known


class _BundleProblem:
    """Parameter packing and residuals of the joint refinement.

    Parameters (in order): per camera ``fx fy cx cy dist[n_dist]``; per non-reference
    camera ``rvec tvec`` (camera <- reference); per view ``rvec tvec`` (reference <- board).
    """

    def __init__(self, names, ref, views, obs_cam, obs_view, obs_pts, obs_uv, n_dist):
        self.names, self.ref, self.views = list(names), ref, list(views)
        self.n_dist = n_dist
        self.n_intr = 4 + n_dist
        self.n_cam = len(self.names)
        self.free = [i for i, n in enumerate(self.names) if n != ref]
        self.ext_index = {ci: j for j, ci in enumerate(self.free)}
        self.view_index = {v: j for j, v in enumerate(self.views)}
        self.obs_cam, self.obs_pts, self.obs_uv = obs_cam, obs_pts, obs_uv
        self.obs_vidx = np.array([self.view_index[v] for v in obs_view], dtype=np.int64)
        self.o_ext = self.n_cam * self.n_intr
        self.o_view = self.o_ext + 6 * len(self.free)
        self.n_params = self.o_view + 6 * len(self.views)

    def pack(self, K, dist, T_cam_ref, T_ref_board) -> np.ndarray:
        x = np.zeros(self.n_params)
        for i, n in enumerate(self.names):
            o = i * self.n_intr
            x[o:o + 4] = K[n][0, 0], K[n][1, 1], K[n][0, 2], K[n][1, 2]
            x[o + 4:o + self.n_intr] = dist[n][: self.n_dist]
        for ci, j in self.ext_index.items():
            T = T_cam_ref[self.names[ci]]
            o = self.o_ext + 6 * j
            x[o:o + 3] = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            x[o + 3:o + 6] = T[:3, 3]
        for v, j in self.view_index.items():
            T = T_ref_board[v]
            o = self.o_view + 6 * j
            x[o:o + 3] = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            x[o + 3:o + 6] = T[:3, 3]
        return x

    def unpack(self, x):
        K, dist, T_cam_ref, T_ref_board = {}, {}, {}, {}
        for i, n in enumerate(self.names):
            o = i * self.n_intr
            fx, fy, cx, cy = x[o:o + 4]
            K[n] = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            dist[n] = x[o + 4:o + self.n_intr].copy()
            T_cam_ref[n] = np.eye(4)
        for ci, j in self.ext_index.items():
            o = self.o_ext + 6 * j
            R = Rotation.from_rotvec(x[o:o + 3]).as_matrix()
            T_cam_ref[self.names[ci]] = _pose_matrix(R, x[o + 3:o + 6])
        for v, j in self.view_index.items():
            o = self.o_view + 6 * j
            T_ref_board[v] = _pose_matrix(Rotation.from_rotvec(x[o:o + 3]).as_matrix(), x[o + 3:o + 6])
        return K, dist, T_cam_ref, T_ref_board

    def residuals(self, x) -> np.ndarray:
        intr = x[: self.o_ext].reshape(self.n_cam, self.n_intr)
        ext = np.zeros((self.n_cam, 6))
        if self.free:
            ext[self.free] = x[self.o_ext:self.o_view].reshape(-1, 6)
        vw = x[self.o_view:].reshape(-1, 6)
        Rc = Rotation.from_rotvec(ext[:, :3]).as_matrix()
        Rv = Rotation.from_rotvec(vw[:, :3]).as_matrix()
        c, v = self.obs_cam, self.obs_vidx
        X_ref = np.einsum("mij,mj->mi", Rv[v], self.obs_pts) + vw[v, 3:]
        X_cam = np.einsum("mij,mj->mi", Rc[c], X_ref) + ext[c, 3:]
        d = np.zeros((len(c), 8))
        d[:, : self.n_dist] = intr[c, 4:]
        z = X_cam[:, 2]
        uv = _distort_pixels(X_cam[:, 0] / z, X_cam[:, 1] / z, intr[c, 0], intr[c, 1],
                             intr[c, 2], intr[c, 3], d)
        return (uv - self.obs_uv).ravel()

    def jacobian(self, x, dense: bool = True):
        """Central-difference Jacobian of :meth:`residuals`, exploiting its block structure.

        Parameter ``k`` of every camera's intrinsics (or pose, or of every view's board
        pose) touches disjoint residual rows, so one pair of evaluations per parameter
        *kind* gives all of their columns: ``2 * (n_intr + 6 + 6)`` evaluations in all.
        """
        m = len(self.obs_cam)
        obs = np.arange(m)
        free = np.array([self.ext_index.get(int(ci), -1) for ci in self.obs_cam], dtype=np.int64)
        groups = []
        for k in range(self.n_intr):
            groups.append((obs, self.obs_cam * self.n_intr + k))
        if self.free:
            for k in range(6):
                sel = free >= 0
                groups.append((obs[sel], self.o_ext + 6 * free[sel] + k))
        for k in range(6):
            groups.append((obs, self.o_view + 6 * self.obs_vidx + k))
        rows_all, cols_all, vals_all = [], [], []
        for o, cols in groups:
            ucols = np.unique(cols)
            h = 1e-6 * np.maximum(1.0, np.abs(x[ucols]))
            step = np.zeros_like(x)
            step[ucols] = h
            diff = (self.residuals(x + step) - self.residuals(x - step)).reshape(-1, 2)
            hh = 2.0 * step[cols]
            for c in (0, 1):
                rows_all.append(2 * o + c)
                cols_all.append(cols)
                vals_all.append(diff[o, c] / hh)
        J = coo_matrix((np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
                       shape=(2 * m, self.n_params))
        return J.toarray() if dense else J.tocsr()


def _levenberg_marquardt(prob: "_BundleProblem", x0, *, robust_scale: float, max_iter: int):
    """Levenberg-Marquardt on the Huber cost of the 2-D reprojection errors.

    Each observation's error ``e = |(du, dv)|`` costs ``e**2`` below ``robust_scale``
    and ``2 s e - s**2`` above (iteratively reweighted normal equations). The normal
    matrix is formed from the sparse Jacobian (no multi-threaded dense SVD, which
    thrashes on shared machines), damped by Marquardt's diagonal scaling.

    Returns
    -------
    x : ndarray
    info : dict
        ``iterations``, ``status``, ``cost``.
    """
    s = robust_scale

    def cost_and_weights(x):
        e = np.linalg.norm(prob.residuals(x).reshape(-1, 2), axis=1)
        big = e > s
        cost = np.where(big, 2 * s * e - s * s, e * e).sum()
        w = np.where(big, s / np.maximum(e, 1e-300), 1.0)
        return cost, w

    x = np.asarray(x0, dtype=np.float64).copy()
    cost, w = cost_and_weights(x)
    lam = 1e-3
    status = "maximum iterations reached"
    it = 0
    for it in range(1, max_iter + 1):
        r = prob.residuals(x)
        J = prob.jacobian(x, dense=False)
        sw = np.sqrt(np.repeat(w, 2))
        Jw = J.multiply(sw[:, None]).tocsr()
        A = (Jw.T @ Jw).toarray()
        g = Jw.T @ (sw * r)
        diag = np.maximum(np.diag(A).copy(), 1e-12)
        improved = False
        while lam < 1e12:
            try:
                dx = -np.linalg.solve(A + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            new_cost, new_w = cost_and_weights(x + dx)
            if np.isfinite(new_cost) and new_cost < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            status = "converged (no further decrease)"
            break
        rel = (cost - new_cost) / max(cost, 1e-300)
        x = x + dx
        cost, w = new_cost, new_w
        lam = max(lam / 10.0, 1e-12)
        if rel < 1e-10 or np.linalg.norm(dx) < 1e-12 * (np.linalg.norm(x) + 1e-12):
            status = "converged"
            break
    return x, {"iterations": it, "status": status, "cost": float(cost)}


def calibrate_rig(detections, image_sizes, board: BoardSpec, *, n_dist: int = 5,
                  min_corners: int = 6, min_views: int = 4, world_board_view: int = 0,
                  world_board_orientation: str = "flat", robust_scale: float = 1.0,
                  max_iter: int = 100) -> RigCalibration:
    """Calibrate every camera's intrinsics, distortion and pose in one world frame.

    Zhang's method per camera, then shared board views chain the cameras, then a
    bundle adjustment refines all intrinsics, camera poses and board poses jointly by
    minimising the reprojection error of every detected corner (Huber loss).

    Parameters
    ----------
    detections : mapping of str to sequence of (BoardDetection or None)
        Per camera (name), one entry per view; view ``i`` of every camera shows the
        same board pose. Sequences may differ in length (missing views = None).
    image_sizes : mapping of str to tuple of int
        ``(width, height)`` of each camera.
    board : BoardSpec
    n_dist, min_corners, min_views, world_board_view, world_board_orientation,
    robust_scale, max_iter
        See :class:`CalibrationParams`.

    Returns
    -------
    RigCalibration
        Cameras in the order of ``detections``; their rms and n_views from the joint fit.

    Raises
    ------
    CalibrationError
        A camera with too few usable views, a camera sharing no view with the others,
        or a ``world_board_view`` no camera saw; ``camera`` names the camera at fault.
    """
    names = list(detections)
    if not names:
        raise CalibrationError("no cameras to calibrate")
    intr = {n: calibrate_intrinsics(detections[n], image_sizes[n], board, n_dist=n_dist,
                                    min_corners=min_corners, min_views=min_views, name=n)
            for n in names}
    ref, T_cam_ref = _spanning_poses(names, intr)
    for n in names:
        if n not in T_cam_ref:
            raise CalibrationError(
                f"shares no board view with camera {ref} (directly or through other cameras); "
                "film the board where both see it at the same time", camera=n)

    # Initial board poses in the reference frame, averaged over the cameras that saw them.
    per_view: dict[int, list] = {}
    for n in names:
        for v, T in intr[n].poses.items():
            per_view.setdefault(v, []).append(_inv(T_cam_ref[n]) @ T)
    views = sorted(per_view)
    T_ref_board = {v: _mean_pose(Ts) for v, Ts in per_view.items()}
    if world_board_view not in T_ref_board:
        raise CalibrationError(
            f"no camera sees the board (with at least {min_corners} corners) in view "
            f"{world_board_view}, which defines the world frame; choose another "
            "--world-board-view")

    obs_cam, obs_view, obs_pts, obs_uv = [], [], [], []
    for ci, n in enumerate(names):
        for v in intr[n].poses:
            d = detections[n][v]
            obs_cam.append(np.full(len(d), ci))
            obs_view.append(np.full(len(d), v))
            obs_pts.append(board.corner_points[d.ids])
            obs_uv.append(d.corners)
    prob = _BundleProblem(names, ref, views, np.concatenate(obs_cam), np.concatenate(obs_view),
                          np.concatenate(obs_pts), np.concatenate(obs_uv), n_dist)
    x0 = prob.pack({n: intr[n].K for n in names},
                   {n: np.pad(intr[n].dist, (0, max(0, n_dist - len(intr[n].dist)))) for n in names},
                   T_cam_ref, T_ref_board)
    r0 = prob.residuals(x0)
    x, info = _levenberg_marquardt(prob, x0, robust_scale=float(robust_scale), max_iter=int(max_iter))
    r = prob.residuals(x).reshape(-1, 2)
    log.info("bundle adjustment: %d observations, %d parameters, RMS %.3f -> %.3f px in %d "
             "iterations (%s)", len(r), prob.n_params,
             np.sqrt(np.mean(np.sum(r0.reshape(-1, 2) ** 2, axis=1))),
             np.sqrt(np.mean(np.sum(r ** 2, axis=1))), info["iterations"], info["status"])
    K, dist, T_cam_ref, T_ref_board = prob.unpack(x)

    # World frame: T_world<-ref = T_world<-board(v*) . T_board(v*)<-ref
    T_world_ref = world_from_board(board, world_board_orientation) @ _inv(T_ref_board[world_board_view])
    T_ref_world = _inv(T_world_ref)
    cams = []
    err2 = np.sum(r ** 2, axis=1)
    for ci, n in enumerate(names):
        T_cw = T_cam_ref[n] @ T_ref_world
        sel = prob.obs_cam == ci
        d_out = np.zeros(8 if n_dist > 5 else 5)  # SPEC: 4, 5, 8, 12 or 14 values
        d_out[:n_dist] = dist[n]
        cams.append(CameraCalibration(
            name=n, image_size=tuple(int(s) for s in image_sizes[n]), K=K[n], dist=d_out,
            R=T_cw[:3, :3].copy(), t=T_cw[:3, 3].copy(), rms=float(np.sqrt(np.mean(err2[sel]))),
            n_views=len(intr[n].poses), n_points=int(sel.sum()), rms_intrinsic=intr[n].rms))
    board_poses = {v: T_world_ref @ T for v, T in T_ref_board.items()}
    return RigCalibration(tuple(cams), board_poses, int(world_board_view), world_board_orientation,
                          float(np.sqrt(np.mean(err2))))


# ----------------------------------------------------------------------------------
# Background planes
# ----------------------------------------------------------------------------------
def background_plane(detections, board: BoardSpec, *, K, dist, R, t,
                     min_corners: int = 6, name: str | None = None) -> dict:
    """Background plane of one camera from views of a board laid on the background.

    Every view's board pose (PnP with the calibrated intrinsics) places its corners in
    the world; one plane is fitted through all of them (the board may be moved across
    the background between views), normal oriented towards the camera.

    Parameters
    ----------
    detections : sequence of BoardDetection or None
    board : BoardSpec
    K, dist, R, t : ndarray
        The camera's calibration (world -> camera, metres).
    min_corners : int
    name : str, optional

    Returns
    -------
    dict
        ``{"point": (3,), "normal": (3,)}`` in world coordinates: the centroid of the
        corners and the unit normal pointing towards the camera.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).ravel()
    T_world_cam = _inv(_pose_matrix(R, t))
    pts = []
    for d in detections:
        if not _usable(d, board, min_corners):
            continue
        T = T_world_cam @ board_pose(d, board, K=K, dist=dist)
        P = board.corner_points[d.ids]
        pts.append(P @ T[:3, :3].T + T[:3, 3])
    if not pts:
        n_images = len(detections)
        raise CalibrationError(f"the background board was not found (with at least {min_corners} "
                               f"corners) in any of its {n_images} background images", camera=name)
    P = np.concatenate(pts)
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P - c)
    n = Vt[2]
    centre = -R.T @ t
    if (centre - c) @ n < 0:
        n = -n
    return {"point": c, "normal": n / np.linalg.norm(n)}


# ----------------------------------------------------------------------------------
# Synthetic board views (ground truth for tests and demos)
# ----------------------------------------------------------------------------------
class BoardRenderer:
    """Render a ChArUco board as seen by a known camera, for ground-truth tests.

    The printed board (:meth:`BoardSpec.texture`, white margin of one square) is sampled
    by exact inverse mapping: every output pixel is split into ``supersample**2``
    sub-pixels whose undistorted rays (distortion inverted numerically, once per
    camera) meet the board plane through a homography; the texture is read there with
    bicubic interpolation and the sub-pixels are averaged (area sampling, no aliasing).
    Optical blur (Gaussian) and sensor noise are then added and the image is
    quantised to uint8.

    Parameters
    ----------
    board : BoardSpec
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (k,)
    image_size : tuple of int
        ``(width, height)``.
    supersample : int
        Sub-pixels per pixel along each axis.
    pixels_per_square : int
        Texture resolution.
    """

    def __init__(self, board: BoardSpec, K, dist, image_size, *, supersample: int = 3,
                 pixels_per_square: int = 160):
        self.board = board
        self.K = np.asarray(K, dtype=np.float64)
        self.dist = np.asarray(dist, dtype=np.float64).ravel()
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.ss = int(supersample)
        self.pps = int(pixels_per_square)
        self.texture = board.texture(self.pps, 1).astype(np.float32) / 255.0
        W, H = self.image_size
        s = self.ss
        off = (np.arange(s) + 0.5) / s - 0.5
        u = (np.arange(W)[:, None] + off[None, :]).ravel().astype(np.float32)
        v = (np.arange(H)[:, None] + off[None, :]).ravel().astype(np.float32)
        if np.any(self.dist != 0):
            # The undistortion map is smooth: solve it exactly on a coarse grid (step
            # 4 px, one cell of margin) and interpolate bicubically to the sub-pixels.
            step = 4.0
            uc = np.arange(-2 * step, W + 2 * step, step)
            vc = np.arange(-2 * step, H + 2 * step, step)
            ug, vg = np.meshgrid(uc, vc)
            coarse = self._undistort(np.stack([ug.ravel(), vg.ravel()], axis=1))
            coarse = coarse.reshape(len(vc), len(uc), 2).astype(np.float64)
            # (cv2.remap would quantise the positions to 1/32 cell: not accurate enough.)
            xy = np.empty((len(v), len(u), 2), dtype=np.float32)
            for k in range(2):
                spline = RectBivariateSpline(vc, uc, coarse[..., k], kx=3, ky=3)
                xy[..., k] = spline(v.astype(np.float64), u.astype(np.float64))
            self._xy = xy
        else:
            Kinv = np.linalg.inv(self.K)
            uu, vv = np.meshgrid(u.astype(np.float64), v.astype(np.float64))
            xy = np.stack([uu, vv], axis=-1) @ Kinv[:2, :2].T + Kinv[:2, 2]
            self._xy = xy.astype(np.float32)

    def _undistort(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates of distorted pixel positions, shape (M, 2)."""
        Kinv = np.linalg.inv(self.K)
        if not np.any(self.dist != 0):
            return uv @ Kinv[:2, :2].T + Kinv[:2, 2]
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        src = uv.reshape(-1, 1, 2)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            xy = cv2.undistortPointsIter(src, self.K, self.dist, None, None, crit)
        else:  # OpenCV 5 takes the criteria in undistortPoints
            xy = cv2.undistortPoints(src, self.K, self.dist, None, None, None, crit)
        xy = xy.reshape(-1, 2).astype(np.float64)
        # Newton polish on the forward model (closed-form 2x2 solve).
        d = np.zeros(8)
        d[: min(8, len(self.dist))] = self.dist[:8]
        fx, fy, cx, cy, sk = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2], self.K[0, 1]
        h = 1e-7
        for _ in range(2):
            x, y = xy[:, 0], xy[:, 1]
            f0 = _distort_pixels(x, y, fx, fy, cx, cy, d, skew=sk)
            jx = (_distort_pixels(x + h, y, fx, fy, cx, cy, d, skew=sk) - f0) / h
            jy = (_distort_pixels(x, y + h, fx, fy, cx, cy, d, skew=sk) - f0) / h
            r = uv - f0
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            xy[:, 0] += (jy[:, 1] * r[:, 0] - jy[:, 0] * r[:, 1]) / det
            xy[:, 1] += (-jx[:, 1] * r[:, 0] + jx[:, 0] * r[:, 1]) / det
        return xy

    def render(self, R, t, *, blur_sigma: float = 0.7, noise_sigma: float = 2.0,
               black: float = 25.0, white: float = 230.0, surround: float = 110.0,
               rng: np.random.Generator | None = None) -> np.ndarray:
        """Image of the board at pose ``x_cam = R @ x_board + t``.

        Parameters
        ----------
        R : ndarray, shape (3, 3)
        t : ndarray, shape (3,)
            Metres.
        blur_sigma : float
            Gaussian optical blur, pixels.
        noise_sigma : float
            Additive Gaussian noise, grey levels.
        black, white, surround : float
            Grey levels of the printed black, the paper and what lies around the board.
        rng : numpy.random.Generator, optional
            Noise source (required when ``noise_sigma > 0``).

        Returns
        -------
        image : ndarray of uint8, shape (H, W)
        """
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).ravel()
        Hn = np.column_stack([R[:, 0], R[:, 1], t])  # board (X, Y, 1) -> normalised camera
        Hinv = np.linalg.inv(Hn)
        W, H = self.image_size
        s = self.ss
        sq = self.board.square_size
        nx, ny = self.board.squares
        # Only the pixels the paper can cover need sampling: bound its projected outline.
        r0, r1, c0, c1 = 0, H, 0, W
        e = np.linspace(0.0, 1.0, 50)
        X0, X1, Y0, Y1 = -sq, (nx + 1) * sq, -sq, (ny + 1) * sq
        edge = np.concatenate([np.stack([X0 + (X1 - X0) * e, np.full_like(e, Y0)], 1),
                               np.stack([X0 + (X1 - X0) * e, np.full_like(e, Y1)], 1),
                               np.stack([np.full_like(e, X0), Y0 + (Y1 - Y0) * e], 1),
                               np.stack([np.full_like(e, X1), Y0 + (Y1 - Y0) * e], 1)])
        Xc = np.column_stack([edge, np.zeros(len(edge))]) @ R.T + t
        if np.all(Xc[:, 2] <= 0):  # the paper lies wholly behind the camera
            r1 = r0
        elif np.all(Xc[:, 2] > 1e-6):
            uv = project_points(Xc, self.K, self.dist)
            if np.all(np.isfinite(uv)):
                c0 = int(np.clip(np.floor(uv[:, 0].min()) - 4, 0, W))
                c1 = int(np.clip(np.ceil(uv[:, 0].max()) + 5, 0, W))
                r0 = int(np.clip(np.floor(uv[:, 1].min()) - 4, 0, H))
                r1 = int(np.clip(np.ceil(uv[:, 1].max()) + 5, 0, H))
        img = np.full((H, W), np.float32(surround), dtype=np.float32)
        if r1 > r0 and c1 > c0:
            xy = self._xy[r0 * s:r1 * s, c0 * s:c1 * s]
            w = Hinv[2, 0] * xy[..., 0] + Hinv[2, 1] * xy[..., 1] + Hinv[2, 2]  # > 0: in front
            XY = cv2.perspectiveTransform(np.ascontiguousarray(xy).reshape(-1, 1, 2), Hinv)
            XY = XY.reshape(xy.shape)
            X, Y = XY[..., 0], XY[..., 1]
            inside = (w > 0) & (X >= X0) & (X <= X1) & (Y >= Y0) & (Y <= Y1)
            scale = np.float32(self.pps / sq)
            off = np.float32(self.pps - 0.5)
            mx = np.where(inside, X * scale + off, np.float32(-1.0))
            my = np.where(inside, Y * scale + off, np.float32(-1.0))
            tex = cv2.remap(self.texture, mx, my, interpolation=cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REPLICATE)
            np.clip(tex, 0.0, 1.0, out=tex)
            sub = np.where(inside, np.float32(black) + np.float32(white - black) * tex,
                           np.float32(surround))
            img[r0:r1, c0:c1] = sub.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3))
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        if noise_sigma > 0:
            if rng is None:
                raise ValueError("rng is required when noise_sigma > 0")
            img = img + rng.normal(0.0, noise_sigma, img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
