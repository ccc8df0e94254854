"""Lab effects (camera motion, lamp, defocus, vignetting, defects) and the dot texture,
each against an independent measurement of the rendered image."""

import dataclasses

import numpy as np
import pytest
from lab_helpers import phase_shift, radial_power

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.params import schema
from schlieren.pipeline.synthetic import lab as L
from schlieren.pipeline.synthetic import render as R
from schlieren.pipeline.synthetic.background import Texture, make_texture_background, wavelet_noise_tile
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.synthetic.tracer import active_box, field_stack

GRID = Grid((-0.04, -0.04, 0.0), (0.04, 0.04, 0.08), 0.004)
SIZE = (320, 240)
R_AMB = 2.9e-4


def _camera_and_background(texture=Texture(), *, seed=1):
    cam = make_rig(3, grid=GRID, image_size=SIZE, line_time=1.54e-5)[1].with_time_offset(0.0)
    zbg = float(np.linalg.norm(cam.center - cam.bg_point))
    bg = make_texture_background(cam.bg_point, cam.bg_normal, texture, pixel_footprint=zbg / cam.K[0, 0],
                                 tile=wavelet_noise_tile(128, seed=0), seed=seed)
    return cam, bg


def _still_frame(cam, bg, rotation):
    """A frame without flow from the camera turned by ``rotation``, every pixel rendered."""
    fields = field_stack([np.full(GRID.shape, R_AMB)], GRID)
    lat = R.make_lattice(SIZE, 3)
    moved = L.moved_camera(cam, rotation)
    tr = R.trace_lattice(moved, lat, fields, np.zeros(1), GRID, frame=0, frame_rate=60.0, n_ambient=1 + R_AMB,
                         clip_box=active_box(fields, GRID))
    assert not tr.marched.any()
    img, delta = R.render_frame(moved, bg, tr, lat)
    np.testing.assert_array_equal(delta, 0.0)
    return img


@pytest.fixture(scope="module")
def scene():
    cam, bg = _camera_and_background()
    return cam, bg, R.reference_image(cam, bg)


def test_lab_params_schema_and_presets():
    fields = {f.name: f for f in schema(L.LabParams)}
    assert fields["motion_offset"].unit == "px" and fields["defocus"].unit == "px"
    assert fields["roll"].unit == "deg" and fields["banding_frequency"].unit == "Hz"
    assert not L.LabParams().active and not L.LabParams().moves
    lab = L.LAB_PRESETS["lab"]   # issue 33's reference lab capture
    assert (lab.motion_offset, lab.motion_walk, lab.flicker_gain, lab.flicker_offset, lab.defocus,
            lab.hot_pixels) == (0.1, 0.05, 0.02, 1.0, 0.7, 25)
    assert lab.active and lab.moves and lab.roll == lab.banding == lab.vignetting == lab.dead_pixels == 0
    assert all(getattr(L.LAB_PRESETS["lab-all"], f) > 0 for f in fields)


def test_motion_rotation_moves_the_principal_point_by_the_shift():
    cam, _ = _camera_and_background()
    f = cam.K[0, 0]
    for shift, roll in (((0.3, -0.2), 0.0), ((-1.5, 0.7), np.deg2rad(0.3)), ((0.0, 0.0), np.deg2rad(-1.0))):
        D = L.motion_rotation(shift, roll, f)
        np.testing.assert_allclose(D @ D.T, np.eye(3), atol=1e-14)
        moved = L.moved_camera(cam, D)
        np.testing.assert_allclose(moved.center, cam.center, atol=1e-12)
        # a point on the reference's optical axis is seen `shift` away from the principal point
        X = cam.center + 3.0 * cam.optical_axis
        np.testing.assert_allclose(moved.project(X[None])[0] - cam.K[:2, 2], shift, atol=1e-9)
        # every point moves by the homography K D K^-1 (no distortion here)
        pts = cam.center + np.array([[0.1, -0.05, 0.02], [-0.2, 0.1, 0.3], [0.02, 0.3, -0.1]]) + 4.0 * cam.optical_axis
        p0 = np.c_[cam.project(pts), np.ones(3)]
        q = p0 @ L.motion_homography(cam, D).T
        np.testing.assert_allclose(q[:, :2] / q[:, 2:], moved.project(pts), atol=1e-9)
        # roll: a point on the moved image's +u axis turns towards +v
        if roll:
            pu = np.array([cam.K[0, 2] + shift[0] + 50.0, cam.K[1, 2] + shift[1], 1.0])
            r = np.linalg.solve(L.motion_homography(cam, D), pu)
            ang = np.arctan2(-(r[1] / r[2] - cam.K[1, 2]), r[0] / r[2] - cam.K[0, 2])
            assert ang == pytest.approx(roll, rel=0.02)


