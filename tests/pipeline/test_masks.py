"""Flow masks: Poisson integration, the global threshold reduction, spatio-temporal dilation."""

import cv2
import numpy as np
import pytest

from schlieren.pipeline import masks as M


def gaussian_phi(h, w, *, cx, cy, s, amp=1.0):
    y, x = np.mgrid[0:h, 0:w].astype(float)
    return amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s**2)), x, y


def hot_plume_flow(h, w, *, cx, cy, s, amp=1.0):
    """delta = -grad(phi) for a Gaussian deficit phi: rays bent away from the centre."""
    phi, x, y = gaussian_phi(h, w, cx=cx, cy=cy, s=s, amp=amp)
    return np.stack([phi * (x - cx) / s**2, phi * (y - cy) / s**2], -1).astype(np.float32), phi


def test_potential_integrates_a_gradient_field_with_positive_sign():
    flow, phi = hot_plume_flow(60, 80, cx=37.3, cy=28.0, s=7.0, amp=5.0)
    P = M.flow_potential(flow)
    assert P.shape == (60, 80) and P.dtype == np.float32
    expect = phi - np.median(phi)
    assert np.abs(P - expect).max() < 0.02 * phi.max()
    assert P[28, 37] > 0.9 * phi.max()  # hot plume -> positive potential


def test_potential_least_squares_ignores_curl_noise():
    rng = np.random.default_rng(0)
    flow, phi = hot_plume_flow(64, 64, cx=30, cy=34, s=6.0, amp=4.0)
    noisy = flow + rng.normal(0, 0.05, flow.shape).astype(np.float32)
    P = M.flow_potential(noisy)
    corr = np.corrcoef(P.ravel(), phi.ravel())[0, 1]
    assert corr > 0.98


def test_threshold_is_sign_robust_and_masks_a_cold_flow_too():
    flow, phi = hot_plume_flow(50, 50, cx=25, cy=25, s=5.0, amp=3.0)
    P_hot = M.flow_potential(flow)
    P_cold = M.flow_potential(-flow)
    np.testing.assert_allclose(P_cold, -P_hot, atol=1e-5)
    thr = M.threshold_from_samples(P_hot, percentile=90)
    m_hot = M.make_mask(P_hot[None], 0, thr, dilation_radius=0, temporal_radius=0)
    m_cold = M.make_mask(P_cold[None], 0, thr, dilation_radius=0, temporal_radius=0)
    np.testing.assert_array_equal(m_hot, m_cold)
    assert m_hot[25, 25] and not m_hot[0, 0]


def test_threshold_from_summaries_matches_pooled_percentile():
    rng = np.random.default_rng(1)
    frames = [rng.gamma(2.0, s, size=(n, 40)) for s, n in ((1.0, 30), (3.0, 30), (0.5, 60))]
    summaries = [M.potential_summary(f, smooth_sigma=0.0, n_quantiles=400) for f in frames]
    assert all(s.shape == (401,) for s in summaries)
    pooled = np.concatenate([f.ravel() for f in frames])
    for pct in (50.0, 80.0, 97.0):
        thr = M.threshold_from_summaries(summaries, percentile=pct)
        frac_below = np.mean(pooled < thr)
        assert abs(frac_below - pct / 100) < 0.004, (pct, frac_below)
        assert thr == pytest.approx(M.threshold_from_samples(pooled, percentile=pct), rel=0.02)


@pytest.mark.parametrize("n", [1, 2, 7, 3072, 20000])
def test_sorted_quantiles_equal_numpys(n):
    """The direct read-off equals np.quantile's linear method on sorted data, float32 and
    float64, ends included."""
    rng = np.random.default_rng(n)
    probs = np.concatenate([[0.0, 1.0], (np.arange(2000) + 0.5) / 2000])
    for dtype in (np.float32, np.float64):
        v = np.sort(rng.gamma(2.0, 1.0, n).astype(dtype))
        np.testing.assert_allclose(M.sorted_quantiles(v, probs), np.quantile(v.astype(np.float64), probs),
                                   rtol=1e-12, atol=0)


