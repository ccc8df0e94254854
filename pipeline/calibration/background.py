"""Each camera's background plane from views of a ChArUco board laid on the background."""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.calibration.board import BoardSpec, CalibrationError, _usable
from schlieren.pipeline.calibration.projection import _inv, _pose_matrix, board_pose

__all__ = ["background_plane"]


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
