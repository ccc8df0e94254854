"""SPEC section 4 metric and the truth resampling."""

import numpy as np
import pytest

from schlieren.pipeline import metrics
from schlieren.pipeline.geometry import Grid


def test_relative_rms_and_psnr_closed_form():
    t = np.zeros((4, 5, 6))
    t[1, 2, 3] = 2.0                      # range 2
    e = t + 0.1                           # RMS error 0.1 -> relative 0.05 -> 26.02 dB
    assert metrics.relative_rms(e, t) == pytest.approx(0.05)
    assert metrics.psnr(0.05) == pytest.approx(20 * np.log10(20))
    assert metrics.relative_rms(t, t) == 0.0
    assert metrics.psnr(0.0) == float("inf")
    assert metrics.relative_rms(np.ones(3), np.zeros(3)) == float("inf")


def test_resample_space_identity_and_linear_exactness():
    fine = Grid((0.0, 0.0, 0.0), (0.04, 0.03, 0.02), 0.001)
    coarse = Grid((0.0, 0.0, 0.0), (0.04, 0.03, 0.02), 0.002)
    c = fine.centres()
    lin = 1.0 + 2.0 * c[..., 0] - 3.0 * c[..., 1] + 0.5 * c[..., 2]
    np.testing.assert_array_equal(metrics.resample_space(lin, fine, fine), lin)
    cc = coarse.centres()
    expected = 1.0 + 2.0 * cc[..., 0] - 3.0 * cc[..., 1] + 0.5 * cc[..., 2]
    np.testing.assert_allclose(metrics.resample_space(lin, fine, coarse), expected, atol=1e-12)
    g2 = metrics.grid_from_attrs(coarse.origin, [coarse.voxel_size] * 3, coarse.shape)
    assert g2.shape == coarse.shape
    np.testing.assert_allclose(g2.origin, coarse.origin)


def test_resample_truth_is_linear_in_time():
    g = Grid((0.0, 0.0, 0.0), (0.004, 0.004, 0.004), 0.001)
    truth = np.stack([np.full(g.shape, 1.0), np.full(g.shape, 3.0)])
    out = metrics.resample_truth(truth, g, np.array([0.0, 1.0]), g, np.array([0.25, 1.0, 2.0]))
    np.testing.assert_allclose(out[:, 0, 0, 0], [1.5, 3.0, 3.0])
    assert metrics.time_bracket(np.array([0.0, 1.0]), 1.0 - 1e-12) == (1, 1, 0.0)


def test_summary():
    s = metrics.summarise([0.01, 0.03, float("nan")])
    assert s["frames"] == 2
    assert s["rms"] == pytest.approx(np.sqrt((0.01**2 + 0.03**2) / 2))
    assert s["psnr"] == pytest.approx(metrics.psnr(s["rms"]))


def test_in_plume_rms_closed_form():
    """In-plume RMS: over |truth - ambient| > 1 % of the range, normalised by the whole-box range."""
    amb = 2.9e-4
    t = np.full((10, 10, 10), amb)
    t[2:4, 2:4, 2:4] = amb - 1e-4          # 8 plume voxels, range 1e-4
    t[5, 5, 5] = amb - 0.5e-6              # 0.5 % of the range: not plume
    e = t.copy()
    e[2:4, 2:4, 2:4] += 2e-6               # plume error 2 % of the range
    e[9, 9, 9] += 5e-6                     # an ambient voxel's error does not count in the plume
    m = metrics.plume_mask(t, amb)
    assert m.sum() == 8
    assert metrics.plume_rms(e, t, amb) == pytest.approx(0.02)
    whole = np.sqrt((8 * 2e-6 ** 2 + 5e-6 ** 2) / 1000) / 1e-4
    assert metrics.relative_rms(e, t) == pytest.approx(whole)
    assert metrics.plume_rms(e, np.full_like(t, amb), amb) != metrics.plume_rms(e, np.full_like(t, amb), amb)
    # a reconstruction at 80 % of the plume's depth has a peak ratio of 0.8
    low = amb + 0.8 * (t - amb)
    assert metrics.peak_ratio(low, t, amb) == pytest.approx(0.8)
