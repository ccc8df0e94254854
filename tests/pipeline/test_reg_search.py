"""The bracketing regularisation search and the solve state it carries between weights."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.tomography import MeasurementBlur, TomoParams, build_geometry
from schlieren.pipeline.tomography.reg_choice import choose_reg_weight, rhs_noise
from schlieren.pipeline.tomography.solve import _solve_restricted, prepare_frame

from test_tomography import blob_field, ring_cameras


@pytest.fixture(scope="module")
def blob():
    grid = Grid((-0.04, -0.04, 0.0), (0.04, 0.04, 0.08), 0.0025)  # 32^3
    cams = ring_cameras(8, grid, image_size=(144, 108))
    geom = build_geometry(cams, grid, FlowGrid((144, 108), 2), params=TomoParams())
    centre, sigma, amp = np.array([0.001, -0.002, 0.04]), 0.007, -8e-5
    _, grad = blob_field(grid, centre, sigma, amp)
    clean = np.stack([geom.S @ grad[..., k].ravel() for k in range(3)], axis=1).reshape(*geom.flow_shape, 3)
    sig = 0.03 * np.sqrt(np.mean(clean[np.abs(clean).sum(-1) > 1e-3 * np.abs(clean).max()] ** 2))
    rhs = clean + np.random.default_rng(7).normal(scale=sig, size=clean.shape)
    hull = np.linalg.norm(grid.centres() - centre, axis=-1) < 3 * sigma
    return grid, cams, geom, grad, rhs, hull, rhs_noise(rhs, np.abs(clean).sum(-1) == 0)


@pytest.mark.parametrize("blurred", [False, True])
def test_solve_state_carries_the_setup_products(blob, blurred):
    """A solve warm-started with the previous solve's ``state`` (its ``S^T S x`` kept by the
    iteration) equals one that recomputes the setup products (to the float32 rounding of
    the fused passes over ``S``)."""
    grid, _, geom, _, rhs, hull, _ = blob
    p = TomoParams(curl_weight=0.0)
    sys_ = prepare_frame(geom, hull, dilation=p.hull_dilation, prior=p.prior)
    b = rhs.reshape(-1, 3)[sys_.op.rows]
    q = dataclasses.replace(p, tol=1e-3, max_iter=200)
    # the image-space flow averaging the pipeline's search uses, or none
    blur = MeasurementBlur(geom.flow_shape, np.full(geom.flow_shape[0], 1.5)) if blurred else None
    state: dict = {}
    _solve_restricted(sys_, b, dataclasses.replace(q, reg_weight=0.5), None, None, blur=blur, state=state)
    x0 = np.zeros(hull.shape + (3,))
    x0[sys_.inset] = state["x"]
    xa, ia, *_ = _solve_restricted(sys_, b, dataclasses.replace(q, reg_weight=0.25), x0, None,
                                   products=state["products"], blur=blur)
    xb, ib, *_ = _solve_restricted(sys_, b, dataclasses.replace(q, reg_weight=0.25), x0, None, blur=blur)
    assert ia == ib > 0, (ia, ib)
    np.testing.assert_allclose(xa, xb, rtol=0, atol=1e-5 * np.abs(xb).max())


@pytest.mark.parametrize("tau", [1.0, 1.3])
def test_bracketing_search_finds_the_top_down_answer(blob, tau):
    """Where the residual crosses the target, the search started anywhere on the grid finds
    the crossing a search down from the largest weight finds (to the 1e-3 convergence of
    each solve: the ratios near the target differ by about 1 % between warm starts), and
    from the default start in no more solves (here 2 instead of 6 for tau 1, 4 for both at 1.3)."""
    _, _, geom, _, rhs, hull, noise = blob
    p = TomoParams()
    top = choose_reg_weight(geom, rhs, hull, noise, params=p, tau=tau, start=4.0)
    assert top.path[-1][1] <= 1.0 < top.path[-2][1], top.path  # crossed, not levelled off
    for start in (0.125, 1e-3):
        mid = choose_reg_weight(geom, rhs, hull, noise, params=p, tau=tau, start=start)
        assert mid.reg_weight == pytest.approx(top.reg_weight, rel=0.05), (start, mid.path, top.path)
        assert [w for w, _ in mid.path] == sorted((w for w, _ in mid.path), reverse=True)
    mid = choose_reg_weight(geom, rhs, hull, noise, params=p, tau=tau)
    assert len(mid.path) <= len(top.path), (mid.path, top.path)
    if tau == 1.0:
        assert len(mid.path) < len(top.path), (mid.path, top.path)


def test_search_arguments_are_checked(blob):
    _, _, geom, _, rhs, hull, noise = blob
    for bad in (dict(start=0.0), dict(factor=1.0), dict(smallest=8.0)):
        with pytest.raises(ValueError, match="start > 0"):
            choose_reg_weight(geom, rhs, hull, noise, **bad)
