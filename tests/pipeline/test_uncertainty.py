"""The uncertainty per voxel (pipeline/uncertainty) against closed forms and known noise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from schlieren.pipeline import uncertainty as unc
from schlieren.pipeline.geometry import Grid, Medium
from schlieren.pipeline.poisson import PoissonParams, integrate
from schlieren.pipeline.tomography import TomoParams
from schlieren.pipeline.tomography.regularisers import curl_normal, regulariser, regulariser_normal
from schlieren.pipeline.tomography.restriction import RestrictedOperator
from schlieren.pipeline.tomography.solve import FrameSystem


def _system(rng, shape=(5, 5, 5), m=700, density=0.03):
    """A small linear-Gaussian tomography problem: a random sparse projection of a full
    basis set (an underdetermined direction or two left to the priors)."""
    inset = np.ones(shape, bool)
    n = int(inset.sum())
    S = sp.random(m, n, density=density, random_state=np.random.RandomState(rng.integers(1 << 30)),
                  data_rvs=lambda k: rng.uniform(0.2, 1.0, k), format="csr", dtype=np.float32)
    S.sort_indices()
    op = RestrictedOperator(S.indptr.astype(np.int64), S.indices.astype(np.int32), S.data.astype(np.float32), n,
                            np.arange(m))
    sys_ = FrameSystem(op=op, inset=inset, LtL=regulariser(inset, "second-differences"), CtC=curl_normal(inset))
    return sys_, S.astype(np.float64)


def _dense_hessian(sys_, S, params: TomoParams):
    """``H`` of the normal equations over the (3 n) unknowns ``3 i + c`` (the curl matrix's numbering)."""
    n = sys_.n
    mean_diag = float(np.mean(S.multiply(S).sum(axis=0)))
    StS = (S.T @ S).toarray()
    R = regulariser_normal(sys_.inset, "second-differences").toarray()
    H = np.kron(StS + params.reg_weight * mean_diag * R, np.eye(3))
    C = sys_.CtC.curl_matrix().toarray()
    return H + params.curl_weight * mean_diag * C.T @ C, np.kron(StS, np.eye(3))


def _ensemble_sd(sys_, params, sigma, rng, *, samples, prior):
    acc = np.zeros((sys_.n, 3))
    for _ in range(samples):
        e = rng.normal(size=(sys_.op.m, 3)) * sigma
        extra = unc.prior_perturbation(sys_, params, np.full(3, sigma), rng) if prior else None
        x, _ = unc.perturbation_solve(sys_, e, params, extra=extra)
        acc += x * x
    return np.sqrt(acc / samples).reshape(-1)  # (3 n,) in the numbering 3 i + c


@pytest.fixture
def one_thread():
    """Serial numba kernels (as on a worker): the tiny solves' thread start-ups cost 20x their work."""
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(before)


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(4)
    sys_, S = _system(rng)
    params = TomoParams(reg_weight=0.05, curl_weight=0.5, max_iter=400, tol=1e-6)
    H, StS = _dense_hessian(sys_, S, params)
    return sys_, params, H, StS


def test_noise_ensemble_recovers_the_estimates_closed_form_spread(problem, one_thread):
    """White ray noise sigma: the converged estimate's covariance is H^-1 S^T S H^-1 sigma^2
    (dense inverse); 400 perturbation solves recover every unknown's sd within 20 %."""
    sys_, params, H, StS = problem
    sigma = 0.3
    Hi = np.linalg.inv(H)
    exact = np.sqrt(np.diag(Hi @ StS @ Hi)) * sigma
    sd = _ensemble_sd(sys_, params, sigma, np.random.default_rng(1), samples=400, prior=False)
    ratio = sd / exact
    assert np.all(np.abs(ratio - 1) < 0.2), (ratio.min(), ratio.max())
    assert abs(np.median(ratio) - 1) < 0.05


def test_prior_samples_recover_the_posterior_sd_of_the_linear_gaussian_model(problem, one_thread):
    """Perturb-then-optimise with the priors perturbed too: the samples' sd is the posterior's,
    sqrt(diag(sigma^2 H^-1)) (dense inverse), within 20 % for every unknown."""
    sys_, params, H, _ = problem
    sigma = 0.3
    exact = np.sqrt(np.diag(np.linalg.inv(H))) * sigma
    sd = _ensemble_sd(sys_, params, sigma, np.random.default_rng(2), samples=400, prior=True)
    ratio = sd / exact
    assert np.all(np.abs(ratio - 1) < 0.2), (ratio.min(), ratio.max())
    assert abs(np.median(ratio) - 1) < 0.05
    # the posterior is wider than the noise's spread alone (the priors' share)
    noise_only = _ensemble_sd(sys_, params, sigma, np.random.default_rng(3), samples=100, prior=False)
    assert np.median(sd / noise_only) > 1.05


def test_bias_solve_is_the_regularisations_closed_form_bias(problem, one_thread):
    """Tikhonov with the curl term: the resolution operator is K = H^-1 S^T S (dense inverse), so
    the bias of the estimate of a field x is (K - I) x; one more regularised solve of x's own
    projection (the bias term's kernel) recovers it within 20 % for every sizeable unknown."""
    sys_, params, H, StS = problem
    rng = np.random.default_rng(5)
    x = rng.normal(size=(sys_.n, 3))
    exact = (np.linalg.solve(H, StS @ x.reshape(-1)) - x.reshape(-1))
    d, it = unc.bias_solve(sys_, x, params)
    d = d.reshape(-1)
    assert it > 0
    assert np.linalg.norm(d - exact) < 0.02 * np.linalg.norm(exact)
    big = np.abs(exact) > 0.1 * np.abs(exact).max()
    ratio = d[big] / exact[big]
    assert np.all(np.abs(ratio - 1) < 0.2), (ratio.min(), ratio.max())
    # on an estimate x_hat = K x the term is (K - I) K x: the same shape, never larger than the bias
    x_hat = np.linalg.solve(H, StS @ x.reshape(-1)).reshape(-1, 3)
    d_hat, _ = unc.bias_solve(sys_, x_hat, params)
    assert np.linalg.norm(d_hat) <= np.linalg.norm(exact)


def test_resolution_loss_vanishes_without_a_prior_and_grows_with_its_weight(problem, one_thread):
    """An overdetermined full-rank problem: without priors K = I and a smooth field loses nothing;
    the loss grows with the prior's weight towards the whole field."""
    sys_, _, _, _ = problem
    grid = Grid((0.0, 0.0, 0.0), (0.005, 0.005, 0.005), 0.001)
    integ = unc.LinearisedIntegration(sys_.inset, grid, tol=1e-8)
    losses = []
    for w in (1e-9, 0.05, 5.0):
        p = TomoParams(reg_weight=w, curl_weight=0.0, max_iter=600, tol=1e-9)
        res = unc.resolution_loss(sys_, integ, p, h=grid.voxel_size, width=1.5, probes=3, smoothing=0.0,
                                  rng=np.random.default_rng(6))
        assert res.probes == 3 and len(res.iterations) == 3
        losses.append(float(np.sqrt(np.mean(res.loss ** 2))))
    assert losses[0] < 0.02, losses
    assert losses[0] < losses[1] < losses[2] < 1.01, losses
    assert losses[2] > 0.3, losses


def test_correlated_flow_noise_has_the_window_correlation_and_level():
    """Unit white noise filtered by a Gaussian of s cells: RMS as asked, correlation
    exp(-d^2 / (4 s^2)) at lag d; the noise level is measured back from the quiet cells."""
    rng = np.random.default_rng(0)
    level = np.array([[0.01, 0.02], [0.03, 0.005]])
    n = unc.correlated_flow_noise(rng, (2, 400, 500), [1.0, 1.5], level)
    assert n.shape == (2, 400, 500, 2) and n.dtype == np.float32
    np.testing.assert_allclose(n.reshape(2, -1, 2).std(axis=1), level, rtol=0.05)
    quiet = np.ones((2, 400, 500), bool)
    np.testing.assert_allclose(unc.flow_noise_level(n, quiet), level, rtol=0.05)
    for c, s in enumerate((1.0, 1.5)):
        corr = unc.noise_correlation(n[c:c + 1], quiet[c:c + 1], lags=(1, 2))
        np.testing.assert_allclose(corr, np.exp(-np.array([1.0, 4.0]) / (4 * s * s)), atol=0.03)


def test_flow_noise_level_ignores_masked_cells_and_fills_a_camera_without_quiet_cells():
    rng = np.random.default_rng(1)
    flows = rng.normal(size=(3, 60, 80, 2)) * 0.01
    flows[:, 20:40, 20:60] += 5.0  # the flow itself, inside the masks
    quiet = np.ones((3, 60, 80), bool)
    quiet[:, 20:40, 20:60] = False
    quiet[2] = False  # a camera that sees flow everywhere
    level = unc.flow_noise_level(flows, quiet)
    np.testing.assert_allclose(level[:2], 0.01, rtol=0.1)
    np.testing.assert_allclose(level[2], np.median(level[:2], axis=0))


def _blob(grid: Grid, centre, width):
    z, y, x = np.meshgrid(*[a for a in grid.axes()[::-1]], indexing="ij")
    return np.exp(-(((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) / (2 * width ** 2)))


def _grad(r, h):
    gz, gy, gx = np.gradient(r, h)
    return np.stack([gx, gy, gz], axis=-1)


GRID = Grid((-0.02, -0.02, 0.0), (0.02, 0.02, 0.04), 0.001)


def test_linearised_integration_is_the_integration_without_its_sign_constraint():
    r = -1e-5 * _blob(GRID, (0.0, 0.0, 0.02), 0.005)
    hull = _blob(GRID, (0.0, 0.0, 0.02), 0.005) > 1e-3
    g = _grad(r, GRID.voxel_size)
    li = unc.LinearisedIntegration(hull, GRID, gradient=g, tol=1e-10)
    ref, _ = integrate(g, hull, GRID, r_ambient=0.0, params=PoissonParams(sign="none", tol=1e-10))
    np.testing.assert_allclose(li(g), ref, atol=1e-12 + 1e-6 * np.abs(ref).max())
    np.testing.assert_allclose(li(2 * g) - li(g), li(g), atol=1e-6 * np.abs(ref).max())  # linear


def test_boundary_sensitivity_vanishes_inside_a_hull_that_holds_the_flow_and_not_where_it_cuts_it():
    r = -1e-5 * _blob(GRID, (0.0, 0.0, 0.02), 0.004)
    g = _grad(r, GRID.voxel_size)
    z, y, x = np.meshgrid(*[a for a in GRID.axes()[::-1]], indexing="ij")
    wide = (np.hypot(x, y) < 0.017) & (np.abs(z - 0.02) < 0.017)  # holds the blob
    li = unc.LinearisedIntegration(wide, GRID, gradient=g, tol=1e-10)
    d_wide = unc.boundary_sensitivity(g, li, GRID)
    cut = wide & (x < 0.001)  # cuts the blob through its centre
    li_cut = unc.LinearisedIntegration(cut, GRID, gradient=g, tol=1e-10)
    d_cut = unc.boundary_sensitivity(g, li_cut, GRID)
    peak = 1e-5
    assert np.abs(d_wide).max() < 0.02 * peak
    assert np.abs(d_cut[cut]).max() > 0.3 * peak
    # the natural integration recovers the cut blob itself (its constant from the quiet surface)
    rn = unc.natural_integration(g, cut, GRID)
    assert np.abs(rn - r)[cut].max() < 0.05 * peak


def test_curvature_rms_of_a_quadratic_field():
    shape = (12, 14, 16)
    hull = np.zeros(shape, bool)
    hull[2:-2, 2:-2, 2:-2] = True
    x = np.arange(shape[2], dtype=float)
    r = np.broadcast_to(0.5 * x ** 2 * 1e-6, shape)  # h^2 lap = 1e-6 in grid units
    c = unc.curvature_rms(r, hull, smoothing=1.0)
    np.testing.assert_allclose(c[hull], 1e-6, rtol=1e-9)
    assert np.all(c[~hull] == 0)


def test_masked_mean_keeps_a_constant_and_is_zero_outside():
    mask = np.zeros((10, 10, 10), bool)
    mask[2:7, 3:9, 1:5] = True
    v = np.where(mask, 3.0, 100.0)
    out = unc.masked_mean(v, mask, 2.0)
    np.testing.assert_allclose(out[mask], 3.0)
    assert np.all(out[~mask] == 0)


def test_derived_sigmas_are_the_first_order_propagation():
    med = Medium()
    r = np.array([2.0e-4, 2.9e-4, 1.5e-4, -1e-6])
    s = np.full(4, 1e-7)
    T = med.T_ambient * med.refractivity_ambient / r
    dT = (med.T_ambient * med.refractivity_ambient / (r - 1e-9) - med.T_ambient * med.refractivity_ambient / (r + 1e-9)) / 2e-9
    got = unc.temperature_sigma(r, s, med)
    np.testing.assert_allclose(got[:3], np.abs(dT[:3]) * 1e-7, rtol=1e-5)
    assert np.isnan(got[3]) and np.all(T[:3] > 0)
    np.testing.assert_allclose(unc.density_sigma(s, med), s / med.gladstone_dale)


def test_params_round_trip_through_the_run_configuration():
    from schlieren.pipeline.stages import RunConfig, config_from_dict, config_to_dict, run_stages

    cfg = config_from_dict({"uncertainty": {"enabled": True, "samples": 3}})
    assert cfg.uncertainty == dataclasses.replace(unc.UncertaintyParams(), enabled=True, samples=3)
    assert config_from_dict(config_to_dict(cfg)) == cfg
    assert "uncertainty" in [s.name for s in run_stages(cfg)]
    assert "uncertainty" not in [s.name for s in run_stages(RunConfig())]