def test_mask_contains_plume_support_over_a_sequence():
    # a plume drifting 1 cell per frame; support = where the true deflection > 0.02 px
    h, w, n = 72, 96, 7
    flows, supports = [], []
    rng = np.random.default_rng(3)
    for t in range(n):
        f, _ = hot_plume_flow(h, w, cx=40 + t, cy=36, s=6.0, amp=4.0)
        supports.append(np.linalg.norm(f, axis=-1) > 0.02)
        flows.append(f + rng.normal(0, 0.005, f.shape).astype(np.float32))
    P = np.stack([M.flow_potential(f) for f in flows])
    params = M.MaskParams(percentile=85.0, deflection_threshold=0.0)
    summaries = [M.potential_summary(p) for p in P]
    thr = M.threshold_from_summaries(summaries, percentile=params.percentile)
    for t in range(n):
        m = M.make_mask(P, t, thr, deflection_threshold=params.deflection_threshold)
        s = supports[t]
        assert m[s].mean() >= 0.995
        assert m.sum() <= 3 * s.sum()


def test_temporal_and_spatial_dilation():
    P = np.zeros((3, 31, 31), np.float32)
    P[2, 15, 15] = 1.0  # only the next frame has a (single-cell) signal
    m0 = M.make_mask(P, 1, 0.5, smooth_sigma=0, dilation_radius=0, temporal_radius=0)
    assert not m0.any()
    m1 = M.make_mask(P, 1, 0.5, smooth_sigma=0, dilation_radius=0, temporal_radius=1)
    assert m1.sum() == 1 and m1[15, 15]
    m3 = M.make_mask(P, 1, 0.5, smooth_sigma=0, dilation_radius=3, temporal_radius=1)
    yy, xx = np.mgrid[0:31, 0:31]
    disk = (yy - 15) ** 2 + (xx - 15) ** 2 <= 9
    np.testing.assert_array_equal(m3, disk)
    # frames outside the given stack are simply absent (sequence ends)
    m_end = M.make_mask(P, 2, 0.5, smooth_sigma=0, dilation_radius=0, temporal_radius=2)
    assert m_end[15, 15]


def test_bad_arguments():
    with pytest.raises(ValueError):
        M.MaskParams(percentile=100.0)
    with pytest.raises(ValueError):
        M.flow_potential(np.zeros((4, 4)))
    with pytest.raises(ValueError):
        M.make_mask(np.zeros((2, 4, 4)), 5, 0.1)


def test_deflection_union_covers_strong_plume_flanks_without_noise_false_positives():
    rng = np.random.default_rng(7)
    h, w = 80, 100
    flow, _ = hot_plume_flow(h, w, cx=50, cy=40, s=5.0, amp=30.0)  # strong: wide |delta| > 0.02
    flow = flow + rng.normal(0, 0.004, flow.shape).astype(np.float32)
    support = np.linalg.norm(hot_plume_flow(h, w, cx=50, cy=40, s=5.0, amp=30.0)[0], axis=-1) > 0.02
    P = M.flow_potential(flow)[None]
    params = M.MaskParams(percentile=97.0)
    thr = M.threshold_from_samples(P, percentile=params.percentile)
    core_only = M.make_mask(P, 0, thr)
    both = M.make_mask(P, 0, thr, flows=flow[None])
    assert core_only[support].mean() < 0.99          # the percentile alone misses the flanks
    assert both[support].mean() >= 0.995
    assert both.sum() <= 3 * support.sum()
    noise = rng.normal(0, 0.004, (1, h, w, 2)).astype(np.float32)
    empty = M.make_mask(np.zeros((1, h, w), np.float32), 0, 1.0, flows=noise)
    assert not empty.any()


