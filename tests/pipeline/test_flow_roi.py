"""The refined flow computed on a crop (pipeline/flow/roi.py) against the full image's."""

from __future__ import annotations

import numpy as np
import pytest

from flow_helpers import NoiseBackground, render
from schlieren.pipeline.flow import (FlowParams, cells_to_pixels, deflection_stage, flow_reach, refine_region,
                                     refined_deflection, refined_deflection_in_region)
from schlieren.pipeline.flow.post import _block_mean

SHAPE = (512, 704)  # rows, columns
RAY_FACTOR = 3
#: The difference a crop may leave on the cells it fills (pixels): its edges are a flow
#: reach away, and its regularisation weight and texture threshold are the crop's own.
TOLERANCE = 1e-4
CENTRE = (300.0, 280.0)  # (u, v) of the blob: off-centre, so the crop is not symmetric


def blob(peak: float = 1.2, sigma: float = 8.0, centre=CENTRE, cut: float = 3.0):
    """A deflection blob that is exactly zero beyond ``cut`` sigmas (a plume seen by rays that
    miss the hull elsewhere): the gradient-like field of a Gaussian, tapered to zero."""
    cu, cv = centre

    def field(u, v):
        r2 = ((u - cu) ** 2 + (v - cv) ** 2) / sigma ** 2
        g = np.exp(-0.5 * r2) * np.clip(1.0 - r2 / cut ** 2, 0.0, None) ** 2
        return peak * g * (u - cu) / sigma, 0.5 * peak * g * (v - cv) / sigma

    return field


def ray_cells(field, factor: int = RAY_FACTOR, scale: float = 0.8) -> np.ndarray:
    """``scale`` times the field's means over ``factor`` x ``factor`` cells (the prediction a
    tomography that misses a fifth of the deflection projects), NaN-free."""
    H, W = SHAPE
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    u, v = field(x, y)
    rows, cols = H // factor, W // factor
    return scale * np.stack([_block_mean(np.ascontiguousarray(a, np.float32), factor, (rows, cols))
                             for a in (u, v)], axis=-1).astype(np.float64)


def reach(params: FlowParams) -> int:
    return flow_reach(window=params.window, levels=params.levels, factor=params.factor, presmooth=params.presmooth,
                      smoothing_sigma=params.smoothing_sigma, adaptive_sigma=params.adaptive_sigma)


def region_of(pred: np.ndarray, params: FlowParams, tolerance: float = 1e-5):
    H, W = SHAPE
    return refine_region(pred, RAY_FACTOR, (W, H), reach=reach(params), factor=params.factor, levels=params.levels,
                         tolerance=tolerance)


@pytest.fixture(scope="module")
def scene():
    bg = NoiseBackground(SHAPE, rng=np.random.default_rng(11), feature_px=1.0)
    field = blob()
    ref = render(bg, SHAPE, noise=0.5, rng=np.random.default_rng(1))
    frame = render(bg, SHAPE, field, noise=0.5, rng=np.random.default_rng(2))
    return ref, frame, field


@pytest.mark.parametrize("params", [FlowParams(window=17, factor=3, presmooth=1.0),
                                    FlowParams(window=9, factor=2, presmooth=0.8, cell_solve="off"),
                                    FlowParams(window=13, factor=3, presmooth=1.0, levels=4, adaptive_sigma=3.0)],
                         ids=["cells-w17-f3", "pixels-w9-f2", "cells-w13-f3-l4-adaptive"])