def test_a_moved_camera_shifts_the_whole_background_by_the_recorded_motion(scene):
    """Phase correlation of the rendered frame against the reference recovers the drawn shift."""
    cam, bg, ref = scene
    rng = np.random.default_rng(5)
    lab = L.draw_camera(L.LabParams(motion_offset=0.3, motion_walk=0.1), cam, rng, n_raw=4, n_ref=0,
                        frame_rate=60.0, lamp_phase=0.0)
    assert np.hypot(*lab.shift[0]) == pytest.approx(0.3)
    assert np.all(lab.roll == 0.0)
    for f in range(4):
        img = _still_frame(cam, bg, lab.rotation[f])
        np.testing.assert_allclose(phase_shift(ref, img), lab.shift[f], atol=0.005)


def test_a_rolled_camera_moves_each_patch_as_its_homography_says(scene):
    cam, bg, ref = scene
    roll = np.deg2rad(0.15)
    D = L.motion_rotation((0.2, -0.1), roll, cam.K[0, 0])
    Hm = L.motion_homography(cam, D)
    img = _still_frame(cam, bg, D)
    wants = []
    for r0, c0 in ((16, 16), (16, 240), (160, 16), (160, 240), (88, 128)):
        centre = np.array([c0 + 31.5, r0 + 31.5, 1.0])
        q = Hm @ centre
        wants.append(q[:2] / q[2] - centre[:2])
        got = phase_shift(ref[r0:r0 + 64, c0:c0 + 64], img[r0:r0 + 64, c0:c0 + 64], kmax=0.1)
        # the patch turns inside its window (+-0.08 px at its edges): 0.025 px of slack
        np.testing.assert_allclose(got, wants[-1], atol=0.025)
    # the corners move apart by far more than that: a roll, not a shift
    assert np.ptp(np.array(wants), axis=0).max() > 0.5


def _row_gain_fit(ref, img):
    """Least squares ``img[v, u] = a_v ref[v, u] + b`` (a gain per row, one offset): (a, b)."""
    H, W = ref.shape
    N = np.zeros((H + 1, H + 1))
    N[np.arange(H), np.arange(H)] = (ref * ref).sum(axis=1)
    N[:H, H] = N[H, :H] = ref.sum(axis=1)
    N[H, H] = ref.size
    rhs = np.r_[(ref * img).sum(axis=1), img.sum()]
    x = np.linalg.solve(N, rhs)
    return x[:H], x[H]


