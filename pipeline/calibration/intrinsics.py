"""One camera's intrinsics by Zhang's planar calibration (``cv2.calibrateCamera``) from its
ChArUco detections: ``K``, distortion and one board pose per usable view.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from schlieren.pipeline.calibration.board import BoardSpec, CalibrationError, _usable
from schlieren.pipeline.calibration.projection import _pose_matrix, board_pose, project_points

__all__ = ["IntrinsicCalibration", "calibrate_intrinsics"]

log = logging.getLogger(__name__)

_N_DIST_FLAGS = {
    0: cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    2: cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    4: cv2.CALIB_FIX_K3,
    5: 0,
    8: cv2.CALIB_RATIONAL_MODEL,
}


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
    run = functools.partial(_zhang, detections, board, (W, H), _N_DIST_FLAGS[n_dist])
    # OpenCV's closed-form initialisation is fragile with views showing few corners:
    # initialise from the well-covered views; check every view against that camera by
    # its own pose (IPPE + LM) and drop those that do not fit (misdetections, motion
    # blur, pose ambiguity); refine over the rest from that guess.
    rich = [i for i in used if len(detections[i]) >= max(12, board.n_corners // 4)]
    if len(rich) < 3:
        rich = used
    rms, K, dist, rvecs, tvecs, errs = run(rich)
    used = _drop_misfits(detections, board, used, K, dist, min_views=min_views, name=name)
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


_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


def _zhang(detections, board: BoardSpec, image_size, flags: int, views, K=None, dist=None):
    """``cv2.calibrateCamera`` over ``views`` (from ``K``, ``dist`` when given): RMS, K, dist,
    the views' rvecs and tvecs, and each view's own RMS reprojection error (pixels)."""
    obj = [board.corner_points[detections[i].ids].astype(np.float32) for i in views]
    img = [detections[i].corners.astype(np.float32).reshape(-1, 1, 2) for i in views]
    f = flags if K is None else flags | cv2.CALIB_USE_INTRINSIC_GUESS
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, image_size, K, dist, flags=f, criteria=_CRITERIA)
    errs = []
    for o, im, rv, tv in zip(obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
        errs.append(float(np.sqrt(np.mean(np.sum((proj - im).reshape(-1, 2) ** 2, axis=1)))))
    return float(rms), K, dist, rvecs, tvecs, np.asarray(errs)


def _drop_misfits(detections, board: BoardSpec, used: list, K, dist, *, min_views: int, name) -> list:
    """The views of ``used`` whose own pose (PnP with ``K``, ``dist``) fits them: RMS within
    max(1 px, 5x the median); all of them when fewer than ``min_views`` would remain."""
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
    return used