def test_invalid_cells_do_not_poison_the_potential_and_stay_in_the_mask():
    """NaN flow cells (invalid image regions): the potential elsewhere is unchanged to within
    the hole's influence, they are left out of the threshold statistics, and the mask keeps
    them (the camera cannot rule flow out there)."""
    h, w = 60, 80
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # a hot plume's outward deflection (gradient of a negative Gaussian potential)
    P_true = np.exp(-((xx - 40) ** 2 + (yy - 30) ** 2) / (2 * 6.0 ** 2))
    flow = np.stack([-np.gradient(P_true, axis=1), -np.gradient(P_true, axis=0)], axis=-1).astype(np.float32)
    holed = flow.copy()
    holed[5:12, 5:15] = np.nan
    P = M.flow_potential(holed)
    assert np.isnan(P[5:12, 5:15]).all() and np.isfinite(P[20:, 20:]).all()
    P_clean = M.flow_potential(flow)
    assert np.abs(P[25:35, 35:45] - P_clean[25:35, 35:45]).max() < 0.05 * P_clean.max()
    s = M.potential_summary(P, n_quantiles=50)
    assert s[0] == h * w - 70
    thr = M.threshold_from_summaries([s], percentile=95)
    m = M.make_mask(P[None], 0, thr, dilation_radius=0)
    assert m[5:12, 5:15].all() and m[30, 40] and not m[50, 70]
    assert M.threshold_from_summaries([M.potential_summary(np.full((4, 4), np.nan, np.float32))]) == np.inf


def test_flow_noise_is_recovered_and_drives_the_deflection_threshold():
    """Known white flow noise is recovered within 20 % despite a plume in 10 % of the cells;
    the mask then ignores the noise (a fixed 0.015 px threshold marked all of it)."""
    rng = np.random.default_rng(3)
    h, w = 120, 160
    sigma = 0.03
    noise = rng.normal(scale=sigma, size=(h, w, 2)).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    plume = np.zeros((h, w, 2), np.float32)
    core = (np.abs(xx - 80) < 12) & (yy > 20)
    plume[core, 0] = np.sign(xx[core] - 80 + 0.5) * 0.4
    flow = plume + noise
    assert M.flow_noise(flow) == pytest.approx(sigma, rel=0.2)
    P = M.flow_potential(flow)
    thr = M.threshold_from_summaries([M.potential_summary(P)], percentile=95)
    fixed = M.make_mask(P[None], 0, thr, flows=flow[None], dilation_radius=0, flow_sigma=0.0, noise_factor=0)
    adaptive = M.make_mask(P[None], 0, thr, flows=flow[None], dilation_radius=0, flow_sigma=0.0)
    far = np.abs(xx - 80) > 40
    assert fixed[far].mean() > 0.5            # the noise passes a fixed 0.015 px threshold
    assert adaptive[far].mean() < 0.05
    assert adaptive[core].mean() > 0.9


def test_noise_cells_set_the_deflection_criterion_where_the_reference_was_not_topped_up():
    """A reference topped up outside the volume's image leaves the flow there 3x quieter than
    inside it; the frame-wide noise then puts the deflection criterion under the inner noise,
    which passes it. Measured on the inner cells (``noise_cells``), the criterion follows the
    inner noise and the inner cells without flow stay out of the evidence."""
    rng = np.random.default_rng(5)
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    inner = (np.abs(xx - 80) < 40) & (np.abs(yy - 60) < 40)  # the volume's image: 33 % of the cells
    sigma = np.where(inner, 0.03, 0.01)[..., None]
    flow = (rng.normal(size=(h, w, 2)) * sigma).astype(np.float32)
    core = (np.abs(xx - 80) < 6) & (np.abs(yy - 60) < 30)
    flow[core, 0] += 0.4
    assert M.flow_noise(flow[inner]) == pytest.approx(0.03, rel=0.2)
    P = M.flow_potential(flow)
    thr = np.inf  # the deflection criterion alone
    whole = M.frame_evidence(P, thr, flow=flow, flow_sigma=0.0, grow_factor=0)
    split = M.frame_evidence(P, thr, flow=flow, flow_sigma=0.0, grow_factor=0, noise_cells=inner)
    quiet_inner = inner & ~core
    assert whole[quiet_inner].mean() > 0.05      # 5 x the frame-wide noise lies under the inner noise's tail
    assert split[quiet_inner].mean() < 0.01
    assert split[core].mean() > 0.95
    assert np.array_equal(M.frame_evidence(P, thr, flow=flow, flow_sigma=0.0, grow_factor=0,
                                           noise_cells=np.zeros((h, w), bool)), whole)  # too few cells: frame-wide


