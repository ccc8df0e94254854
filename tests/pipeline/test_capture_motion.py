"""The background-motion model, its robust fit to a flow, and the static region (issue 33)."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.capture import (box_footprint, fit_flow_motion, motion_displacement, motion_extent,
                                        motion_field, motion_summary, static_cells, static_region)
from schlieren.pipeline.geometry import Camera, Grid

SIZE = (320, 240)  # width, height


def test_translation_and_rotation_about_the_centre():
    cx, cy = (SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2
    dx, dy = motion_displacement([0.3, -0.2, 0, 0, 0, 0, 0, 0], [0.0, 100.0], [5.0, 200.0], SIZE)
    np.testing.assert_allclose(dx, 0.3)
    np.testing.assert_allclose(dy, -0.2)
    th = 1e-3  # small rotation: a = d = cos - 1, b = -sin, c = sin
    m = [0, 0, np.cos(th) - 1, -np.sin(th), np.sin(th), np.cos(th) - 1, 0, 0]
    dx, dy = motion_displacement(m, cx + 100.0, cy, SIZE)
    np.testing.assert_allclose([dx, dy], [100 * (np.cos(th) - 1), 100 * np.sin(th)], atol=1e-12)
    s = motion_summary(m, SIZE)
    assert s["rotation"] == pytest.approx(np.sin(th))
    assert s["extent"] == pytest.approx(th * np.hypot(cx, cy), rel=1e-3)


def test_homography_terms_vanish_at_the_centre_and_grow_outwards():
    m = [0, 0, 0, 0, 0, 0, 1e-6, 0]
    cx, cy = (SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2
    dx, dy = motion_displacement(m, np.array([cx, cx + 150]), np.array([cy, cy]), SIZE)
    assert dx[0] == 0 and dy[0] == 0
    assert dx[1] == pytest.approx(150 / (1 + 150e-6) - 150)


def test_motion_field_is_the_cell_mean_of_an_affine_motion():
    m = np.array([0.25, -0.1, 2e-4, -3e-4, 3e-4, 1e-4, 0, 0])
    f = 3
    field = motion_field(m, SIZE, f)
    W, H = SIZE
    y, x = np.mgrid[0:H, 0:W].astype(float)
    dx, dy = motion_displacement(m, x, y, SIZE)
    mean = dx[:H // f * f, :W // f * f].reshape(H // f, f, W // f, f).mean(axis=(1, 3))
    np.testing.assert_allclose(field[..., 0], mean, atol=1e-6)
    assert motion_extent(m, SIZE) == pytest.approx(np.max(np.hypot(dx, dy)), rel=1e-9)


def test_flow_fit_recovers_an_affine_motion_beside_a_plume():
    rng = np.random.default_rng(4)
    f = 2
    m = np.array([0.15, 0.08, 1.5e-4, -2e-4, 2e-4, -5e-5, 0, 0])
    flow = motion_field(m, SIZE, f) + rng.normal(0, 0.02, (SIZE[1] // f, SIZE[0] // f, 2)).astype(np.float32)
    # a "plume" of 0.4 px deflections over a fifth of the cells, and NaN cells
    flow[40:100, 60:90, 0] += 0.4
    flow[5:8, 5:8] = np.nan
    fit, info = fit_flow_motion(flow, np.ones(flow.shape[:2], bool), SIZE, f, model="affine")
    W, H = SIZE
    y, x = np.mgrid[0:H:4, 0:W:4]
    dx, dy = motion_displacement(fit - m, x, y, SIZE)
    assert np.sqrt(np.mean(dx ** 2 + dy ** 2)) < 0.002  # px
    assert info["cells"] < flow.shape[0] * flow.shape[1] - 60 * 30  # the plume's cells were dropped


def _camera(distance=2.5, f=2400.0):
    R = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # looks along +x, z up
    t = np.array([0.0, 0.15, distance])
    bp, bn = Camera.background_from_distance(R, t, 2 * distance)
    return Camera("c", np.array([[f, 0, 159.5], [0, f, 119.5], [0, 0, 1]]), np.zeros(5), R, t, SIZE, bp, bn)


def _hits_box(cam: Camera, uv: np.ndarray, lo, hi) -> np.ndarray:
    o, d = cam.rays(uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (np.asarray(lo) - o) / d, (np.asarray(hi) - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    return tmax >= np.maximum(tmin, 0)


def test_static_region_holds_exactly_the_rays_that_miss_the_box():
    cam = _camera()
    grid = Grid((-0.05, -0.05, 0.05), (0.05, 0.05, 0.25), 0.005)
    fp = box_footprint(cam, grid.vmin, grid.vmax)
    W, H = SIZE
    v, u = np.mgrid[0:H:3, 0:W:3]
    uv = np.stack([u, v], axis=-1).reshape(-1, 2).astype(float)
    hits = _hits_box(cam, uv, grid.vmin, grid.vmax)
    inside = fp[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    assert 0.1 < inside.mean() < 0.9
    assert np.mean(inside == hits) > 0.995  # pixel-edge rounding only
    static = static_region(cam, grid.vmin, grid.vmax, margin=10)
    assert not (static & fp).any()
    assert static.mean() < (~fp).mean()
    cells = static_cells(static, 3)
    assert cells.shape == (H // 3, W // 3) and cells.any()


def test_a_camera_inside_the_box_has_no_static_region():
    cam = _camera()
    big = (-5.0, -5.0, -5.0), (5.0, 5.0, 5.0)
    assert not static_region(cam, *big).any()