def test_cropped_refinement_is_the_full_refinement(scene, params):
    """On a camera-frame whose deflection (and prediction) is a blob that is zero beyond a
    radius, the refinement on the crop equals the full image's within TOLERANCE on the
    region's cells; outside them it is the plain flow, and so is the full image's
    refinement there up to its resampling's own floor (the reference resampled at zero
    displacement, :func:`test_flow_refine.test_zero_prediction_is_the_plain_flow`): the
    prediction itself changes the full refinement there by less than TOLERANCE. The crop
    is a fraction of the image, on flow-cell and pyramid-cell boundaries."""
    ref, frame, field = scene
    pred = ray_cells(field)
    H, W = SHAPE
    full = refined_deflection(ref, frame, cells_to_pixels(pred, RAY_FACTOR, (W, H)), params)
    zero = refined_deflection(ref, frame, np.zeros((H, W, 2), np.float32), params)
    plain = deflection_stage(ref, frame, params)
    region = region_of(pred, params)
    assert not region.empty and region.share((W, H)) < 0.95
    x0, y0, _, _ = region.crop
    a = params.factor * 2 ** (params.levels - 1)
    assert x0 % a == 0 and y0 % a == 0  # flow cells and pyramid pixels coincide with the image's
    pixels = cells_to_pixels(pred, RAY_FACTOR, (W, H), box=region.crop)
    cropped = refined_deflection_in_region(ref, frame, pixels, plain, region, params)
    assert cropped.shape == full.shape
    r0, c0, r1, c1 = region.cells
    inside = np.zeros(full.shape[:2], bool)
    inside[r0:r1, c0:c1] = True
    assert np.abs(cropped - full)[inside].max() < TOLERANCE
    np.testing.assert_array_equal(cropped[~inside], plain[~inside])
    assert np.abs(full - zero)[~inside].max() < TOLERANCE
    # the refinement changes the flow by far more than that where the blob is
    assert np.abs(full - plain).max() > 100 * TOLERANCE


def test_region_covers_the_prediction(scene):
    """Every pixel where the interpolated prediction exceeds the tolerance lies in the
    region's cells, at least a flow reach inside the crop's edges (but where they are the
    image's edges)."""
    _, _, field = scene
    params = FlowParams(window=17, factor=3, presmooth=1.0)
    pred = ray_cells(field)
    H, W = SHAPE
    region = region_of(pred, params, 1e-5)
    p = np.hypot(*np.moveaxis(cells_to_pixels(pred, RAY_FACTOR, (W, H)), -1, 0))
    rows, cols = np.nonzero(p > 1e-5)
    f = params.factor
    r0, c0, r1, c1 = region.cells
    grow = reach(params)
    assert rows.min() - grow >= r0 * f and (rows.max() + grow) < r1 * f
    assert cols.min() - grow >= c0 * f and (cols.max() + grow) < c1 * f
    x0, y0, x1, y1 = region.crop
    assert (x0 == 0 or x0 <= c0 * f - grow) and (x1 == W or x1 >= c1 * f + grow)
    assert (y0 == 0 or y0 <= r0 * f - grow) and (y1 == H or y1 >= r1 * f + grow)


def test_no_prediction_keeps_the_plain_flow(scene):
    ref, frame, _ = scene
    params = FlowParams(window=17, factor=3, presmooth=1.0)
    H, W = SHAPE
    pred = np.zeros((H // RAY_FACTOR, W // RAY_FACTOR, 2))
    region = region_of(pred, params)
    assert region.empty and region.share((W, H)) == 0.0
    plain = np.random.default_rng(0).standard_normal((H // 3, W // 3, 2)).astype(np.float32)
    np.testing.assert_array_equal(refined_deflection_in_region(ref, frame, None, plain, region, params), plain)


def test_cells_to_pixels_box_is_the_full_field_there():
    cells = np.random.default_rng(3).standard_normal((20, 30, 2))
    full = cells_to_pixels(cells, 3, (90, 60))
    np.testing.assert_array_equal(cells_to_pixels(cells, 3, (90, 60), box=(12, 6, 57, 41)), full[6:41, 12:57])


def test_flow_reach_grows_with_window_levels_and_smoothing():
    r = flow_reach(window=9, factor=3, presmooth=1.0)
    assert flow_reach(window=17, factor=3, presmooth=1.0) > r
    assert flow_reach(window=9, factor=3, presmooth=1.0, levels=4) > r
    assert flow_reach(window=9, factor=3, presmooth=1.0, smoothing_sigma=6.0) > r
    assert flow_reach(window=9, factor=3, presmooth=2.0) > r
    with pytest.raises(ValueError):
        flow_reach(presmooth="auto")