def test_lamp_gain_offset_and_banding_recovered_by_least_squares(scene):
    cam, _, ref = scene
    params = L.LabParams(flicker_gain=0.03, flicker_offset=2.0, banding=0.02, banding_frequency=100.0)
    rng = np.random.default_rng(2)
    lab = L.draw_camera(params, cam, rng, n_raw=6, n_ref=2, frame_rate=60.0, lamp_phase=1.0)
    for f in range(6):
        img = L.photometry(ref, params, cam, gain=lab.gain[f], offset=lab.offset[f], phase=lab.phase[f])
        coef, offset = _row_gain_fit(ref, img)
        t = np.arange(ref.shape[0]) * cam.line_time
        want = lab.gain[f] * (1 + 0.02 * np.sin(2 * np.pi * 100.0 * t + lab.phase[f]))
        np.testing.assert_allclose(coef, want, rtol=1e-9)
        assert offset == pytest.approx(lab.offset[f], abs=1e-7)
    # the banding phase follows the frame's start time (one lamp for the rig)
    step = np.mod(np.diff(lab.phase) - 2 * np.pi * 100.0 / 60.0 + np.pi, 2 * np.pi) - np.pi
    np.testing.assert_allclose(step, 0.0, atol=1e-9)
    assert np.std(lab.gain) > 0.005 and np.std(lab.offset) > 0.3


def test_defocus_reduces_fine_texture_energy_as_its_gaussian_predicts(scene):
    _, _, ref = scene
    sigma = 0.7
    blurred = L.defocus(ref, sigma)
    edges = np.array([0.05, 0.1, 0.15, 0.2, 0.25, 0.3])
    ratio = radial_power(blurred, edges) / radial_power(ref, edges)
    k = 0.5 * (edges[:-1] + edges[1:])
    np.testing.assert_allclose(ratio, np.exp(-(2 * np.pi * sigma * k) ** 2), rtol=0.08)


def test_vignetting_and_defects(scene):
    cam, _, ref = scene
    v = L.vignette(cam, 0.25)
    assert v.max() == pytest.approx(1.0, abs=1e-4) and v.min() == pytest.approx(0.75)
    assert v[0, 0] == pytest.approx(0.75)
    params = L.LabParams(hot_pixels=30, dead_pixels=20, stuck_pixels=10)
    lab = L.draw_camera(params, cam, np.random.default_rng(3), n_raw=1, n_ref=0, frame_rate=60.0, lamp_phase=0.0)
    pos = np.concatenate([lab.hot, lab.dead, lab.stuck])
    assert len({tuple(p) for p in pos}) == 60                         # distinct pixels
    frame = R.sensor(ref, noise=1.5, bit_depth=16, rng=np.random.default_rng(0))
    out = L.apply_defects(frame, lab)
    assert np.all(out[lab.hot[:, 0], lab.hot[:, 1]] == 65535) and np.all(out[lab.dead[:, 0], lab.dead[:, 1]] == 0)
    np.testing.assert_allclose(out[lab.stuck[:, 0], lab.stuck[:, 1]], lab.stuck_value * 257, atol=0.5)
    keep = np.ones(frame.shape, bool)
    keep[pos[:, 0], pos[:, 1]] = False
    np.testing.assert_array_equal(out[keep], frame[keep])
    with pytest.raises(ValueError, match="do not fit"):
        L.draw_camera(dataclasses.replace(params, hot_pixels=10 ** 6), cam, np.random.default_rng(0), n_raw=1,
                      n_ref=0, frame_rate=60.0, lamp_phase=0.0)


def test_dot_texture_is_normalised_and_shifts_cleanly():
    """A printed dot pattern: zero-mean unit-variance pattern (grey levels mean 128, std 40),
    dark dots of the requested size, rendered cleanly enough that a camera shift is
    recovered as precisely as on noise."""
    tex = Texture(kind="dots", scale=4.0, dot_diameter=0.6, dot_edge=0.1)
    cam, bg = _camera_and_background(tex, seed=4)
    ref = R.reference_image(cam, bg)
    assert ref.mean() == pytest.approx(128.0, abs=3.0) and ref.std() == pytest.approx(40.0, rel=0.1)
    # about pi r^2 of the paper is ink (overlaps take a little): 28 % for 0.6 pitch
    ink = bg.dot_par[2]
    assert 0.22 < ink < 0.29
    D = L.motion_rotation((0.23, -0.17), 0.0, cam.K[0, 0])
    np.testing.assert_allclose(phase_shift(ref, _still_frame(cam, bg, D)), (0.23, -0.17), atol=0.005)
