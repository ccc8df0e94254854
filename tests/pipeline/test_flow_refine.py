"""The flow measured around a prediction (pipeline/flow/refine.py) against known deflections."""

from __future__ import annotations

import numpy as np
import pytest

from flow_helpers import NoiseBackground, pixel_truth, render
from schlieren.pipeline.flow import FlowParams, cells_to_pixels, deflection_stage, refined_deflection
from schlieren.pipeline.flow.post import _block_mean

SHAPE = (96, 96)
PARAMS = FlowParams(window=9, factor=2, smoothing_sigma=0.0, outlier_threshold=0.0)


def bump(peak: float = 0.3, sigma: float = 4.0, centre=(48.0, 48.0)):
    """A deflection that varies quadratically across the LK window near its centre: a
    Gaussian bump of ``sigma`` pixels (less than half the 9-pixel window) in u, its
    derivative's shape in v."""
    cu, cv = centre

    def field(u, v):
        g = np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma ** 2))
        return peak * g, -0.5 * peak * g * (v - cv) / sigma

    return field


def cells(px: np.ndarray, f: int) -> np.ndarray:
    rows, cols = SHAPE[0] // f, SHAPE[1] // f
    return np.stack([_block_mean(np.ascontiguousarray(px[..., i], np.float32), f, (rows, cols)) for i in range(2)],
                    axis=-1).astype(np.float64)


@pytest.fixture(scope="module")
def scene():
    bg = NoiseBackground(SHAPE, rng=np.random.default_rng(5), feature_px=1.0)
    field = bump()
    truth = pixel_truth(field, SHAPE)
    return render(bg, SHAPE), render(bg, SHAPE, field), truth


def _bias(flow: np.ndarray, truth: np.ndarray) -> float:
    """RMS error over the cells where the bump's deflection exceeds a tenth of its peak."""
    t = cells(truth, PARAMS.factor)
    inside = np.hypot(t[..., 0], t[..., 1]) > 0.1 * np.abs(t).max()
    return float(np.sqrt(np.mean((flow[inside] - t[inside]) ** 2)))


def test_refinement_shrinks_the_window_bias(scene):
    """A prediction that misses a fifth of the deflection leaves a fifth of the residual to
    the window: the refined flow's bias at most 0.35 of the plain flow's (noise-free frames)."""
    ref, frame, truth = scene
    plain = deflection_stage(ref, frame, PARAMS)
    refined = refined_deflection(ref, frame, 0.8 * truth.astype(np.float32), PARAMS)
    b_plain, b_refined = _bias(plain, truth), _bias(refined, truth)
    assert b_plain > 0.008  # the window bias the test is about is there: over 2.5 % of the peak
    assert b_refined < 0.35 * b_plain


def test_exact_prediction_leaves_no_bias(scene):
    """With the exact deflection as the prediction the residual is zero: the refined flow
    is the truth's cell means within 0.003 px (the plain flow's bias is over 0.008)."""
    ref, frame, truth = scene
    refined = refined_deflection(ref, frame, truth.astype(np.float32), PARAMS)
    assert _bias(refined, truth) < 0.003


def test_zero_prediction_is_the_plain_flow(scene):
    """Within 5e-4 px: the reference resampled at zero displacement differs from itself
    only by the truncation of the B-spline prefilter."""
    ref, frame, _ = scene
    zero = np.zeros(SHAPE + (2,), np.float32)
    np.testing.assert_allclose(refined_deflection(ref, frame, zero, PARAMS), deflection_stage(ref, frame, PARAMS),
                               atol=5e-4)


def test_cells_to_pixels_reproduces_a_linear_field():
    """Cubic interpolation from the cell centres is exact on a linear field, up to the
    image's edges, and returns the cell values at the centres."""
    f, rows, cols = 3, 10, 12
    yc = np.arange(rows) * f + (f - 1) / 2.0
    xc = np.arange(cols) * f + (f - 1) / 2.0
    Y, X = np.meshgrid(yc, xc, indexing="ij")
    c = np.stack([0.01 * X - 0.02 * Y, 0.03 * Y + 0.1], axis=-1)
    px = cells_to_pixels(c, f, (cols * f, rows * f))
    y, x = np.mgrid[0:rows * f, 0:cols * f].astype(float)
    exact = np.stack([0.01 * x - 0.02 * y, 0.03 * y + 0.1], axis=-1)
    np.testing.assert_allclose(px, exact, atol=1e-5)
    np.testing.assert_allclose(px[1::f, 1::f], c, atol=1e-5)


def test_prediction_shape_is_checked(scene):
    ref, frame, _ = scene
    with pytest.raises(ValueError, match="prediction shape"):
        refined_deflection(ref, frame, np.zeros((10, 10, 2), np.float32), PARAMS)
