"""Re-projection residuals against closed-form line integrals of a Gaussian blob."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid
from schlieren.pipeline.residuals import line_integrals, predict_flows, residual_stats
from schlieren.pipeline.tomography import TomoParams, build_geometry, rhs_from_flows

N_AMB = 1.00029
AMP = 1.0e-4    # refractivity deficit at the blob centre
SIGMA = 0.012   # metres


def look_at_camera(eye, target, *, f=900.0, size=(120, 90), bg_distance=1.5, name="cam", dist=None):
    eye = np.asarray(eye, float)
    target = np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image down = -world up
    R = np.stack([x, y, z])
    t = -R @ eye
    W, H = size
    K = [[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]]
    point = target + bg_distance * z
    return Camera(name, K, np.zeros(5) if dist is None else dist, R, t, size, point, -z)


def blob(grid, centre):
    X = grid.centres()
    d = X - np.asarray(centre)
    g = AMP * np.exp(-np.sum(d ** 2, axis=-1) / (2 * SIGMA ** 2))
    r = (N_AMB - 1.0) - g
    grad = d / SIGMA ** 2 * g[..., None]  # grad r = -grad g = +(x - c)/s^2 g
    return r, grad


def analytic_integral(origin, dirs, centre):
    """Closed form of integral grad r ds for the blob along straight rays (unit dirs)."""
    oc = np.asarray(centre) - origin
    tau = oc @ dirs.T
    closest = origin + tau[:, None] * dirs
    b = closest - np.asarray(centre)
    b2 = np.sum(b ** 2, axis=-1)
    return AMP * np.sqrt(2 * np.pi) / SIGMA * b * np.exp(-b2 / (2 * SIGMA ** 2))[:, None]


@pytest.fixture(scope="module")
def setup():
    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.0025)  # 40^3
    cam = look_at_camera([0.03, -0.6, 0.01], [0.0, 0.0, 0.0])
    fg = FlowGrid(cam.image_size, 2)
    geom = build_geometry([cam], grid, fg)
    return grid, cam, fg, geom


def _integral_error(cam, fg, h, centre, prune=0.0):
    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), h)
    geom = build_geometry([cam], grid, fg, params=TomoParams(prune=prune))
    _, grad = blob(grid, centre)
    got = line_integrals(geom, grad)[0].reshape(-1, 3)
    c, d = cam.rays(fg.pixel_centres().reshape(-1, 2))
    want = analytic_integral(c, d, centre)
    return np.abs(got - want).max() / np.abs(want).max()


def test_line_integrals_match_closed_form(setup):
    """Max error relative to the peak: a few % at sigma = 4.8 voxels, second-order in h (the
    basis's own quadrature, unpruned); the default pruned projection (``prune`` 0.05) stays
    within the same few %."""
    _, cam, fg, _ = setup
    centre = (0.004, 0.002, -0.003)
    fine = _integral_error(cam, fg, 0.0025, centre)
    coarse = _integral_error(cam, fg, 0.005, centre)
    assert fine < 0.035, fine
    assert coarse / fine > 3.0, (coarse, fine)  # ~4 for second order
    assert _integral_error(cam, fg, 0.0025, centre, prune=TomoParams().prune) < 0.035


def test_zero_gradient_predicts_zero_deflection(setup):
    grid, cam, fg, geom = setup
    delta = predict_flows(geom, [cam], np.zeros(grid.shape + (3,)), n_ambient=N_AMB)
    assert delta.shape == (1,) + fg.shape + (2,)
    assert np.all(delta == 0.0)


def test_prediction_inverts_the_tomography_right_hand_side(setup):
    """The tomography turns flows into n_amb (d_out - d_in); feeding it the predicted flows
    must give back the line integrals S g the prediction started from."""
    grid, cam, fg, geom = setup
    _, grad = blob(grid, (0.003, -0.002, 0.004))
    I = line_integrals(geom, grad)
    rhs = rhs_from_flows(geom, predict_flows(geom, [cam], grad, n_ambient=N_AMB), n_ambient=N_AMB)
    # compare the components across the ray (the along-ray part is second order)
    perp = lambda v: v - np.sum(v * geom.d_in, axis=-1, keepdims=True) * geom.d_in
    err = np.abs(perp(rhs) - perp(I)).max() / np.abs(I).max()
    assert err < 1e-4, err


def test_prediction_round_trip_with_lens_distortion():
    """Same round trip through a distorted camera (projection with distortion here, the
    tomography's linearised undistortion there)."""
    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.005)
    cam = look_at_camera([0.2, -0.55, 0.05], [0.0, 0.0, 0.0], dist=[-0.25, 0.08, 0.001, -0.002, 0.0])
    geom = build_geometry([cam], grid, FlowGrid(cam.image_size, 3))
    _, grad = blob(grid, (0.01, 0.0, -0.005))
    I = line_integrals(geom, grad)
    flows = predict_flows(geom, [cam], grad, n_ambient=N_AMB)
    assert np.nanmax(np.abs(flows)) > 0.05
    rhs = rhs_from_flows(geom, flows, n_ambient=N_AMB)
    perp = lambda v: v - np.sum(v * geom.d_in, axis=-1, keepdims=True) * geom.d_in
    err = np.abs(perp(rhs) - perp(I)).max() / np.abs(I).max()
    assert err < 1e-4, err


def test_predicted_deflection_small_angle_magnitude_and_sign(setup):
    """A ray passing the hot blob bends away from it by eps = I / n; on the image the shift is
    f * eps * L / Z (L = refraction point to background, Z = background depth)."""
    grid, cam, fg, geom = setup
    centre = (0.0, 0.0, 0.0)
    _, grad = blob(grid, centre)
    delta = predict_flows(geom, [cam], grad, n_ambient=N_AMB)[0]
    uv = fg.pixel_centres()
    c, d = cam.rays(uv.reshape(-1, 2))
    I = analytic_integral(c, d, centre).reshape(uv.shape[:2] + (3,))
    # pick the pixel with the largest predicted deflection: it must point away from the blob
    mag = np.hypot(delta[..., 0], delta[..., 1])
    i, j = np.unravel_index(np.argmax(mag), mag.shape)
    blob_uv = cam.project(np.asarray(centre))
    outward = uv[i, j] - blob_uv
    assert np.dot(delta[i, j], outward) > 0.9 * np.linalg.norm(delta[i, j]) * np.linalg.norm(outward)
    # magnitude: small-angle model at that pixel
    ray = d.reshape(uv.shape[:2] + (3,))[i, j]
    eps = I[i, j] - (I[i, j] @ ray) * ray
    eps = eps / N_AMB
    X_c = c + ((np.asarray(centre) - c) @ ray) * ray
    B = cam.intersect_background(X_c, ray)
    L = np.linalg.norm(B - X_c)
    Z = (cam.R @ B + cam.t)[2]
    f = cam.K[0, 0]
    expected = f * np.linalg.norm(eps) * L / Z  # paraxial: ray ~ optical axis
    assert mag[i, j] == pytest.approx(expected, rel=0.05)
    assert mag[i, j] > 0.05  # a measurable BOS deflection, not a vanishing one


def test_residual_stats_recover_known_noise():
    rng = np.random.default_rng(3)
    pred = rng.normal(0, 0.3, (20, 30, 2))
    noise = rng.normal(0, 0.05, (20, 30, 2))
    meas = pred + noise
    mask = np.zeros((20, 30), bool)
    mask[5:10, 5:20] = True
    st = residual_stats(meas, pred, mask)
    assert st.rms == pytest.approx(np.sqrt(np.mean(np.sum(noise ** 2, -1))), rel=1e-12)
    assert st.rms_in_mask == pytest.approx(np.sqrt(np.mean(np.sum(noise[mask] ** 2, -1))), rel=1e-12)
    assert st.rms_measured == pytest.approx(np.sqrt(np.mean(np.sum(meas ** 2, -1))), rel=1e-12)
    assert st.count == 600
    meas[0, 0] = np.nan
    assert residual_stats(meas, pred).count == 599
