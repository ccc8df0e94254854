"""The shared conjugate-gradient loop: against direct solves, step by step, its stop reasons."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from schlieren.pipeline.linalg import CGLSVectors, ConjugateGradient, SerialVectors, cgls, pcg


def _spd(n, rng):
    B = rng.standard_normal((n, n))
    return sp.csr_matrix(B @ B.T + n * np.eye(n))


def test_pcg_solves_an_spd_system_to_its_tolerance():
    rng = np.random.default_rng(0)
    A = _spd(40, rng)
    f = rng.standard_normal(40)
    exact = np.linalg.solve(A.toarray(), f)
    dinv = 1.0 / A.diagonal()
    u, it = pcg(A, f, lambda v: dinv * v, tol=1e-10, max_iter=200)
    assert 0 < it <= 40 and np.linalg.norm(f - A @ u) <= 1e-10 * np.linalg.norm(f)
    np.testing.assert_allclose(u, exact, rtol=1e-8, atol=1e-12)
    # a warm start at the solution needs no iteration; a zero right-hand side neither
    u0, it0 = pcg(A, f, lambda v: v, x0=exact, tol=1e-8, max_iter=50)
    assert it0 == 0 and np.array_equal(u0, exact)
    z, itz = pcg(A, np.zeros(40), lambda v: v, tol=1e-8, max_iter=50)
    assert itz == 0 and not z.any()


def test_step_wise_run_equals_run_and_reports_each_step():
    rng = np.random.default_rng(1)
    A = _spd(30, rng)
    f = rng.standard_normal(30)
    seen = []
    res = ConjugateGradient(SerialVectors(A, f, lambda v: v, tol=1e-9), max_iter=100).run(
        lambda s: seen.append((s.iterations, s.vectors.solution().copy())))
    assert res.stop_reason == "tol" and res.iterations == len(seen) and seen[-1][0] == res.iterations
    assert res.residual[0] <= (1e-9 * np.linalg.norm(f)) ** 2
    errs = [np.linalg.norm(A @ x - f) for _, x in seen]
    assert errs[-1] < 1e-3 * errs[0]
    cg = ConjugateGradient(SerialVectors(A, f, lambda v: v, tol=1e-9), max_iter=100).setup()
    while cg.step():
        pass
    assert cg.iterations == res.iterations and np.array_equal(cg.vectors.x, res.x)
    capped = ConjugateGradient(SerialVectors(A, f, lambda v: v, tol=1e-9), max_iter=3).run()
    assert capped.stop_reason == "max_iter" and capped.iterations == 3
    np.testing.assert_array_equal(capped.x, seen[2][1])


def test_no_positive_curvature_is_a_breakdown():
    """An operator with p . A p <= 0 (here A = 0) stops the run without a step."""
    f = np.ones(5)
    res = ConjugateGradient(SerialVectors(sp.csr_matrix((5, 5)), f, lambda v: v, tol=1e-8), max_iter=10).run()
    assert res.stop_reason == "breakdown" and res.iterations == 0 and not res.x.any()


def test_cgls_columns_are_independent_least_squares_solves():
    """k columns at once give each column's own least-squares solution (numpy lstsq),
    and the discrepancy stop ends the run at the first iterate whose data residual is small enough."""
    rng = np.random.default_rng(2)
    A = rng.standard_normal((50, 12))
    B = rng.standard_normal((50, 3))
    B[:, 2] = 0.0  # a zero column is converged from the start
    res = cgls(lambda x: [A @ x], lambda r: A.T @ r[0], [B], np.zeros((12, 3)), max_iter=100, tol=1e-12)
    want = np.linalg.lstsq(A, B, rcond=None)[0]
    np.testing.assert_allclose(res.x, want, atol=1e-10)
    assert res.stop_reason == "tol" and not res.x[:, 2].any()
    np.testing.assert_allclose(res.data_residual, np.linalg.norm(A @ want - B, axis=0), rtol=1e-8)
    stop = 1.05 * res.data_residual
    early = cgls(lambda x: [A @ x], lambda r: A.T @ r[0], [B], np.zeros((12, 3)), max_iter=100, tol=1e-12,
                 stop_data_norm=stop)
    assert early.stop_reason == "discrepancy" and early.iterations < res.iterations
    assert np.all(early.data_residual <= stop)
    vec = CGLSVectors(lambda x: [A @ x], lambda r: A.T @ r[0], [B], np.zeros((12, 3)), tol=1e-12,
                      stop_data_norm=stop)
    cg = ConjugateGradient(vec, max_iter=100).setup()
    steps = 0
    while vec.early_stop() is None and cg.step():
        steps += 1
    assert steps == early.iterations and np.array_equal(vec.x, early.x)
