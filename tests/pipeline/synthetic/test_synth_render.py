"""Renderer: images and deflections against independent computations."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.synthetic import render as R
from schlieren.pipeline.synthetic.background import make_background, wavelet_noise_tile
from schlieren.pipeline.synthetic.phantoms import gaussian_blob
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.synthetic.tracer import active_box, field_stack

R_AMB = 2.9e-4
N_AMB = 1.0 + R_AMB
GRID = Grid((-0.04, -0.04, 0.0), (0.04, 0.04, 0.08), 0.002)
SIZE = (160, 120)


@pytest.fixture(scope="module")
def scene():
    cams = make_rig(4, grid=GRID, image_size=SIZE, line_time=0.0)
    cam = cams[0].with_time_offset(0.0)
    tile = wavelet_noise_tile(128, seed=0)
    zbg = np.linalg.norm(cam.center - cam.bg_point)
    bg = make_background(cam.bg_point, cam.bg_normal, spacing=1.5 * zbg / cam.K[0, 0], tile=tile, seed=1)
    return cam, bg


def _numpy_image(cam, bg, shift, s=3):
    """Independent path: pixel-area mean of the pattern seen straight through p + shift."""
    W, H = cam.image_size
    off = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(W)[:, None] + off[None, :]).ravel()
    v = (np.arange(H)[:, None] + off[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    uv = np.stack([uu + shift[0], vv + shift[1]], axis=-1)
    C, d = cam.rays(uv)
    X = cam.intersect_background(C, d)
    vals = bg.values(bg.plane_coords(X))
    return vals.reshape(H, s, W, s).mean(axis=(1, 3))


def _static(r):
    f = field_stack([r], GRID)
    return f, np.zeros(1)


def test_reference_matches_independent_path_and_zero_flow_is_reference(scene):
    cam, bg = scene
    ref = R.reference_image(cam, bg, supersample=3)
    np.testing.assert_allclose(ref, _numpy_image(cam, bg, (0.0, 0.0)), atol=1e-9)
    fields, kt = _static(np.full(GRID.shape, R_AMB))
    lat = R.make_lattice(SIZE, 3)
    tr = R.trace_lattice(cam, lat, fields, kt, GRID, frame=0, frame_rate=60.0, n_ambient=N_AMB,
                         clip_box=active_box(fields, GRID))
    img, delta = R.render_image(cam, bg, tr, lat, ref)
    assert not tr.marched.any()
    np.testing.assert_array_equal(img, ref)
    np.testing.assert_array_equal(delta, 0.0)


def test_uniform_gradient_gives_the_expected_image_shift(scene):
    cam, bg = scene
    # r = r_amb + G y: camera 0 looks along -x with image u along +y, so rays bend by
    # theta = G L / n towards +y, as if refracted once at the box centre: at the background
    # (2.5 m behind the centre, 5 m from the camera) the shift is f * theta * 2.5 / 5 pixels.
    G, L = 1e-2, 0.08
    x, y, z = GRID.axes()
    r = R_AMB + G * np.broadcast_to(y[None, :, None], GRID.shape)
    fields, kt = _static(r)
    lat = R.make_lattice(SIZE, 3)
    tr = R.trace_lattice(cam, lat, fields, kt, GRID, frame=0, frame_rate=60.0, n_ambient=N_AMB,
                         clip_box=(np.asarray(GRID.vmin), np.asarray(GRID.vmax)), step=GRID.voxel_size / 2)
    expected_u = cam.K[0, 0] * (G * L / N_AMB) * 2.5 / 5.0
    u, v = lat.coords()
    ci = np.argmin(np.abs(v - cam.K[1, 2]))
    cj = np.argmin(np.abs(u - cam.K[0, 2]))
    assert tr.delta[ci, cj, 0] == pytest.approx(expected_u, rel=0.01)
    assert abs(tr.delta[ci, cj, 1]) < 1e-3 * expected_u
    ref = R.reference_image(cam, bg)
    img, delta = R.render_image(cam, bg, tr, lat, ref)
    # central region (rays crossing front and back faces): the frame is the reference pattern
    # seen through p + delta, computed independently
    sl = (slice(45, 75), slice(60, 100))
    shifted = _numpy_image(cam, bg, (expected_u, 0.0))
    change = np.sqrt(np.mean((img[sl] - ref[sl]) ** 2))
    err = np.sqrt(np.mean((img[sl] - shifted[sl]) ** 2))
    spread = np.abs(delta[sl][..., 0] - expected_u).max()
    assert change > 5.0
    assert err < 0.05 * change, (err, change, spread)


def test_lattice_interpolation_matches_direct_tracing(scene):
    cam, bg = scene
    ph = gaussian_blob(GRID, sigma=0.008, peak_temperature=500.0, centre=(0.0, 0.0, 0.04))
    fields, kt = _static(ph.refractivity(0.0))
    box = active_box(fields, GRID)
    lat = R.make_lattice(SIZE, 3)
    tr = R.trace_lattice(cam, lat, fields, kt, GRID, frame=0, frame_rate=60.0, n_ambient=N_AMB, clip_box=box)
    ref = R.reference_image(cam, bg, supersample=1)
    _, delta = R.render_image(cam, bg, tr, lat, ref, supersample=1)   # delta at pixel centres
    direct = R.trace_lattice(cam, R.Lattice(1, 0.0, SIZE[0], SIZE[1]), fields, kt, GRID, frame=0,
                             frame_rate=60.0, n_ambient=N_AMB, clip_box=box)
    # the deflection is kinked at the voxel faces (trilinear gradient), 2.7 px apart here, so
    # a 3-px lattice cannot be exact; the error stays far below optical-flow precision
    peak = np.abs(direct.delta).max()
    err = np.abs(delta - direct.delta)
    assert peak > 0.2
    assert err.max() < 0.02 * peak
    assert np.sqrt(np.mean(err[direct.marched] ** 2)) < 0.003 * peak


def test_rolling_shutter_rows_see_their_own_time(scene):
    cam, _ = scene
    cam = cam.with_time_offset(-0.004)
    cam = type(cam)(cam.name, cam.K, cam.dist, cam.R, cam.t, cam.image_size, cam.bg_point, cam.bg_normal,
                    1.0 / (60.0 * 130), cam.time_offset)
    kt = np.linspace(-0.01, 0.05, 7)
    ph = gaussian_blob(GRID, sigma=0.008, peak_temperature=500.0, centre=(0.0, -0.02, 0.04),
                       velocity=(0.0, 2.0, 0.0), knot_times=kt)
    fields = field_stack([ph.knot_refractivity(i) for i in range(len(kt))], GRID)
    lat = R.make_lattice(SIZE, 3)
    rs = R.trace_lattice(cam, lat, fields, kt, GRID, frame=1, frame_rate=60.0, n_ambient=N_AMB)
    _, v = lat.coords()
    t_rows = R.row_times(cam, 1, v, frame_rate=60.0)
    np.testing.assert_allclose(t_rows, -0.004 + 1 / 60.0 + v * cam.line_time)
    for i in (10, 20, 30):
        gs = R.trace_lattice(cam, lat, fields, kt, GRID, frame=None, time=float(t_rows[i]), frame_rate=60.0,
                             n_ambient=N_AMB)
        np.testing.assert_allclose(rs.delta[i], gs.delta[i], atol=1e-12)
        np.testing.assert_allclose(rs.d_out[i], gs.d_out[i], atol=1e-15)
    # and the field really moves between those rows' times
    g0 = R.trace_lattice(cam, lat, fields, kt, GRID, frame=None, time=float(t_rows[10]), frame_rate=60.0,
                         n_ambient=N_AMB)
    assert np.abs(g0.delta[30] - rs.delta[30]).max() > 0.05


def test_flash_band_follows_the_strobe_model(scene):
    cam, _ = scene
    H = cam.height
    lt = 1.0 / (60.0 * 130)
    fr, exposure = 60.0, 1.0 / 120.0
    r_edge = 70
    off = -1 / fr - r_edge * lt - 0.3 * lt
    c = type(cam)(cam.name, cam.K, cam.dist, cam.R, cam.t, cam.image_size, cam.bg_point, cam.bg_normal, lt, off)
    for f in range(3):
        lit = R.flash_rows(c, f, frame_rate=fr, exposure=exposure)
        start = np.array([off + f / fr + r * lt for r in range(H)])
        brute = np.array([s <= 0.0 < s + exposure for s in start])
        np.testing.assert_array_equal(lit, brute)
    lit1 = R.flash_rows(c, 1, frame_rate=fr, exposure=exposure)
    assert np.nonzero(lit1)[0].max() == r_edge           # lower edge of the band = last row with start <= 0
    assert lit1.sum() == min(r_edge + 1, int(np.ceil(exposure / lt)))
    assert not R.flash_rows(c, 2, frame_rate=fr, exposure=exposure).any()
    img = R.apply_flash(np.full((H, 4), 100.0), lit1, 80.0)
    np.testing.assert_array_equal(img[lit1], 180.0)
    np.testing.assert_array_equal(img[~lit1], 100.0)


def test_sensor_noise_and_bit_depth():
    rng = np.random.default_rng(0)
    flat = np.full((200, 200), 100.3)
    a = R.sensor(flat, noise=1.5, bit_depth=8, rng=rng)
    assert a.dtype == np.uint8
    assert abs(a.std() - np.sqrt(1.5**2 + 1 / 12)) < 0.05
    assert abs(a.mean() - 100.3) < 0.05
    b = R.sensor(flat, noise=0.0, bit_depth=16, rng=rng)
    assert b.dtype == np.uint16 and np.all(b == round(100.3 * 257))


def test_cell_average():
    d = np.arange(6 * 9, dtype=float).reshape(6, 9, 1)
    out = R.cell_average(d, FlowGrid((9, 6), 3))
    assert out.shape == (2, 3, 1)
    assert out[0, 0, 0] == d[:3, :3, 0].mean()
