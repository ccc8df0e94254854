"""Camera and grid geometry against closed-form answers."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid, rodrigues


def _camera(dist=(0.0, 0.0, 0.0, 0.0, 0.0), yaw=0.3):
    # camera on a ring at 2.5 m looking at the origin, z up
    C = np.array([2.5 * np.sin(yaw), -2.5 * np.cos(yaw), 0.15])
    z = -C / np.linalg.norm(C)
    x = np.cross(z, [0, 0, 1.0]); x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    t = -R @ C
    bp, bn = Camera.background_from_distance(R, t, 5.0)
    return Camera("cam", [[1200, 0, 320], [0, 1200, 240], [0, 0, 1]], dist, R, t, (640, 480), bp, bn)


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.2, 0.05, 1e-3, -2e-3, 0.01),
                                  (0.1, -0.02, 0, 0, 0, 0.01, 0.0, 0.002)])
def test_rays_pass_through_the_points_they_image(dist):
    cam = _camera(dist)
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.3], size=(50, 3))
    uv = cam.project(X)
    o, d = cam.rays(uv)
    v = X - o
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.abs(np.cross(d, v)).max() < 1e-9
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)


def test_centre_axis_and_background_plane():
    cam = _camera()
    assert np.allclose(cam.center, [2.5 * np.sin(0.3), -2.5 * np.cos(0.3), 0.15])
    # the optical axis points at the origin
    assert np.allclose(np.cross(cam.optical_axis, -cam.center / np.linalg.norm(cam.center)), 0, atol=1e-12)
    assert cam.background_distance() == pytest.approx(5.0)
    o, d = cam.rays(np.array([[320.0, 240.0]]))
    B = cam.intersect_background(o, d)
    assert np.linalg.norm(B[0] - cam.center) == pytest.approx(5.0)
    # a ray pointing away from the plane never meets it
    assert np.isnan(cam.intersect_background(o, -d)).all()


def test_points_behind_the_camera_project_to_nan():
    cam = _camera()
    behind = cam.center - 1.0 * cam.optical_axis
    assert np.isnan(cam.project(behind[None])).all()


def test_rodrigues_roundtrip():
    R = rodrigues([0.1, -0.2, 0.3])
    assert np.allclose(R @ R.T, np.eye(3))
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_flow_grid_cells_average_image_pixels():
    fg = FlowGrid((1440, 1080), 3)
    assert fg.shape == (360, 480)
    c = fg.pixel_centres()
    assert c.shape == (360, 480, 2)
    assert tuple(c[0, 0]) == (1.0, 1.0) and tuple(c[-1, -1]) == (1438.0, 1078.0)
    fg4 = FlowGrid((10, 7), 4)
    assert fg4.shape == (1, 2)
    assert tuple(fg4.pixel_centres()[0, 1]) == (5.5, 1.5)


def test_grid_shape_origin_and_index():
    g = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.30), 0.0025)
    assert g.shape == (120, 60, 60)
    assert np.allclose(g.origin, [-0.07375, -0.07375, 0.00125])
    X = g.centres()
    assert X.shape == (120, 60, 60, 3)
    assert np.allclose(g.world_to_index(X[5, 7, 9]), [9, 7, 5])
    assert g.to_attrs()["voxel_size"] == [0.0025] * 3


def test_auto_voxel_from_the_pixel_footprint_and_its_budgets():
    """Focal length 1000 px at 2 m: 2 mm per pixel at the box centre; 2 px per voxel -> 4 mm."""
    from schlieren.pipeline.geometry import auto_voxel_size, pixel_footprint

    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    bp, bn = Camera.background_from_distance(np.eye(3), np.array([0.0, 0.0, 2.0]), 5.0)
    cams = [Camera(f"c{i}", K, np.zeros(5), np.eye(3), np.array([0.0, 0.0, 2.0]), (640, 480), bp, bn)
            for i in range(3)]
    assert pixel_footprint(cams[0], (0.0, 0.0, 0.0)) == pytest.approx(0.002)
    v, info = auto_voxel_size(cams, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), px_per_voxel=2.0)
    assert v == pytest.approx(0.004) and info["limited_by"] == "footprint"
    assert info["px_per_voxel"] == pytest.approx(2.0)
    # a voxel budget of 1000 voxels for a (0.2 m)^3 box: 20 mm
    v, info = auto_voxel_size(cams, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), max_voxels=1000)
    assert v == pytest.approx(0.02) and info["limited_by"] == "voxels"
    # the matrix budget: 3 cameras x 213 x 160 rays x 0.2 m chord / 1e6 crossings = 20.4 mm
    v, info = auto_voxel_size(cams, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), max_crossings=1e6)
    assert info["limited_by"] == "matrix" and v == pytest.approx(0.02045, abs=5e-5)
