"""Ground-truth tests of the ChArUco rig calibration (pipeline/calibration/).

Synthetic board views are rendered through known cameras (K, distortion, R, t): the
printed board is mapped into each camera by exact inverse mapping (plane homography +
numerically inverted lens distortion), area-supersampled, blurred and noised, then
detected and calibrated. The recovered cameras are compared with the truth.

The scene: three 960x720 cameras on a ring of radius 2.5 m, 40 degrees apart, looking
down at 40 degrees onto the volume centre; a 10x7 board of 6 cm squares. View 0 is the
board lying flat at the world origin (it defines the world frame, so the recovered
cameras are directly comparable with the truth); views 1-6 are shared tilted poses near
the volume; then four close-up views per camera fill that camera's frame.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from schlieren.pipeline.calibration import (
    BoardDetection,
    BoardRenderer,
    BoardSpec,
    CalibrationError,
    background_plane,
    board_pose,
    calibrate_intrinsics,
    calibrate_rig,
    detect_board,
    project_points,
    world_from_board,
)

BOARD = BoardSpec((10, 7), 0.06, 0.045)
SIZE = (960, 720)
# Lateral offsets (metres, camera x/y) of each camera's close-up views at 1.35 m.
CLOSE_UPS = [(-0.18, -0.12), (0.18, 0.12), (0.15, -0.12), (-0.15, 0.12), (0.0, 0.0), (0.2, 0.0)]


# ----------------------------------------------------------------------------------
# scene
# ----------------------------------------------------------------------------------
def look_at(C, target, up=(0.0, 0.0, 1.0)):
    """World -> camera (R, t) of a camera at C looking at target, image x horizontal."""
    z = np.asarray(target, float) - C
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ C


def pose(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def facing(p, target, rng, tilt):
    """Board -> world pose: board centre at p, printed face towards target, random tilt."""
    n = target - p
    n /= np.linalg.norm(n)
    zb = -n  # the board's z points into the board, away from its face
    xb = -np.cross([0.0, 0.0, 1.0], zb)
    xb /= np.linalg.norm(xb)
    yb = np.cross(zb, xb)
    Rwb = Rotation.from_rotvec(rng.uniform(-tilt, tilt, 3) * np.array([1, 1, 0.3])).as_matrix()
    Rwb = Rwb @ np.stack([xb, yb, zb], axis=1)
    return pose(Rwb, p - Rwb @ BOARD.centre)


def make_cameras(elevation_deg=40.0):
    cams = {}
    for i, az in enumerate([-40, 0, 40]):
        a, el = np.radians(az - 90), np.radians(elevation_deg)
        C = 2.5 * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
        R, t = look_at(C, [0.0, 0.0, 0.1])
        f = 1500.0 + 80 * i
        K = np.array([[f, 0, 475.0 + 10 * i], [0, f * 1.001, 363.0 - 8 * i], [0, 0, 1]])
        dist = np.array([-0.10 + 0.03 * i, 0.05, 0.0008 * (i - 1), -0.0005, 0.0])
        cams[f"cam{i}"] = dict(K=K, dist=dist, R=R, t=t, C=C)
    return cams


def make_poses(cams, rng):
    """Board -> world poses; view 0 = flat at the world origin."""
    poses = [world_from_board(BOARD, "flat")]
    mean_c = np.mean([c["C"] for c in cams.values()], axis=0)
    for _ in range(6):
        p = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.05, 0.4)])
        poses.append(facing(p, mean_c, rng, 0.6))
    for c in cams.values():  # close-ups filling each camera's frame, strongly tilted
        for ox, oy in CLOSE_UPS:
            R = c["R"]
            p = c["C"] + 1.35 * R[2] + ox * R[0] + oy * R[1]
            poses.append(facing(p, c["C"], rng, 0.7))
    return poses


def cam_from_board(c, T_wb):
    return pose(c["R"], c["t"]) @ T_wb


def rotation_error_deg(Ra, Rb):
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec())))


@pytest.fixture(scope="module")
def rendered():
    """Render and detect every view in every camera (about 60 images, ~10 s)."""
    rng = np.random.default_rng(7)
    cams = make_cameras()
    poses = make_poses(cams, rng)
    dets, images = {}, {}
    for name, c in cams.items():
        r = BoardRenderer(BOARD, c["K"], c["dist"], SIZE, supersample=2)
        dets[name] = []
        for v, T in enumerate(poses):
            Tcb = cam_from_board(c, T)
            img = r.render(Tcb[:3, :3], Tcb[:3, 3], blur_sigma=0.8, noise_sigma=2.0, rng=rng)
            if v < 2:
                images[(name, v)] = img
            dets[name].append(detect_board(img, BOARD))
    return cams, poses, dets, images


# ----------------------------------------------------------------------------------
# the board and the projection model
# ----------------------------------------------------------------------------------
def test_corner_points_match_opencv_board():
    ref = np.asarray(BOARD.cv_board().getChessboardCorners(), dtype=np.float64)
    np.testing.assert_allclose(BOARD.corner_points, ref, atol=1e-6)
    np.testing.assert_allclose(BOARD.centre, [0.3, 0.21, 0.0])


@pytest.mark.parametrize("kwargs, match", [
    (dict(squares=(10, 7), square_size=0.03, marker_size=0.03), "smaller than the square"),
    (dict(squares=(10, 7), square_size=0.03, marker_size=0.02, dictionary="DICT_NOPE"), "unknown ArUco"),
    (dict(squares=(20, 20), square_size=0.03, marker_size=0.02, dictionary="DICT_4X4_50"),
     "needs 200 markers"),
])
def test_board_spec_rejects_bad_boards(kwargs, match):
    with pytest.raises(CalibrationError, match=match):
        BoardSpec(**kwargs)


@pytest.mark.parametrize("dist", [
    np.array([-0.2, 0.1, 0.001, -0.002, 0.03]),
    np.array([-0.2, 0.1, 0.001, -0.002, 0.03, 0.01, -0.02, 0.005]),
    np.zeros(5),
])
def test_project_points_matches_opencv(dist):
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), rng.uniform(1.0, 3.0, 50)])
    K = np.array([[1200.0, 0.0, 470.0], [0.0, 1210.0, 350.0], [0.0, 0.0, 1.0]])
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(project_points(X, K, dist), ref.reshape(-1, 2), atol=1e-9)


def test_rendered_corners_are_detected_where_projected(rendered):
    """The renderer and detector agree with the projection model (unbiased, ~0.1 px)."""
    cams, poses, dets, _ = rendered
    errs = []
    for name in ("cam1", "cam2"):
        c = cams[name]
        for v in range(1, 7):
            d = dets[name][v]
            assert len(d) >= 45
            T = cam_from_board(c, poses[v])
            X = BOARD.corner_points[d.ids] @ T[:3, :3].T + T[:3, 3]
            errs.append(d.corners - project_points(X, c["K"], c["dist"]))
    e = np.concatenate(errs)
    assert np.sqrt(np.mean(np.sum(e ** 2, axis=1))) < 0.15
    assert np.all(np.abs(e.mean(axis=0)) < 0.03)


# ----------------------------------------------------------------------------------
# the rig calibration against ground truth
# ----------------------------------------------------------------------------------
def test_rig_calibration_recovers_known_cameras(rendered):
    """The issue's targets: focal lengths within 0.5 %, camera centres within 2 mm at
    2.5 m, rotations within 0.1 degree; plus the whole projection of the volume."""
    cams, poses, dets, _ = rendered
    rig = calibrate_rig(dets, {n: SIZE for n in cams}, BOARD, world_board_view=0,
                        world_board_orientation="flat")
    assert rig.names == list(cams)
    vol = np.stack(np.meshgrid(*[np.linspace(-0.15, 0.15, 5)] * 2, np.linspace(0.0, 0.3, 5)),
                   axis=-1).reshape(-1, 3)
    for c in rig.cameras:
        g = cams[c.name]
        assert abs(c.K[0, 0] / g["K"][0, 0] - 1) < 0.005
        assert abs(c.K[1, 1] / g["K"][1, 1] - 1) < 0.005
        assert np.linalg.norm(c.center - g["C"]) < 0.002
        assert rotation_error_deg(c.R, g["R"]) < 0.1
        assert 0 < c.rms < 0.3
        assert c.n_views >= 10
        assert len(c.dist) == 5
        # Every point of the reconstruction volume projects where the true camera puts it.
        uv = project_points(vol @ c.R.T + c.t, c.K, c.dist)
        uv_true = project_points(vol @ g["R"].T + g["t"], g["K"], g["dist"])
        assert np.max(np.linalg.norm(uv - uv_true, axis=1)) < 0.5
    # The board poses too: view 0 is the world frame itself (z up).
    np.testing.assert_allclose(rig.board_poses[0], world_from_board(BOARD, "flat"), atol=1e-12)
    for v in (1, 2, 3):
        assert np.linalg.norm(rig.board_poses[v][:3, 3] - poses[v][:3, 3]) < 0.002


def synthetic_detections(cams, poses, rng, noise=0.05):
    """Detections from exact projections plus Gaussian noise (no images)."""
    dets = {}
    for name, c in cams.items():
        dets[name] = []
        for T in poses:
            Tcb = cam_from_board(c, T)
            X = BOARD.corner_points @ Tcb[:3, :3].T + Tcb[:3, 3]
            uv = project_points(X, c["K"], c["dist"])
            facing_cam = (Tcb[:3, :3] @ [0.0, 0.0, -1.0]) @ (-Tcb[:3, 3]) > 0
            ok = (X[:, 2] > 0) & np.all((uv >= 0) & (uv <= np.array(SIZE) - 1), axis=1)
            if not facing_cam or ok.sum() < 6:
                dets[name].append(None)
                continue
            ids = np.flatnonzero(ok)
            dets[name].append(BoardDetection(ids, uv[ids] + rng.normal(0, noise, (len(ids), 2)), 10))
    return dets


def test_bundle_adjustment_on_exact_projections_and_upright_world():
    """Without rendering: 0.05 px noise gives near-exact cameras; the world frame can be
    set by a board standing upright (z along its printed top edge)."""
    rng = np.random.default_rng(3)
    cams = make_cameras(elevation_deg=15.0)
    poses = make_poses(cams, rng)
    # View 1: the board standing upright at the origin, face towards the cameras (-y).
    upright = world_from_board(BOARD, "upright")
    poses[1] = upright
    dets = synthetic_detections(cams, poses, rng)
    rig = calibrate_rig(dets, {n: SIZE for n in cams}, BOARD, world_board_view=1,
                        world_board_orientation="upright")
    for c in rig.cameras:
        g = cams[c.name]
        assert abs(c.K[0, 0] / g["K"][0, 0] - 1) < 0.001
        assert np.linalg.norm(c.center - g["C"]) < 0.002
        assert rotation_error_deg(c.R, g["R"]) < 0.05
        assert c.rms < 0.1
        # The camera model as a whole (k2/k3 and cx/R trade off): world points in and
        # around the volume land on the same pixels.
        X = np.stack(np.meshgrid(*[np.linspace(-0.4, 0.4, 7)] * 3), -1).reshape(-1, 3)
        diff = (project_points(X @ c.R.T + c.t, c.K, c.dist)
                - project_points(X @ g["R"].T + g["t"], g["K"], g["dist"]))
        assert np.max(np.linalg.norm(diff, axis=1)) < 0.1


def test_huber_loss_keeps_misdetected_corners_from_biasing_the_rig():
    """3 % of the corners misdetected by 3-8 px: with the Huber loss (scale 1 px) the cameras
    stay near the truth; without it (scale 1e6 px: least squares) they are pulled away."""
    rng = np.random.default_rng(3)
    cams = make_cameras(elevation_deg=15.0)
    poses = make_poses(cams, rng)
    dets = synthetic_detections(cams, poses, rng)
    for name in dets:
        for v, d in enumerate(dets[name]):
            if d is None:
                continue
            uv = d.corners.copy()
            bad = rng.random(len(uv)) < 0.03
            ang, r = rng.uniform(0, 2 * np.pi, bad.sum()), rng.uniform(3.0, 8.0, bad.sum())
            uv[bad] += np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
            dets[name][v] = BoardDetection(d.ids, uv, d.n_markers)
    X = np.stack(np.meshgrid(*[np.linspace(-0.4, 0.4, 7)] * 3), -1).reshape(-1, 3)
    worst = {}
    for scale in (1.0, 1e6):
        rig = calibrate_rig(dets, {n: SIZE for n in cams}, BOARD, robust_scale=scale)
        errs = []
        for c in rig.cameras:
            g = cams[c.name]
            if scale == 1.0:
                assert abs(c.K[0, 0] / g["K"][0, 0] - 1) < 0.001
                assert np.linalg.norm(c.center - g["C"]) < 0.002
                assert rotation_error_deg(c.R, g["R"]) < 0.15
            diff = (project_points(X @ c.R.T + c.t, c.K, c.dist)
                    - project_points(X @ g["R"].T + g["t"], g["K"], g["dist"]))
            errs.append(np.max(np.linalg.norm(diff, axis=1)))
        worst[scale] = max(errs)
    assert worst[1.0] < 0.5
    assert worst[1.0] < 0.5 * worst[1e6]


def test_bundle_loss_is_scipys_huber_with_gauss_newton_weights():
    """The cost and its derivative are scipy's "huber"; rho'' is 0 (IRLS weights sqrt(rho'))."""
    from scipy.optimize import least_squares

    from schlieren.pipeline.calibration.bundle import _huber

    z = np.array([0.0, 0.25, 1.0, 1.0 + 1e-9, 4.0, 100.0])
    rho = _huber(z)
    np.testing.assert_allclose(rho[0], np.where(z <= 1, z, 2 * np.sqrt(z) - 1))
    np.testing.assert_allclose(rho[1], np.where(z <= 1, 1.0, 1 / np.sqrt(np.maximum(z, 1))))
    assert np.all(rho[2] == 0)
    # the same cost as scipy's own loss on a residual vector with inliers and outliers
    f = np.array([0.3, -0.8, 2.5, -7.0])
    ours = least_squares(lambda x: f + 0 * x, np.zeros(1), loss=_huber, f_scale=1.5, max_nfev=1).cost
    scipys = least_squares(lambda x: f + 0 * x, np.zeros(1), loss="huber", f_scale=1.5, max_nfev=1).cost
    assert ours == pytest.approx(scipys, rel=1e-15)


def test_world_from_board_conventions():
    for orientation, up_in_board in (("flat", [0.0, 0.0, -1.0]), ("upright", [0.0, -1.0, 0.0])):
        T = world_from_board(BOARD, orientation)
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R @ up_in_board, [0.0, 0.0, 1.0])  # z up
        np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [1.0, 0.0, 0.0])  # x along the columns
        np.testing.assert_allclose(R @ BOARD.centre + T[:3, 3], 0.0, atol=1e-15)
    with pytest.raises(CalibrationError, match="flat"):
        world_from_board(BOARD, "sideways")


# ----------------------------------------------------------------------------------
# refusals name the camera
# ----------------------------------------------------------------------------------
def test_camera_with_too_few_views_is_refused_by_name(rendered):
    cams, _, dets, _ = rendered
    bad = dict(dets)
    bad["cam1"] = [d if v < 2 else None for v, d in enumerate(dets["cam1"])]
    with pytest.raises(CalibrationError, match="only 2 of its 25 images") as info:
        calibrate_rig(bad, {n: SIZE for n in cams}, BOARD)
    assert info.value.camera == "cam1"


def test_blank_or_wrong_board_images_give_a_clear_error(rendered):
    cams, _, _, images = rendered
    rng = np.random.default_rng(1)
    blank = [detect_board(rng.integers(90, 130, (720, 960), dtype=np.uint8), BOARD) for _ in range(5)]
    with pytest.raises(CalibrationError, match="no ArUco marker of DICT_5X5_100") as info:
        calibrate_intrinsics(blank, SIZE, BOARD, name="cam7")
    assert info.value.camera == "cam7"
    # The right images analysed with the wrong dictionary find no marker either.
    wrong = BoardSpec((10, 7), 0.06, 0.045, dictionary="DICT_4X4_50")
    dets = [detect_board(images[("cam1", v)], wrong) for v in (0, 1)]
    assert all(d.n_markers == 0 for d in dets)
    with pytest.raises(CalibrationError, match="check --dictionary"):
        calibrate_intrinsics(dets, SIZE, wrong, name="cam1")
    # ... and with the wrong number of squares, markers are found but no corner.
    wrong_sq = BoardSpec((9, 7), 0.06, 0.045)
    dets = [detect_board(images[("cam1", v)], wrong_sq) for v in (0, 1)]
    with pytest.raises(CalibrationError, match="check --squares 9x7"):
        calibrate_intrinsics(dets, SIZE, wrong_sq, name="cam1")


def test_camera_sharing_no_view_is_refused_by_name():
    rng = np.random.default_rng(5)
    cams = make_cameras()
    poses = make_poses(cams, rng)
    dets = synthetic_detections(cams, poses, rng)
    # cam2 keeps only its own close-ups (views 15..18), which no other camera sees.
    dets["cam2"] = [d if v >= 15 else None for v, d in enumerate(dets["cam2"])]
    for other in ("cam0", "cam1"):
        dets[other] = [d if v < 15 else None for v, d in enumerate(dets[other])]
    with pytest.raises(CalibrationError, match="shares no board view") as info:
        calibrate_rig(dets, {n: SIZE for n in cams}, BOARD)
    assert info.value.camera == "cam2"


def test_world_view_nobody_saw_is_refused():
    rng = np.random.default_rng(5)
    cams = make_cameras()
    poses = make_poses(cams, rng)
    dets = synthetic_detections(cams, poses, rng)
    for n in dets:
        dets[n][3] = None
    with pytest.raises(CalibrationError, match="view 3"):
        calibrate_rig(dets, {n: SIZE for n in cams}, BOARD, world_board_view=3)


# ----------------------------------------------------------------------------------
# background planes
# ----------------------------------------------------------------------------------
def test_background_plane_from_a_board_on_the_background():
    """A board on a wall 3.4 m from the camera, seen in two places: the fitted plane is the
    wall (points within 3 mm, normal within 0.3 degree, facing the camera)."""
    rng = np.random.default_rng(11)
    c = make_cameras(elevation_deg=10.0)["cam1"]  # at azimuth -90: looks along +y
    wall_y = 1.0  # the wall is the plane y = 1.0, normal -y towards the camera
    r = BoardRenderer(BOARD, c["K"], c["dist"], SIZE, supersample=2)
    dets, truth = [], []
    for x0, z0 in ((-0.5, 0.2), (0.35, -0.3)):
        # board face towards -y: board x = world x, board y = world -z, board z = +y
        Rwb = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
        T = pose(Rwb, np.array([x0, wall_y, z0]) - Rwb @ BOARD.centre)
        Tcb = cam_from_board(c, T)
        truth.append(Tcb)
        img = r.render(Tcb[:3, :3], Tcb[:3, 3], blur_sigma=0.8, noise_sigma=2.0, rng=rng)
        dets.append(detect_board(img, BOARD))
    assert all(len(d) >= 50 for d in dets)
    plane = background_plane(dets, BOARD, K=c["K"], dist=c["dist"], R=c["R"], t=c["t"])
    n = plane["normal"]
    assert np.degrees(np.arccos(np.clip(n @ [0.0, -1.0, 0.0], -1, 1))) < 0.3
    assert abs(plane["point"][1] - wall_y) < 0.003
    # One view alone: the board pose in the camera (PnP) is the true one.
    T = board_pose(dets[0], BOARD, K=c["K"], dist=c["dist"])
    assert np.linalg.norm(T[:3, 3] - truth[0][:3, 3]) < 0.01
    assert rotation_error_deg(T[:3, :3], truth[0][:3, :3]) < 0.5
    with pytest.raises(CalibrationError, match="background board was not found") as info:
        background_plane([None, None], BOARD, K=c["K"], dist=c["dist"], R=c["R"], t=c["t"],
                         name="cam1")
    assert info.value.camera == "cam1"
