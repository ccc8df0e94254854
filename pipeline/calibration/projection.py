"""The camera model of the calibration: OpenCV's pinhole projection with lens distortion
(vectorised for the bundle adjustment), 4x4 rigid poses, and one board's pose by PnP.

Poses are 4x4 matrices ``T`` with ``x_to = T[:3, :3] @ x_from + T[:3, 3]`` (metres).
"""

from __future__ import annotations

import cv2
import numpy as np

from schlieren.pipeline.calibration.board import BoardDetection, BoardSpec, CalibrationError

__all__ = ["project_points", "board_pose"]


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
