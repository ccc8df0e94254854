"""Curved-ray tracer against closed forms (paper eq. 1-3)."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.synthetic.tracer import active_box, field_stack, trace_rays, trace_rays_timed

R_AMB = 2.9e-4
N_AMB = 1.0 + R_AMB


def _blob(h=0.001, L=0.06, s=0.012, A=-1e-4):
    g = Grid((-L, -L, -L), (L, L, L), h)
    x, y, z = g.axes()
    R2 = x[None, None, :] ** 2 + y[None, :, None] ** 2 + z[:, None, None] ** 2
    return g, R_AMB + A * np.exp(-R2 / (2 * s * s))


def test_gaussian_blob_weak_deflection_matches_closed_form():
    # n - 1 = r_amb + A exp(-rho^2 / (2 s^2)); a ray along x at impact parameter b (along y):
    # Delta d_y = int dn/dy dx = -A b / s^2 exp(-b^2/(2 s^2)) * sqrt(2 pi) s
    # and the exit direction's y component is Delta d_y / n_amb (d = n * unit direction).
    s, A = 0.012, -1e-4
    g, r = _blob(s=s, A=A)
    b = np.linspace(0.25 * s, 2.0 * s, 8)
    orig = np.stack([np.full_like(b, -1.0), b, np.zeros_like(b)], axis=1)
    d = np.tile([1.0, 0.0, 0.0], (b.size, 1))
    res = trace_rays(r, g, orig, d, n_ambient=N_AMB)
    expected = -np.sqrt(2 * np.pi) * A * b / s * np.exp(-b**2 / (2 * s * s)) / N_AMB
    assert res.hit.all()
    np.testing.assert_allclose(res.d_out[:, 1], expected, rtol=0.01)
    # hot blob (A < 0): rays bend away from the centre
    assert np.all(res.d_out[:, 1] > 0)
    np.testing.assert_allclose(np.linalg.norm(res.d_out, axis=1), 1.0, atol=1e-12)
    # the exit point is on the far face of the box
    np.testing.assert_allclose(res.exit_point[:, 0], g.vmax[0], atol=1e-9)


def test_step_size_convergence():
    # A strong field so that the discretisation error is visible above round-off. The
    # interpolated gradient is continuous but kinked at the cell faces, so RK4 converges with
    # order about 1-3 on it (order 4 only for smooth integrands); the median error must fall
    # with every halving of the step, with an overall order above 1, and be negligible
    # (relative 1e-5 of the deflection) at the default step.
    g, r = _blob(h=0.002, A=-0.01)
    rng = np.random.default_rng(0)
    n = 200
    orig = np.stack([np.full(n, -1.0), rng.uniform(-0.02, 0.02, n), rng.uniform(-0.02, 0.02, n)], axis=1)
    d = np.stack([np.ones(n), rng.uniform(-0.05, 0.05, n), rng.uniform(-0.05, 0.05, n)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = trace_rays(r, g, orig, d, n_ambient=N_AMB, step=g.voxel_size / 256)
    errs = []
    for k in (1, 2, 4, 8):
        res = trace_rays(r, g, orig, d, n_ambient=N_AMB, step=g.voxel_size / k)
        errs.append(np.median(np.linalg.norm(res.d_out - ref.d_out, axis=1)))
    errs = np.array(errs)
    assert np.all(errs[1:] < errs[:-1] / 1.5), errs
    order = np.log2(errs[0] / errs[-1]) / 3
    assert order > 1.0, (errs, order)
    deflection = np.median(np.linalg.norm(ref.d_out - d, axis=1))
    assert errs[2] < 1e-5 * deflection  # default step (voxel / 4)


def test_uniform_gradient_gives_exact_linear_deflection():
    # r = r0 + G x inside the box: d_x grows by exactly G * (path length); for a ray along y
    # at x = 0 the path length is the box depth.
    h, L, G = 0.002, 0.04, 2e-3
    g = Grid((-L, -L, -L), (L, L, L), h)
    x, _, _ = g.axes()
    r = R_AMB + G * np.broadcast_to(x[None, None, :], g.shape)
    res = trace_rays(r, g, np.array([[0.0, -1.0, 0.003]]), np.array([[0.0, 1.0, 0.0]]), n_ambient=N_AMB)
    n_exit = 1.0 + R_AMB + G * res.exit_point[0, 0]
    dx = res.d_out[0, 0] * n_exit
    assert dx == pytest.approx(G * 2 * L, rel=2e-3)


def test_rays_missing_the_box_or_ambient_field_are_straight():
    g, r = _blob()
    orig = np.array([[-1.0, 0.5, 0.0], [-1.0, 0.0, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    res = trace_rays(r, g, orig, d, n_ambient=N_AMB)
    assert not res.hit[0] and res.hit[1]
    np.testing.assert_array_equal(res.d_out[0], d[0])
    flat = np.full(g.shape, R_AMB)
    res = trace_rays(flat, g, orig, d, n_ambient=N_AMB)
    np.testing.assert_array_equal(res.d_out, d)
    lo, hi = active_box(field_stack([flat], g), g)
    assert np.all(lo > hi)


def test_time_knots_blend_linearly():
    # a field that is r0 at knot 0 and r1 at knot 1: a ray at the mid time sees the mean.
    g, r1 = _blob(h=0.002, A=-2e-4)
    r0 = np.full(g.shape, R_AMB)
    fields = field_stack([r0, r1], g)
    orig = np.array([[-1.0, 0.01, 0.0]])
    d = np.array([[1.0, 0.0, 0.0]])
    mid = trace_rays_timed(fields, np.array([0.0, 1.0]), g, orig, d, np.array([0.5]), n_ambient=N_AMB)
    half = trace_rays(0.5 * (r0 + r1), g, orig, d, n_ambient=N_AMB)
    np.testing.assert_allclose(mid.d_out, half.d_out, atol=1e-12)


def test_agrees_with_an_adaptive_high_order_integrator():
    # The same ODE (eq. 2) on the same trilinear field, integrated by scipy's DOP853 with tight
    # tolerances (an independent integrator), for a strongly deflected ray.
    from scipy.integrate import solve_ivp

    g, r = _blob(h=0.002, A=-0.01)
    F = field_stack([r], g)[0].astype(np.float64)
    nz, ny, nx = g.shape
    hi = np.array([nx - 1, ny - 1, nz - 1])

    def sample(p):
        f = np.clip((p - g.origin) / g.voxel_size, 0, hi)
        i = np.minimum(f.astype(int), hi - 1)
        a = f - i
        out = np.zeros(4)
        for cz in (0, 1):
            for cy in (0, 1):
                for cx in (0, 1):
                    w = (a[2] if cz else 1 - a[2]) * (a[1] if cy else 1 - a[1]) * (a[0] if cx else 1 - a[0])
                    out += w * F[i[2] + cz, i[1] + cy, i[0] + cx]
        return out

    L = g.vmax[0]
    p0 = np.array([-L, 0.007, -0.004])
    d0 = np.array([1.0, 0.0, 0.0])

    def rhs(s, Y):
        q = sample(Y[:3])
        return np.concatenate([Y[3:] / (1 + q[0]), q[1:]])

    def leave(s, Y):
        return Y[0] - L

    leave.terminal = True
    sol = solve_ivp(rhs, [0, 1.0], np.concatenate([p0, (1 + sample(p0)[0]) * d0]), method="DOP853",
                    rtol=1e-13, atol=1e-16, events=leave, max_step=g.voxel_size / 8)
    v = sol.y[3:, -1]
    d_ref = v / np.linalg.norm(v)
    res = trace_rays(r, g, np.array([[-1.0, p0[1], p0[2]]]), d0[None], n_ambient=N_AMB)
    deflection = np.linalg.norm(d_ref - d0)
    assert deflection > 0.01
    assert np.linalg.norm(res.d_out[0] - d_ref) < 1e-6 * deflection
    np.testing.assert_allclose(res.exit_point[0], sol.y[:3, -1], atol=1e-8)
