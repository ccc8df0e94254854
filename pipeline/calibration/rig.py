"""The rig calibration: every camera's intrinsics, distortion and pose in one world frame.

Zhang's method per camera (:mod:`.intrinsics`); shared board views chain the cameras into
camera-to-camera poses; the bundle adjustment (:mod:`.bundle`) refines everything jointly;
one board view defines the world frame (:func:`world_from_board`, conventions in
:mod:`schlieren.pipeline.calibration`).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline.calibration.board import BoardSpec, CalibrationError
from schlieren.pipeline.calibration.bundle import _bundle_adjust, _BundleProblem
from schlieren.pipeline.calibration.intrinsics import calibrate_intrinsics
from schlieren.pipeline.calibration.projection import _inv, _mean_pose, _pose_matrix

__all__ = ["CalibrationParams", "CameraCalibration", "RigCalibration", "world_from_board", "calibrate_rig"]

log = logging.getLogger(__name__)


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
        Huber loss scale of the bundle adjustment (``f_scale``), pixels per residual
        component.
    max_iter : int
        Most residual evaluations of the bundle adjustment (``max_nfev`` of
        :func:`scipy.optimize.least_squares`: one per trust-region iteration).
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
    ref, T_cam_ref = _chain_cameras(names, intr)
    T_ref_board = _initial_board_poses(names, intr, T_cam_ref)
    if world_board_view not in T_ref_board:
        raise CalibrationError(
            f"no camera sees the board (with at least {min_corners} corners) in view "
            f"{world_board_view}, which defines the world frame; choose another "
            "--world-board-view")
    prob = _bundle_problem(names, ref, sorted(T_ref_board), intr, detections, board, n_dist)
    x0 = prob.pack({n: intr[n].K for n in names},
                   {n: np.pad(intr[n].dist, (0, max(0, n_dist - len(intr[n].dist)))) for n in names},
                   T_cam_ref, T_ref_board)
    r0 = prob.residuals(x0)
    x, info = _bundle_adjust(prob, x0, robust_scale=float(robust_scale), max_iter=int(max_iter))
    r = prob.residuals(x).reshape(-1, 2)
    log.info("bundle adjustment: %d observations, %d parameters, RMS %.3f -> %.3f px in %d "
             "iterations (%s)", len(r), prob.n_params,
             np.sqrt(np.mean(np.sum(r0.reshape(-1, 2) ** 2, axis=1))),
             np.sqrt(np.mean(np.sum(r ** 2, axis=1))), info["iterations"], info["status"])
    return _rig_in_world(prob, x, r, intr, image_sizes, board, n_dist=n_dist, world_board_view=world_board_view,
                         world_board_orientation=world_board_orientation)


def _chain_cameras(names, intr) -> tuple[str, dict]:
    """The reference camera and every camera's initial pose relative to it (shared views)."""
    ref, T_cam_ref = _spanning_poses(names, intr)
    for n in names:
        if n not in T_cam_ref:
            raise CalibrationError(
                f"shares no board view with camera {ref} (directly or through other cameras); "
                "film the board where both see it at the same time", camera=n)
    return ref, T_cam_ref


def _initial_board_poses(names, intr, T_cam_ref) -> dict:
    """Initial board poses in the reference frame, averaged over the cameras that saw them."""
    per_view: dict[int, list] = {}
    for n in names:
        for v, T in intr[n].poses.items():
            per_view.setdefault(v, []).append(_inv(T_cam_ref[n]) @ T)
    return {v: _mean_pose(Ts) for v, Ts in per_view.items()}


def _bundle_problem(names, ref, views, intr, detections, board: BoardSpec, n_dist: int) -> _BundleProblem:
    """Every corner each camera detected in the views of its intrinsic calibration."""
    obs_cam, obs_view, obs_pts, obs_uv = [], [], [], []
    for ci, n in enumerate(names):
        for v in intr[n].poses:
            d = detections[n][v]
            obs_cam.append(np.full(len(d), ci))
            obs_view.append(np.full(len(d), v))
            obs_pts.append(board.corner_points[d.ids])
            obs_uv.append(d.corners)
    return _BundleProblem(names, ref, views, np.concatenate(obs_cam), np.concatenate(obs_view),
                          np.concatenate(obs_pts), np.concatenate(obs_uv), n_dist)


def _rig_in_world(prob: _BundleProblem, x, r, intr, image_sizes, board: BoardSpec, *, n_dist: int,
                  world_board_view: int, world_board_orientation: str) -> RigCalibration:
    """The refined cameras and board poses in the world frame of ``world_board_view``, with
    the reprojection errors ``r`` (shape (M, 2)) per camera and overall."""
    names = prob.names
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
