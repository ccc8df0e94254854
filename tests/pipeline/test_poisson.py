"""Poisson integration against analytic solutions (paper eq. 7-8, Appendix)."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.poisson import (
    LaplaceMultigrid,
    PoissonParams,
    assemble,
    diffusion_tensor,
    integrate,
    laplacian_matrix,
    pcg,
    sign_constraint,
)

R_AMB = 2.9e-4


def bump(n, amp=-1e-4, R=0.04):
    """u = amp (1 - rho^2/R^2)^3 inside a ball (C^2, zero outside) and its exact gradient."""
    grid = Grid((-0.05,) * 3, (0.05,) * 3, 0.1 / n)
    X = grid.centres()
    w = np.clip(1 - (X ** 2).sum(-1) / R ** 2, 0, None)
    u = amp * w ** 3
    g = (amp * 3 * w ** 2 * (-2 / R ** 2))[..., None] * X
    hull = (X ** 2).sum(-1) < (R + 2.5 * grid.voxel_size) ** 2
    return grid, u, g, hull


def rel_err(r, u, amp=1e-4):
    return np.sqrt(np.mean((r - R_AMB - u) ** 2)) / amp


@pytest.mark.parametrize("solver", ["mg", "jacobi_cg", "amg"])
@pytest.mark.parametrize("alpha", [1.0, 0.8])
def test_integrates_analytic_gradient_second_order(solver, alpha):
    errs = []
    for n in (16, 32):
        grid, u, g, hull = bump(n)
        r, info = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(alpha=alpha, solver=solver, tol=1e-8))
        assert info.residual <= 1e-8 and info.iterations > 0 and info.n_unknowns == hull.sum()
        np.testing.assert_array_equal(r[~hull], R_AMB)  # Dirichlet outside the hull
        errs.append(rel_err(r, u))
    assert errs[1] < 2e-3
    assert errs[0] / errs[1] > 3.0  # second order: ~4x per halving of h


def test_solvers_agree_and_warm_start():
    grid, u, g, hull = bump(24)
    ra, ia = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(solver="amg", tol=1e-10, sign="none"))
    # sign "none": the solvers' own solutions (the discrete integral of the bump's
    # gradient has a discretisation error of both signs outside its support, which the
    # sign would clip, and the warm start would then start from another field)
    rj, ij = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(solver="jacobi_cg", tol=1e-10, sign="none"))
    np.testing.assert_allclose(ra, rj, atol=1e-12)
    assert ia.iterations < ij.iterations
    rw, iw = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(solver="jacobi_cg", tol=1e-10, sign="none"),
                       x0=rj)
    assert iw.iterations < ij.iterations / 2


def test_zero_gradient_gives_ambient_and_bad_solver_raises():
    grid, u, g, hull = bump(12)
    r, info = integrate(np.zeros_like(g), hull, grid, r_ambient=R_AMB)
    np.testing.assert_array_equal(r, R_AMB)
    with pytest.raises(ValueError):
        integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(solver="nope"))


def test_plain_poisson_is_laplacian_and_symmetric():
    grid, u, g, hull = bump(10)
    pad = ((1, 1),) * 3
    A, f = assemble(np.pad(g, pad + ((0, 0),)), np.pad(hull, pad), grid.voxel_size, params=PoissonParams(alpha=1.0))
    h2 = grid.voxel_size ** 2
    np.testing.assert_allclose(A.diagonal() * h2, 6.0)
    assert abs(A - A.T).max() == 0
    A8, _ = assemble(np.pad(g, pad + ((0, 0),)), np.pad(hull, pad), grid.voxel_size, params=PoissonParams(alpha=0.8))
    assert abs(A8 - A8.T).max() < 1e-9 * abs(A8).max()
    ev = np.linalg.eigvalsh(A8.toarray())
    assert ev.min() > 0


def test_diffusion_tensor_eigenvalues():
    rng = np.random.default_rng(0)
    grid, u, g, hull = bump(16)
    D = diffusion_tensor(g + 1e-4 * rng.standard_normal(g.shape), grid.voxel_size, alpha=0.8, sigma=0.5,
                         k=0.5e-5)
    ev = np.linalg.eigvalsh(D)
    assert ev.min() >= 0.8 - 1e-12 and ev.max() <= 1.0 + 1e-12
    # Paper's k on a coarse grid: anisotropic somewhere (the exponent is ~1 at the edges).
    assert (ev[:, 2] - ev[:, 0]).max() > 0.05
    # k -> 0: exponent -> infinity, D = alpha I.
    D0 = diffusion_tensor(g, grid.voxel_size, alpha=0.8, sigma=0.5, k=1e-30)
    np.testing.assert_allclose(D0, 0.8 * np.broadcast_to(np.eye(3), D0.shape), atol=1e-12)
    # k -> infinity: D = I - (1 - alpha) v v^T with v the dominant structure direction,
    # which for a radial bump is radial: D x_hat = alpha x_hat, D t = t for tangents t.
    Dinf = diffusion_tensor(g, grid.voxel_size, alpha=0.8, sigma=0.5, k=1e30).reshape(g.shape[:3] + (3, 3))
    X = grid.centres()
    rho = np.linalg.norm(X, axis=-1)
    sel = (rho > 0.012) & (rho < 0.03)
    xh = X[sel] / rho[sel, None]
    np.testing.assert_allclose(np.einsum("nij,nj->ni", Dinf[sel], xh), 0.8 * xh, atol=0.01)
    t = np.cross(xh, [0.3, 0.5, 0.81])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", Dinf[sel], t), t, atol=0.01)
    # alpha = 1 is the identity (plain Poisson).
    np.testing.assert_allclose(diffusion_tensor(g, grid.voxel_size, alpha=1.0, sigma=0.5, k=0.5e-5),
                               np.broadcast_to(np.eye(3), D.shape))


def test_diffusion_tensor_inert_shortcut_matches_eigendecomposition():
    """Voxels skipped by the trace bound get exactly alpha I; the rest follow the Appendix."""
    from schlieren.pipeline.poisson.tensor import _range_estimate
    import scipy.ndimage as ndi

    rng = np.random.default_rng(5)
    grid, u, g, hull = bump(16)
    g = g + 1e-4 * rng.standard_normal(g.shape)
    h, alpha, sigma, k, vs = grid.voxel_size, 0.8, 0.5, 3e-4, 255.0
    D = diffusion_tensor(g, h, alpha=alpha, sigma=sigma, k=k, value_scale=vs)
    # Reference: eigendecomposition everywhere (the formula of the Appendix).
    gh = g * h * vs / _range_estimate(g, h)
    M = np.sqrt((gh ** 2).sum(-1)).max()
    J = np.empty(g.shape[:3] + (3, 3))
    for a in range(3):
        for b in range(3):
            J[..., a, b] = ndi.gaussian_filter(gh[..., a] * gh[..., b], sigma, mode="constant")
    lam, V = np.linalg.eigh(J.reshape(-1, 3, 3))
    with np.errstate(divide="ignore", over="ignore"):
        e = [np.where(d > 0, np.exp(-M / (k * d)), 0.0) for d in ((lam[:, 2] - lam[:, 0]) ** 2,
                                                                   (lam[:, 2] - lam[:, 1]) ** 2)]
    lt = np.stack([alpha + (1 - alpha) * e[0], alpha + (1 - alpha) * e[1], np.full(len(lam), alpha)], 1)
    ref = np.einsum("nij,nj,nkj->nik", V, lt, V)
    np.testing.assert_allclose(D, ref, atol=1e-12)
    inert = np.all(D == alpha * np.eye(3), axis=(1, 2))
    assert 0 < inert.sum() < len(D)  # both branches exercised


def test_multigrid_preconditioner_is_symmetric_and_converges():
    rng = np.random.default_rng(3)
    grid, u, g, hull = bump(24)
    mask = np.pad(hull, 1)
    mg = LaplaceMultigrid(mask, grid.voxel_size, coarse_size=200)
    assert mg.levels >= 3
    x, y = rng.standard_normal((2, mg.n))
    assert mg.apply(x) @ y == pytest.approx(x @ mg.apply(y), rel=1e-10)
    assert mg.apply(x) @ x > 0
    # Stationary V-cycle iteration on the masked Laplacian reduces the error fast.
    A = laplacian_matrix(mask, grid.voxel_size)
    f = A @ rng.standard_normal(mg.n)
    sol = np.zeros(mg.n)
    for _ in range(8):
        sol += mg.apply(f - A @ sol)
    assert np.linalg.norm(f - A @ sol) < 1e-2 * np.linalg.norm(f)
    # The assembled plain-Poisson operator is exactly this Laplacian.
    A1, _ = assemble(np.pad(g, ((1, 1),) * 3 + ((0, 0),)), mask, grid.voxel_size, params=PoissonParams(alpha=1.0))
    assert abs(A1 - A).max() < 1e-9 * abs(A).max()


@pytest.mark.parametrize("shape", ["box", "ball"])
def test_multigrid_v_cycle_contracts_as_a_stationary_iteration(shape):
    """The coarse levels keep the fine Dirichlet boundary where it is (Galerkin-style
    face weights): as a stationary iteration the V-cycle contracts every cycle, on a full
    box and on a ball. A plain rediscretisation (boundary moving outwards by half a
    coarse cell per level) over-corrects the smoothest modes and diverged on the box
    (factor 1.9 per cycle), costing CG about half again as many iterations."""
    rng = np.random.default_rng(0)
    if shape == "box":
        mask = np.pad(np.ones((24, 24, 40), bool), 1)
    else:
        mask = np.pad(bump(32)[3], 1)
    L = laplacian_matrix(mask, 0.01)
    mg = LaplaceMultigrid(mask, 0.01, coarse_size=100)
    assert mg.levels >= 4
    f = L @ rng.standard_normal(mg.n)
    x = np.zeros(mg.n)
    norms = [np.linalg.norm(f)]
    for _ in range(12):
        x += mg.apply(f - L @ x)
        norms.append(np.linalg.norm(f - L @ x))
    factors = np.array(norms[1:]) / np.array(norms[:-1])
    assert factors.max() < 0.5, factors  # measured: <= 0.42
    _, it = pcg(L, f, mg.apply, tol=1e-8, max_iter=100)
    assert it <= 12, it  # measured: 10


def test_multigrid_with_natural_faces_matches_assembled_operator():
    """Hull cut by the top and bottom faces: the V-cycle gets the same natural faces as A."""
    rng = np.random.default_rng(4)
    grid, u, g, hull = bump(24)
    hull = hull.copy()
    hull[:, 6:18, 6:18] = True  # a column through the whole box: touches both z faces
    mask = np.pad(hull, 1)
    real = np.pad(np.ones(hull.shape, bool), 1)
    A1, _ = assemble(np.pad(g, ((1, 1),) * 3 + ((0, 0),)), mask, grid.voxel_size,
                     params=PoissonParams(alpha=1.0), real=real)
    L = laplacian_matrix(mask, grid.voxel_size, real)
    assert abs(A1 - L).max() < 1e-9 * abs(L).max()
    assert abs(L - laplacian_matrix(mask, grid.voxel_size)).max() > 0  # the faces matter
    mg = LaplaceMultigrid(mask, grid.voxel_size, coarse_size=200, real=real)
    x, y = rng.standard_normal((2, mg.n))
    assert mg.apply(x) @ y == pytest.approx(x @ mg.apply(y), rel=1e-10)
    assert mg.apply(x) @ x > 0
    f = L @ rng.standard_normal(mg.n)
    its = {}
    for name, m in (("natural", mg), ("dirichlet", LaplaceMultigrid(mask, grid.voxel_size, coarse_size=200))):
        sol, its[name] = pcg(L, f, m.apply, tol=1e-8, max_iter=200)
        assert np.linalg.norm(f - L @ sol) <= 1e-8 * np.linalg.norm(f)
    assert its["natural"] < its["dirichlet"], its


def test_box_boundary_neumann_for_flow_leaving_the_box():
    """A bump cut by the top face: Neumann there recovers it, Dirichlet cannot."""
    grid = Grid((-0.05, -0.05, -0.05), (0.05, 0.05, 0.0125), 0.1 / 32)
    X = grid.centres()
    R, amp = 0.04, -1e-4
    w = np.clip(1 - (X ** 2).sum(-1) / R ** 2, 0, None)
    u = amp * w ** 3
    g = (amp * 3 * w ** 2 * (-2 / R ** 2))[..., None] * X
    hull = (X ** 2).sum(-1) < (R + 2.5 * grid.voxel_size) ** 2
    assert hull[-1].any()  # the flow leaves through the top face
    errs = {}
    for bc in ("neumann", "dirichlet"):
        r, _ = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(alpha=1.0, box_boundary=bc, tol=1e-10))
        errs[bc] = rel_err(r, u)
    assert errs["neumann"] < 2e-3 and errs["dirichlet"] > 5 * errs["neumann"], errs
    # A hull filling the whole box falls back to Dirichlet rather than a singular system.
    r, info = integrate(g, np.ones(grid.shape, bool), grid, r_ambient=R_AMB)
    assert np.isfinite(r).all() and info.residual < 1e-5


def _ring(grid, amp, radius, width):
    """A lobe of the given sign on a spherical shell: the limited views' ringing around a plume."""
    X = grid.centres()
    rho = np.sqrt((X ** 2).sum(-1))
    v = amp * np.exp(-((rho - radius) / width) ** 2)
    g = (v * (-2 * (rho - radius) / width ** 2) / np.maximum(rho, 1e-12))[..., None] * X
    return v, g


