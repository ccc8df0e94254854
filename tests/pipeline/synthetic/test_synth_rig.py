"""Virtual camera rigs: geometry against the construction."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.synthetic.rig import make_rig, ring_angles

GRID = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.0025)


@pytest.mark.parametrize("ring,n,span", [("half", 16, np.pi), ("full", 15, 2 * np.pi)])
def test_ring_spacing_and_pointing(ring, n, span):
    cams = make_rig(n, ring=ring, grid=GRID, radius=2.5, image_size=(320, 240))
    c = GRID.center
    az = np.array([np.arctan2(*(cam.center - c)[[1, 0]]) for cam in cams]) % (2 * np.pi)
    np.testing.assert_allclose(np.diff(az), span / n, atol=1e-9)
    np.testing.assert_allclose(az, ring_angles(n, ring), atol=1e-9)
    for cam in cams:
        # at radius 2.5 m, at the centre's height, looking at the centre (principal point)
        assert np.hypot(*(cam.center - c)[:2]) == pytest.approx(2.5)
        np.testing.assert_allclose(cam.project(c), cam.K[:2, 2], atol=1e-9)
        np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
        assert cam.R[1] @ np.array([0, 0, 1.0]) < 0  # image rows go down = world z goes up
        # the whole box is inside the frame, and fills it in at least one direction
        uv = cam.project(GRID.corners())
        assert np.all(uv >= -0.5) and np.all(uv[:, 0] <= 319.5) and np.all(uv[:, 1] <= 239.5)
        # background plane: perpendicular to the axis, 2.5 m behind the centre, facing the camera
        assert cam.background_distance() == pytest.approx(5.0)
        np.testing.assert_allclose(cam.bg_normal, -cam.optical_axis, atol=1e-12)
        assert (cam.bg_point - c) @ cam.optical_axis == pytest.approx(2.5)
    if ring == "full":  # odd count: no camera faces another
        dirs = np.array([cam.optical_axis for cam in cams])
        assert (dirs @ dirs.T).min() > -0.999
    fill = max(max(np.ptp(cam.project(GRID.corners())[:, 0]) / 320, np.ptp(cam.project(GRID.corners())[:, 1]) / 240)
               for cam in cams)
    assert fill > 0.85


def test_height_jitter_and_distortion():
    cams = make_rig(8, grid=GRID, image_size=(320, 240), height_jitter=0.05, seed=3,
                    distortion=[-0.05, 0.01, 0, 0, 0])
    z = np.array([cam.center[2] for cam in cams])
    assert z.std() > 0.01
    for cam in cams:
        assert cam.has_distortion
        np.testing.assert_allclose(cam.project(GRID.center), cam.K[:2, 2], atol=1e-6)
