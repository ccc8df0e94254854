"""Visual hull: conservative carving against an analytic sphere silhouette."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid
from schlieren.pipeline.hull import HullParams, visual_hull


def ring(n, grid, image_size, dist=None, radius=1.0):
    c = np.asarray(grid.center)
    W, H = image_size
    ext = grid.vmax[0] - grid.vmin[0]
    f = 0.6 * W * radius / ext
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    cams = []
    for k in range(n):
        phi = np.pi * (k + 0.5) / n
        C = c + radius * np.array([np.cos(phi), np.sin(phi), 0.1 * (k % 2)])
        fwd = (c - C) / np.linalg.norm(c - C)
        x = np.cross(fwd, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(fwd, x), fwd])
        cams.append(Camera(f"c{k}", K, np.zeros(5) if dist is None else dist, R, -R @ C, image_size,
                           c + fwd, -fwd))
    return cams


def sphere_masks(cams, fg, centre, radius):
    """Flow pixels whose (undistorted) ray passes within ``radius`` of ``centre``."""
    uv = fg.pixel_centres()
    out = []
    for cam in cams:
        o, d = cam.rays(uv)
        v = centre - o
        perp = v - (v @ d.reshape(-1, 3).T).reshape(d.shape[:-1])[..., None] * d
        out.append(np.linalg.norm(perp, axis=-1) <= radius)
    return np.stack(out)


@pytest.mark.parametrize("dist", [None, np.array([-0.1, 0.03, 0.0, 0.0, 0.0])])
def test_hull_of_sphere_is_conservative_and_tight(dist):
    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.0025)  # 40^3
    image = (160, 120)
    fg = FlowGrid(image, 2)
    cams = ring(8, grid, image, dist=dist)
    centre = np.array([0.006, -0.004, 0.003])
    R = 0.02
    masks = sphere_masks(cams, fg, centre, R)
    hull = visual_hull(masks, cams, grid, fg, params=HullParams())
    r = np.linalg.norm(grid.centres() - centre, axis=-1)
    # Conservative: every voxel that overlaps the sphere survives.
    assert hull[r <= R + 0.5 * grid.voxel_size].all()
    # Tight: 8 views on a half ring bound the hull by a 16-gon (circumradius 1.02 R) in
    # every horizontal slice; allow the footprint tolerance (about two voxels).
    assert not hull[r > 1.02 * R + 2.5 * grid.voxel_size].any()
    assert hull.sum() < 1.8 * (r <= R).sum()


def test_unseen_voxels_and_empty_masks():
    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.005)
    image = (80, 60)
    fg = FlowGrid(image, 2)
    cams = ring(4, grid, image)
    full = np.ones((4,) + fg.shape, bool)
    assert visual_hull(full, cams, grid, fg).all()
    empty = full.copy()
    empty[2] = False  # one camera sees no flow anywhere: in the strict intersection everything it sees is carved
    strict = HullParams(outlier_ratio=0.0)
    assert not visual_hull(empty, cams, grid, fg, params=strict).any()
    # ... by default it disagrees with the three others' consensus (it alone rejects every voxel they keep)
    assert visual_hull(empty, cams, grid, fg).all()
    # the first camera carves everything: the distorted cameras after it have nothing to test
    lens = [Camera(c.name, c.K, np.array([-0.05, 0.01, 0.0, 0.0, 0.0]), c.R, c.t, image, c.bg_point, c.bg_normal)
            for c in cams]
    first_empty = full.copy()
    first_empty[0] = False
    assert not visual_hull(first_empty, lens, grid, fg, params=strict).any()
    assert not visual_hull(np.zeros_like(full), lens, grid, fg).any()  # no camera sees flow: nothing is kept
    assert visual_hull(full, lens, grid, fg).sum() > 0
    # A camera that does not see the volume cannot carve it.
    away = cams[0]
    R = away.R.copy()
    R[[0, 2]] *= -1  # turn around: the volume is behind the camera
    behind = Camera("away", away.K, away.dist, R, -R @ away.center, image, away.bg_point, away.bg_normal)
    masks = np.concatenate([full[:3], np.zeros((1,) + fg.shape, bool)])
    hull = visual_hull(masks, cams[:3] + [behind], grid, fg)
    assert hull.all()
    # ... unless it is required to see it.
    assert visual_hull(full[:1], [behind], grid, fg, params=HullParams(min_views=1)).sum() == 0


def test_rejects_bad_shapes():
    grid = Grid((-0.05,) * 3, (0.05,) * 3, 0.01)
    fg = FlowGrid((80, 60), 2)
    cams = ring(2, grid, (80, 60))
    with pytest.raises(ValueError):
        visual_hull(np.ones((3,) + fg.shape, bool), cams, grid, fg)


@pytest.mark.parametrize("dist", [None, np.array([-0.1, 0.03, 0.0, 0.0, 0.0])])
def test_shared_projection_carves_the_same_hull_for_every_frame(dist):
    """A sequence computes the mask-independent projection once (hull_projection): the hulls of
    moving spheres and of ragged masks equal the ones each frame carves on its own, and the
    OpenCV distance transform equals scipy's exact one."""
    from scipy import ndimage

    from schlieren.pipeline.hull import _distance_to_mask, hull_projection

    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.0025)
    image = (160, 120)
    fg = FlowGrid(image, 2)
    cams = ring(8, grid, image, dist=dist)
    params = HullParams(margin_px=0.5, min_views=2)
    proj = hull_projection(cams, grid, fg, params=params)
    assert proj.pixel.shape == (8, 40 ** 3) and proj.nbytes == 8 * 8 * 40 ** 3
    rng = np.random.default_rng(5)
    for k in range(3):
        masks = sphere_masks(cams, fg, np.array([0.004 * k, -0.004, 0.01 * k - 0.01]), 0.015 + 0.004 * k)
        masks &= rng.random(masks.shape) > 0.05  # holes
        masks[k] = False if k == 2 else masks[k]  # a camera without flow
        alone = visual_hull(masks, cams, grid, fg, params=params)
        assert alone.any() or k == 2
        np.testing.assert_array_equal(visual_hull(masks, cams, grid, fg, params=params, projection=proj), alone)
        for m in masks[:2]:
            np.testing.assert_allclose(_distance_to_mask(m), ndimage.distance_transform_edt(~m), atol=1e-4)
    with pytest.raises(ValueError, match="projection"):
        visual_hull(masks[:4], cams[:4], grid, fg, projection=proj)