def test_sign_constraint_removes_the_opposite_lobe_and_brings_the_estimate_closer():
    """A negative bump (heated gas) plus a positive lobe around it: integrating the sum
    recovers both with sign "none"; the default ("auto") finds the bump's sign and sets
    the lobe's positive voxels to ambient, which is closer to the bump alone."""
    grid, u, g, hull = bump(32)
    lobe, g_lobe = _ring(grid, 2e-6, 0.043, 0.003)  # 2 % of the bump's depth, just outside it
    hull = (grid.centres() ** 2).sum(-1) < 0.048 ** 2
    plain, info0 = integrate(g + g_lobe, hull, grid, r_ambient=R_AMB, params=PoissonParams(tol=1e-10, sign="none"))
    assert info0.sign == "none" and info0.clipped == 0.0
    assert (plain - R_AMB).max() > 0.5 * lobe.max()  # the lobe is there without the sign
    signed, info = integrate(g + g_lobe, hull, grid, r_ambient=R_AMB, params=PoissonParams(tol=1e-10))
    assert info.sign == "negative"
    assert (signed - R_AMB).max() <= 0.0
    np.testing.assert_allclose(info.clipped, np.mean(plain[hull] > R_AMB))
    untouched = plain <= R_AMB
    np.testing.assert_array_equal(signed[untouched], plain[untouched])
    assert rel_err(signed, u) < 0.7 * rel_err(plain, u)