def test_grow_factor_follows_faint_flanks_connected_to_the_plume_and_not_the_noise():
    """Hysteresis of the deflection criterion: with noisy flow (the noise lifts the criterion
    to 5 sigma) the flanks of a plume whose deflection decays smoothly are kept down to
    ``grow_factor`` sigma where they connect to its core; noise far from the plume stays out;
    with lower noise (the criterion within GROW_NOISE_RATIO times its 0.015 px floor, as on
    lossless frames) the mask does not change."""
    rng = np.random.default_rng(5)
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    d = np.abs(xx - 80.0)
    plume = np.zeros((h, w, 2), np.float32)
    plume[..., 0] = np.where(yy > 20, 0.3 * np.exp(-0.5 * (d / 10.0) ** 2), 0.0)  # Gaussian flanks
    far = d > 50
    for sigma, grows in ((0.05, True), (0.0176, False), (0.001, False)):
        flow = plume + rng.normal(scale=sigma, size=(h, w, 2)).astype(np.float32)
        # the noise of the smoothed flow the criterion sees (flow_sigma 1.5 cells)
        s = M.flow_noise(cv2.GaussianBlur(flow, (0, 0), 1.5, borderType=cv2.BORDER_REFLECT))
        if sigma == 0.0176:  # criterion above its floor, but within GROW_NOISE_RATIO of it: no growth
            assert 1.0 < 5 * s / 0.015 < M.GROW_NOISE_RATIO
        P = M.flow_potential(flow)
        thr = M.threshold_from_summaries([M.potential_summary(P)], percentile=95)
        kw = dict(flows=flow[None], dilation_radius=0)
        plain = M.make_mask(P[None], 0, thr, grow_factor=0.0, **kw)
        grown = M.make_mask(P[None], 0, thr, grow_factor=2.0, **kw)
        assert (grown >= plain).all()
        if not grows:
            np.testing.assert_array_equal(grown, plain)
            continue
        low = max(0.015, 2 * s)
        assert 5 * s > 1.5 * low
        flank = (yy > 30) & (plume[..., 0] > 1.2 * low) & (plume[..., 0] < 4 * s)  # between the two criteria
        assert flank.sum() > 300
        assert grown[flank].mean() > plain[flank].mean() + 0.3, (plain[flank].mean(), grown[flank].mean())
        assert grown[far].mean() < plain[far].mean() + 0.01, (plain[far].mean(), grown[far].mean())


def _static_frame(h, w, margin):
    """Cells whose rays miss a volume imaged in the middle ``w - 2 margin`` columns and
    ``h - 2 margin`` rows (a frame of static cells around it)."""
    s = np.ones((h, w), bool)
    s[margin:h - margin, margin:w - margin] = False
    return s


def test_static_baseline_removes_the_potential_of_an_affine_flow_bias():
    # a plume plus a small affine bias of the flow (a registration a little off: 0.003 px
    # shift, 2e-5 px/cell scale): integrated over the image, the bias is a quadratic
    # potential comparable to the plume's flanks; the baseline fitted where no ray crosses
    # the volume removes it and leaves the plume's own potential
    h, w = 80, 120
    flow, phi = hot_plume_flow(h, w, cx=60, cy=40, s=6.0, amp=0.3)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    bias = np.stack([0.003 + 2e-5 * (x - 60), -0.002 + 2e-5 * (y - 40)], -1)
    static = _static_frame(h, w, 22)
    P_static = M.flow_potential(flow + bias, static=static)
    P_median = M.flow_potential(flow + bias)
    truth = phi  # zero far from the plume
    assert np.abs(P_median - truth).max() > 0.2  # the bias' quadratic, as large as the plume's core
    assert np.abs(P_static - truth).max() < 0.01
    assert np.abs(P_static[static]).max() < 0.01


def test_static_baseline_falls_back_to_the_median_without_surrounding_static_cells():
    h, w = 60, 80
    flow, _ = hot_plume_flow(h, w, cx=40, cy=30, s=5.0, amp=0.5)
    one_side = np.zeros((h, w), bool)
    one_side[:, :15] = True  # the volume fills the rest: no surface can be fitted across it
    few = np.zeros((h, w), bool)
    few[0, :50] = True
    ref = M.flow_potential(flow)
    for static in (one_side, few, np.zeros((h, w), bool)):
        np.testing.assert_array_equal(M.flow_potential(flow, static=static), ref)
    assert M.static_baseline(ref, one_side) is None