@pytest.mark.parametrize("shared", [False, True])
def test_max_misses_keeps_voxels_one_noisy_mask_cut_off(shared):
    """``max_misses`` = k: a voxel is carved only when more than k of the cameras that see it
    reject it. One camera whose mask lost part of the sphere (noisy masks of a lossy capture)
    cuts it out of the strict hull; with k = 1 the sphere survives whole while a region two
    cameras reject is still carved, and k = 1 equals the brute-force count of rejections."""
    from schlieren.pipeline.hull import _distance_to_mask, hull_projection

    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.0025)
    image = (160, 120)
    fg = FlowGrid(image, 2)
    cams = ring(8, grid, image)
    centre, R = np.array([0.0, 0.0, 0.0]), 0.02
    masks = sphere_masks(cams, fg, centre, R)
    cut = masks.copy()
    cut[3, : fg.shape[0] // 2] = False  # camera 3 misses the sphere's upper half
    r = np.linalg.norm(grid.centres() - centre, axis=-1)
    inside = r <= R + 0.5 * grid.voxel_size
    for k, expect_whole in ((0, False), (1, True)):
        params = HullParams(max_misses=k, outlier_ratio=0.0)
        proj = hull_projection(cams, grid, fg, params=params) if shared else None
        hull = visual_hull(cut, cams, grid, fg, params=params, projection=proj)
        assert hull[inside].all() == expect_whole, k
        # brute force: count each voxel's rejections over all cameras
        pr = hull_projection(cams, grid, fg, params=params)
        misses = np.zeros(pr.pixel.shape[1], int)
        for c in range(len(cams)):
            d = _distance_to_mask(cut[c]).ravel()
            seen = pr.pixel[c] >= 0
            misses[seen] += d[pr.pixel[c][seen]] > pr.tol[c][seen]
        np.testing.assert_array_equal(hull.ravel(), misses <= k)
    # a second camera missing the same half: two rejections, carved again with k = 1
    cut[5, : fg.shape[0] // 2] = False
    assert not visual_hull(cut, cams, grid, fg, params=HullParams(max_misses=1))[inside].all()
    assert visual_hull(cut, cams, grid, fg, params=HullParams(max_misses=2))[inside].all()
    # an empty mask counts as one rejection of everything its camera sees
    empty = masks.copy()
    empty[0] = False
    assert not visual_hull(empty, cams, grid, fg, params=HullParams(outlier_ratio=0.0)).any()
    assert visual_hull(empty, cams, grid, fg, params=HullParams(max_misses=1))[inside].all()


@pytest.mark.parametrize("shared", [False, True])
def test_outlier_camera_is_forgiven_and_agreeing_masks_stay_strict(shared):
    """``outlier_ratio``: one camera whose mask lost part of the sphere (a known voxel set only it
    rejects) is an outlier against the others' consensus, and the sphere survives whole; where the
    masks agree (the analytic silhouettes, or all of them with random holes) every camera alone
    carves about as much as the median camera and the hull equals the strict intersection
    exactly; two cameras missing the same part still carve it."""
    from schlieren.pipeline.hull import hull_projection, lone_rejections

    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.0025)
    image = (160, 120)
    fg = FlowGrid(image, 2)
    cams = ring(8, grid, image)
    centre, R = np.array([0.002, -0.003, 0.001]), 0.02
    masks = sphere_masks(cams, fg, centre, R)
    r = np.linalg.norm(grid.centres() - centre, axis=-1)
    inside = r <= R + 0.5 * grid.voxel_size
    params = HullParams(outlier_ratio=3.0)
    proj = hull_projection(cams, grid, fg, params=params) if shared else None

    def hull(m, p=params):
        return visual_hull(m, cams, grid, fg, params=p, projection=proj)

    strict = HullParams(outlier_ratio=0.0)
    assert HullParams().outlier_ratio == params.outlier_ratio  # the default
    np.testing.assert_array_equal(hull(masks), hull(masks, strict))
    rng = np.random.default_rng(2)
    ragged = masks & (rng.random(masks.shape) > 0.03)
    np.testing.assert_array_equal(hull(ragged), hull(ragged, strict))
    cut = masks.copy()
    cut[3, : fg.shape[0] // 2] = False  # camera 3 misses the sphere's upper half
    assert not hull(cut, strict)[inside].all()
    alone = lone_rejections(cut, cams, grid, fg, projection=proj)
    assert alone.argmax() == 3 and alone[3] > 3.0 * np.median(alone)
    assert lone_rejections(masks, cams, grid, fg).max() <= 3.0 * max(np.median(lone_rejections(masks, cams, grid, fg)), 1)
    kept = hull(cut)
    assert kept[inside].all()
    others = [c for c in range(len(cams)) if c != 3]  # what only camera 3 carved comes back, nothing more
    seven = visual_hull(masks[others], [cams[c] for c in others], grid, fg, params=strict)
    assert (kept >= hull(masks, strict)).all() and (kept <= seven).all()
    cut[5, : fg.shape[0] // 2] = False
    assert not hull(cut)[inside].all()