def test_sign_constraint_leaves_two_signed_flows_and_follows_an_explicit_sign():
    grid, u, g, hull = bump(24)
    r = R_AMB + u
    both = r.copy()
    shift = grid.shape[0] // 4
    both -= 0.8 * np.roll(u, shift, axis=0)  # a positive bump holding 40 % of |r - r_amb|
    full = np.ones(grid.shape, bool)
    out, applied, clipped = sign_constraint(both, full, R_AMB)
    assert applied == "none" and clipped == 0.0 and out is both
    out, applied, clipped = sign_constraint(both, full, R_AMB, sign="negative")
    assert applied == "negative" and (out - R_AMB).max() <= 0 and clipped > 0
    out, applied, _ = sign_constraint(R_AMB - u + 1e-7 * (u < -1e-6), full, R_AMB)  # a denser (positive) flow
    assert applied == "positive" and (out - R_AMB).min() >= 0
    broken = r + 1e-7 * (np.abs(u) < 1e-9)  # a negative flow with a positive margin ...
    broken[0, 0, 0] = np.nan                 # ... and a voxel a failed step left undefined
    out, applied, clipped = sign_constraint(broken, full, R_AMB)
    assert applied == "negative" and np.isnan(out[0, 0, 0])  # left as it is, not made ambient
    assert np.nanmax(out - R_AMB) <= 0 and clipped > 0
    with pytest.raises(ValueError, match="sign must be one of"):
        sign_constraint(both, full, R_AMB, sign="down")
