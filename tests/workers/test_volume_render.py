"""The volume renderer checked against what it must show: the emission-absorption integral
of a homogeneous slab, blob positions in the orthographic view, one scale for an animation
(workers/report/volume_render.py)."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid
from schlieren.workers.report import volume_render

from report_volumes import GRID, R_AMB, blob


# -- volume rendering -------------------------------------------------------------------------

def test_ambient_volume_renders_background_only():
    vol = np.full(GRID.shape, R_AMB)
    tf = volume_render.TransferFunction(r_ambient=R_AMB, scale=1e-5)
    img = volume_render.render_volume(vol, GRID, image_size=(40, 30), transfer=tf, draw_box=False,
                                      background=(10, 20, 30))
    assert img.shape == (30, 40, 3) and img.dtype == np.uint8
    assert np.all(img == np.array([10, 20, 30], dtype=np.uint8))


def test_homogeneous_slab_matches_emission_absorption_integral():
    """Gas at full signal everywhere, view along -x through the box centre: the centre pixel
    is rgb(1) * (1 - exp(-sigma * L_x)), sigma = optical_depth / L_max."""
    tf = volume_render.TransferFunction(r_ambient=R_AMB, scale=2e-5, optical_depth=1.5)
    vol = np.full(GRID.shape, R_AMB - 2e-5)
    img = volume_render.render_volume(vol, GRID, azimuth_deg=0.0, elevation_deg=0.0, image_size=(41, 41),
                                      transfer=tf, draw_box=False, step=0.5).astype(float)
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
    tf = volume_render.TransferFunction(r_ambient=R_AMB, scale=5e-5)
    img = volume_render.render_volume(vol, GRID, azimuth_deg=0.0, elevation_deg=0.0, image_size=(W, H),
                                      transfer=tf, draw_box=False).astype(float).sum(axis=-1)
    rows, cols = np.mgrid[0:H, 0:W]
    col = (img * cols).sum() / img.sum()
    row = (img * rows).sum() / img.sum()
    centre_z = 0.025
    assert col == pytest.approx((W - 1) / 2 + y0 / pix, abs=0.5)
    assert row == pytest.approx((H - 1) / 2 - (z0 - centre_z) / pix, abs=0.5)
    # from the opposite side (azimuth 180) the blob is mirrored left-right
    img2 = volume_render.render_volume(vol, GRID, azimuth_deg=180.0, elevation_deg=0.0, image_size=(W, H),
                                       transfer=tf, draw_box=False).astype(float).sum(axis=-1)
    assert (img2 * cols).sum() / img2.sum() == pytest.approx((W - 1) / 2 - y0 / pix, abs=0.5)


def test_early_termination_changes_nothing_visible_and_input_untouched():
    vol = blob((0.0, 0.0, 0.025), amp=2e-4, sigma=0.008)
    before = vol.copy()
    tf = volume_render.TransferFunction(r_ambient=R_AMB, scale=2e-4, optical_depth=40.0)
    a = volume_render.render_volume(vol, GRID, image_size=(48, 40), transfer=tf, min_transmittance=1e-3).astype(int)
    b = volume_render.render_volume(vol, GRID, image_size=(48, 40), transfer=tf, min_transmittance=0.0).astype(int)
    assert np.abs(a - b).max() <= 1
    np.testing.assert_array_equal(vol, before)


def test_fit_image_size_follows_the_box_aspect():
    tall = Grid((-0.01, -0.01, 0.0), (0.01, 0.01, 0.08), 0.0025)
    w, h = volume_render.fit_image_size(tall, azimuth_deg=0.0, elevation_deg=0.0, long_side=400)
    assert h == 400 and w == pytest.approx(100, abs=1)


def test_animation_uses_one_scale_for_all_frames():
    vols = np.stack([blob((0, 0, 0.025), amp=6e-5), blob((0, 0, 0.025), amp=2e-5)])
    frames = volume_render.animation_frames(vols, GRID, r_ambient=R_AMB, times=[0.0, 1 / 60], image_size=(64, 56))
    assert len(frames) == 2 and frames[0].shape == (56, 64, 3)
    # the weaker blob is darker (a per-frame scale would make them look alike)
    core = (slice(18, 38), slice(22, 42))
    assert frames[0][core].mean() > 1.5 * frames[1][core].mean()
