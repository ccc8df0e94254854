"""Pictures checked against what they must show: colour-wheel hues, arrow positions, world
extents of slices, the emission-absorption integral of a homogeneous slab, blob positions."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline import viz
from schlieren.pipeline.geometry import FlowGrid, Grid

GRID = Grid((-0.02, -0.03, 0.0), (0.02, 0.03, 0.05), 0.0025)  # nx, ny, nz = 16, 24, 20
R_AMB = 2.9e-4


def blob(centre, amp=5e-5, sigma=0.004, grid=GRID):
    d = grid.centres() - np.asarray(centre)
    return R_AMB - amp * np.exp(-np.sum(d ** 2, axis=-1) / (2 * sigma ** 2))


# -- colour coding --------------------------------------------------------------------------

def test_flow_colours_follow_the_middlebury_wheel():
    flow = np.array([[[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [np.nan, 0.0]]])
    rgb = viz.flow_to_rgb(flow, max_magnitude=1.0)[0].astype(int)
    assert rgb[0].tolist() == [255, 255, 255]          # no flow: white
    assert rgb[1][0] == 255 and rgb[1][1] == 0 and rgb[1][2] < 50  # right: red
    assert rgb[2][0] == 0 and rgb[2][2] == 255          # left: cyan-blue
    assert rgb[3][0] == 255 and rgb[3][2] == 0 and 100 < rgb[3][1] < 255  # down: orange-yellow
    assert rgb[4][2] == 255 and rgb[4][1] == 0          # up: blue-violet
    assert rgb[5].tolist() == [0, 0, 0]                 # invalid: black


def test_flow_colour_saturation_grows_with_magnitude_and_wheel_has_no_seam():
    mags = np.linspace(0, 1, 11)
    flow = np.stack([mags * np.cos(0.7), mags * np.sin(0.7)], axis=-1)[None]
    rgb = viz.flow_to_rgb(flow, max_magnitude=1.0)[0].astype(float)
    dist_from_white = np.linalg.norm(255 - rgb, axis=-1)
    assert np.all(np.diff(dist_from_white) > 0)
    over = viz.flow_to_rgb(np.array([[[2.0, 0.0]]]), max_magnitude=1.0)[0, 0]
    assert over.max() == round(0.75 * 255)  # saturated beyond the range, darkened
    ang = np.linspace(-np.pi, np.pi, 3601)
    ring = viz.flow_to_rgb(np.stack([np.cos(ang), np.sin(ang)], -1)[None], max_magnitude=1.0)[0].astype(int)
    assert np.abs(np.diff(ring, axis=0)).max() <= 12  # continuous hue, including across +-pi
    wheel = viz.flow_wheel(51)
    assert wheel[25, 25].tolist() == [255, 255, 255] and wheel[0, 0].tolist() == [255, 255, 255]


def test_flow_to_rgb_default_scale_and_input_untouched():
    rng = np.random.default_rng(1)
    flow = rng.normal(size=(8, 9, 2)).astype(np.float32)
    before = flow.copy()
    a = viz.flow_to_rgb(flow)
    b = viz.flow_to_rgb(flow, max_magnitude=float(np.hypot(flow[..., 0], flow[..., 1]).max()))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(flow, before)
    with pytest.raises(ValueError):
        viz.flow_to_rgb(np.zeros((4, 4)))


# -- figures ----------------------------------------------------------------------------------

def test_quiver_arrows_start_at_flow_grid_centres():
    fg = FlowGrid((61, 46), 3)  # image 61 x 46 px -> flow 15 x 20 (a remainder column and row)
    rng = np.random.default_rng(2)
    flow = rng.normal(0, 0.2, fg.shape + (2,))
    fig = viz.quiver_figure(rng.random((46, 61)), flow, step=4)
    q = fig.axes[0].collections[0]
    centres = fg.pixel_centres()
    rows = np.arange(2, fg.shape[0], 4)
    cols = np.arange(2, fg.shape[1], 4)
    want_xy = centres[np.ix_(rows, cols)].reshape(-1, 2)
    np.testing.assert_allclose(q.XY, want_xy)
    np.testing.assert_allclose(q.U, flow[np.ix_(rows, cols)][..., 0].ravel())
    np.testing.assert_allclose(q.V, flow[np.ix_(rows, cols)][..., 1].ravel())
    assert "arrows x" in fig.axes[0].get_title()


def test_deflection_figure_shows_the_colour_coding_and_mask():
    fg = FlowGrid((64, 48), 2)
    yy, xx = np.mgrid[0:fg.shape[0], 0:fg.shape[1]]
    flow = np.stack([(xx - 16.0) / 16, (yy - 12.0) / 16], axis=-1) * 0.3
    mask = np.hypot(flow[..., 0], flow[..., 1]) < 0.1
    fig = viz.deflection_figure(np.zeros((48, 64)), flow, mask=mask, potential=flow[..., 0], step=4,
                                max_magnitude=0.3)
    coded = fig.axes[1].images[0].get_array()
    np.testing.assert_array_equal(np.asarray(coded), viz.flow_to_rgb(flow, max_magnitude=0.3))
    mask_ax = [ax for ax in fig.axes if ax.get_title().startswith("mask")][0]
    np.testing.assert_array_equal(np.asarray(mask_ax.images[0].get_array()), mask)
    labels = [a.get_ylabel() for a in fig.axes]
    assert "integrated deflection (px$^2$)" in labels and "|deflection| (px)" in labels
    assert viz.figure_to_rgb(fig).shape[2] == 3


def test_slice_figure_world_extent_units_and_values():
    vol = blob((0.004, -0.01, 0.02))
    fig = viz.slice_figure(vol * 1e6, GRID, axis="y", index=8, label="refractivity", units="1e-6")
    ax = fig.axes[0]
    img = ax.images[0]
    assert img.get_extent() == pytest.approx([-20.0, 20.0, 0.0, 50.0])  # x and z in mm
    np.testing.assert_allclose(np.asarray(img.get_array()), vol[:, 8, :] * 1e6)
    assert ax.get_xlabel() == "x (mm)" and ax.get_ylabel() == "z (mm)"
    assert fig.axes[1].get_ylabel() == "refractivity (1e-6)"  # colour bar
    assert ax.get_title() == f"y = {GRID.axes()[1][8] * 1e3:.1f} mm"
    with pytest.raises(IndexError):
        viz.slice_figure(vol, GRID, axis="x", index=16)


def test_orthoslices_share_one_colour_range():
    vol = blob((0.0, 0.0, 0.02))
    fig = viz.orthoslices_figure(vol, GRID, index=(8, 12, 8), label="T", units="K")
    ims = [ax.images[0] for ax in fig.axes if ax.images]
    assert len(ims) == 3
    assert len({im.get_clim() for im in ims}) == 1
    np.testing.assert_allclose(np.asarray(ims[0].get_array()), vol[8])
    assert fig.axes[-1].get_ylabel() == "T (K)"


def test_gradient_arrows_point_outward_from_a_hot_blob():
    """Arrows are the in-plane gradient components at voxel centres (mm): for a refractivity
    dip the gradient points away from the centre on every slice through it."""
    c = (0.0025 * 0.5, 0.0025 * 0.5, 0.02 + 0.0025 * 0.5)  # a voxel centre
    vol = blob(c, sigma=0.006)
    gz, gy, gx = np.gradient(vol, GRID.voxel_size)
    vec = np.stack([gx, gy, gz], axis=-1)
    idx = tuple(int(round(v)) for v in GRID.world_to_index(np.asarray(c))[::-1])  # (iz, iy, ix)
    fig = viz.orthoslices_figure(np.linalg.norm(vec, axis=-1), GRID, index=idx, vectors=vec, vector_step=2)
    centre_mm = np.asarray(c) * 1e3
    for ax, (h, v) in zip(fig.axes[:3], ((0, 1), (0, 2), (1, 2))):
        q = ax.collections[0]
        rel = q.XY - centre_mm[[h, v]]
        uv = np.stack([q.U, q.V], axis=-1)
        big = np.hypot(*uv.T) > 0.2 * np.hypot(*uv.T).max()
        cos = np.sum(rel[big] * uv[big], axis=1) / (np.linalg.norm(rel[big], axis=1) * np.linalg.norm(uv[big], axis=1))
        assert big.sum() > 8 and np.all(cos > 0.95)


def test_residual_and_hull_figures_show_their_data():
    rng = np.random.default_rng(4)
    meas = rng.normal(0, 0.1, (10, 12, 2))
    pred = meas + 0.02
    fig = viz.residual_figure(meas, pred)
    assert fig.axes[2].get_title() == f"residual (RMS {np.sqrt(2) * 0.02:.3g} px)"
    hull = np.zeros(GRID.shape, bool)
    hull[5:15, 8:16, 4:10] = True
    fig = viz.hull_figure(hull, GRID)
    silhouettes = [np.asarray(ax.images[0].get_array()) for ax in fig.axes[1:4]]
    np.testing.assert_allclose(silhouettes[0], hull.mean(axis=0))
    np.testing.assert_allclose(silhouettes[2], hull.mean(axis=2))
    fig = viz.timings_figure({"flow": 3.0, "tomography": 5.5})
    assert [p.get_width() for p in fig.axes[0].patches] == [3.0, 5.5]


# -- volume rendering -------------------------------------------------------------------------

def test_ambient_volume_renders_background_only():
    vol = np.full(GRID.shape, R_AMB)
    tf = viz.TransferFunction(r_ambient=R_AMB, scale=1e-5)
    img = viz.render_volume(vol, GRID, image_size=(40, 30), transfer=tf, draw_box=False, background=(10, 20, 30))
    assert img.shape == (30, 40, 3) and img.dtype == np.uint8
    assert np.all(img == np.array([10, 20, 30], dtype=np.uint8))


def test_homogeneous_slab_matches_emission_absorption_integral():
    """Gas at full signal everywhere, view along -x through the box centre: the centre pixel
    is rgb(1) * (1 - exp(-sigma * L_x)), sigma = optical_depth / L_max."""
    tf = viz.TransferFunction(r_ambient=R_AMB, scale=2e-5, optical_depth=1.5)
    vol = np.full(GRID.shape, R_AMB - 2e-5)
    img = viz.render_volume(vol, GRID, azimuth_deg=0.0, elevation_deg=0.0, image_size=(41, 41), transfer=tf,
                            draw_box=False, step=0.5).astype(float)
    rgb_top = tf.tables()[0][-1]
    sigma = tf.optical_depth / 0.06  # longest edge: y, 60 mm
    Lx = 0.04
    want = 255 * rgb_top * (1 - np.exp(-sigma * Lx))
    np.testing.assert_allclose(img[20, 20], want, atol=1.0)
    # a corner pixel outside the box's projection stays black
    assert np.all(img[0, 0] == 0)


def test_blob_appears_where_the_orthographic_camera_sees_it():
    """From azimuth 0 (eye on +x) image right is +y and up is +z; the pixel size follows
    from fitting the projected box (y 60 mm x z 50 mm) into the image with a 8 % margin."""
    W, H = 121, 101
    pix = 1.08 * max(0.06 / W, 0.05 / H)
    y0, z0 = 0.012, 0.032
    vol = blob((0.0, y0, z0))
    tf = viz.TransferFunction(r_ambient=R_AMB, scale=5e-5)
    img = viz.render_volume(vol, GRID, azimuth_deg=0.0, elevation_deg=0.0, image_size=(W, H), transfer=tf,
                            draw_box=False).astype(float).sum(axis=-1)
    rows, cols = np.mgrid[0:H, 0:W]
    col = (img * cols).sum() / img.sum()
    row = (img * rows).sum() / img.sum()
    centre_z = 0.025
    assert col == pytest.approx((W - 1) / 2 + y0 / pix, abs=0.5)
    assert row == pytest.approx((H - 1) / 2 - (z0 - centre_z) / pix, abs=0.5)
    # from the opposite side (azimuth 180) the blob is mirrored left-right
    img2 = viz.render_volume(vol, GRID, azimuth_deg=180.0, elevation_deg=0.0, image_size=(W, H), transfer=tf,
                             draw_box=False).astype(float).sum(axis=-1)
    assert (img2 * cols).sum() / img2.sum() == pytest.approx((W - 1) / 2 - y0 / pix, abs=0.5)


def test_early_termination_changes_nothing_visible_and_input_untouched():
    vol = blob((0.0, 0.0, 0.025), amp=2e-4, sigma=0.008)
    before = vol.copy()
    tf = viz.TransferFunction(r_ambient=R_AMB, scale=2e-4, optical_depth=40.0)
    a = viz.render_volume(vol, GRID, image_size=(48, 40), transfer=tf, min_transmittance=1e-3).astype(int)
    b = viz.render_volume(vol, GRID, image_size=(48, 40), transfer=tf, min_transmittance=0.0).astype(int)
    assert np.abs(a - b).max() <= 1
    np.testing.assert_array_equal(vol, before)


def test_fit_image_size_follows_the_box_aspect():
    tall = Grid((-0.01, -0.01, 0.0), (0.01, 0.01, 0.08), 0.0025)
    w, h = viz.fit_image_size(tall, azimuth_deg=0.0, elevation_deg=0.0, long_side=400)
    assert h == 400 and w == pytest.approx(100, abs=1)


def test_animation_uses_one_scale_for_all_frames():
    vols = np.stack([blob((0, 0, 0.025), amp=6e-5), blob((0, 0, 0.025), amp=2e-5)])
    frames = viz.animation_frames(vols, GRID, r_ambient=R_AMB, times=[0.0, 1 / 60], image_size=(64, 56))
    assert len(frames) == 2 and frames[0].shape == (56, 64, 3)
    # the weaker blob is darker (a per-frame scale would make them look alike)
    core = (slice(18, 38), slice(22, 42))
    assert frames[0][core].mean() > 1.5 * frames[1][core].mean()


def test_viz_and_residuals_stay_pure():
    """pipeline.viz / pipeline.residuals import no storage, workers, dask or zarr, and never pyplot."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import schlieren.pipeline.viz, schlieren.pipeline.residuals\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'zarr')\n"
        "             or m.startswith(('schlieren.storage', 'schlieren.workers')) or m == 'matplotlib.pyplot')\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
