"""Deflection kernels against synthetic images with known displacement fields."""

import cv2
import numpy as np
import pytest
from flow_helpers import NoiseBackground, pixel_truth, plume_deflection, render

from schlieren.pipeline import flow as F
from schlieren.pipeline.flow import _kernels, lk, post, stage, windows
from schlieren.pipeline.geometry import FlowGrid

SHAPE = (96, 128)


@pytest.fixture(scope="module")
def background():
    return NoiseBackground(SHAPE, rng=np.random.default_rng(11), feature_px=1.0)


@pytest.fixture(scope="module")
def reference(background):
    return render(background, SHAPE)


def shift(du, dv):
    return lambda u, v: (np.full_like(u, du), np.full_like(v, dv))


def interior(a, m=16):
    return a[m:-m, m:-m]


@pytest.mark.parametrize("method", F.METHODS)
def test_identical_images_give_zero_flow(reference, method):
    flow = F.deflection_field(reference, reference.copy(), method=method)
    assert flow.shape == SHAPE + (2,) and flow.dtype == np.float32
    assert np.abs(flow).max() < 1e-3


# classic top-hat window correlation is biased towards zero (loss of pairs at the edges)
@pytest.mark.parametrize("method,tol", [("lk", 0.01), ("hs", 0.02), ("correlation", 0.1),
                                        ("dis", 0.1)])
@pytest.mark.parametrize("du,dv", [(0.25, -0.1), (0.6, 0.35), (-0.9, 0.8)])
def test_subpixel_shift_recovered(background, reference, method, tol, du, dv):
    frame = render(background, SHAPE, shift(du, dv))
    flow = interior(F.deflection_field(reference, frame, method=method))
    mean = flow.reshape(-1, 2).mean(axis=0)
    assert abs(mean[0] - du) < tol and abs(mean[1] - dv) < tol, mean
    assert np.median(np.linalg.norm(flow - [du, dv], axis=-1)) < 2 * tol


@pytest.mark.parametrize("gradient", ["symmetric", "reference"])
def test_subpixel_shift_recovered_with_reference_gradients(background, reference, gradient):
    frame = render(background, SHAPE, shift(0.6, -0.35))
    flow = interior(F.deflection_field(reference, frame, gradient=gradient))
    assert np.abs(flow.reshape(-1, 2).mean(axis=0) - [0.6, -0.35]).max() < 0.01
    assert np.median(np.linalg.norm(flow - [0.6, -0.35], axis=-1)) < 0.02


def test_texture_bias_equals_its_definition_for_a_linear_field():
    # b(p) = T_p^-1 (S_x J[:, 0] + S_y J[:, 1]), T_p = sum_q w g g^T, S_k = sum_q w (q - p)_k g g^T,
    # evaluated directly at the cell centres (box window 9 = three whole 3x3 blocks).
    rng = np.random.default_rng(4)
    f, win, rows, cols = 3, 9, 16, 18
    gx = rng.standard_normal((rows * f, cols * f)).astype(np.float32)
    gy = rng.standard_normal((rows * f, cols * f)).astype(np.float32)
    J = np.array([[0.02, -0.01], [0.015, 0.03]])  # J[:, k] = d(u, v) / d(x, y)_k, per pixel
    ii, jj = np.mgrid[0:rows, 0:cols]
    u = (J[0, 0] * f * jj + J[0, 1] * f * ii).astype(np.float32)
    v = (J[1, 0] * f * jj + J[1, 1] * f * ii).astype(np.float32)
    bu, bv = lk._texture_bias(gx, gy, u, v, window=win, window_type="box", factor=f)
    h = win // 2
    for i in range(4, rows - 4):  # away from the reflected borders of the J smoothing
        for j in range(4, cols - 4):
            r, c = i * f + 1, j * f + 1
            a, b = gx[r - h:r + h + 1, c - h:c + h + 1], gy[r - h:r + h + 1, c - h:c + h + 1]
            dy, dx = np.mgrid[-h:h + 1, -h:h + 1]
            gg = np.stack([np.stack([a * a, a * b]), np.stack([a * b, b * b])]).astype(np.float64)
            T = gg.sum(axis=(2, 3))
            Sx, Sy = (gg * dx).sum(axis=(2, 3)), (gg * dy).sum(axis=(2, 3))
            expect = np.linalg.solve(T, Sx @ J[:, 0] + Sy @ J[:, 1])
            np.testing.assert_allclose([bu[i, j], bv[i, j]], expect, rtol=1e-3, atol=1e-6)
    # a uniform flow has no window bias
    zu, zv = lk._texture_bias(gx, gy, np.full_like(u, 0.4), np.full_like(v, -0.2), window=win,
                             window_type="box", factor=f)
    assert np.abs(zu).max() == 0 and np.abs(zv).max() == 0


def test_sign_convention_frame_samples_reference_at_p_plus_delta(background, reference):
    # frame(p) = reference(p + (0.5, 0)): the pattern moved to the LEFT in the frame,
    # the deflection is +0.5 px in u (SPEC flow convention).
    frame = render(background, SHAPE, shift(0.5, 0.0))
    flow = interior(F.deflection_field(reference, frame))
    assert flow[..., 0].mean() == pytest.approx(0.5, abs=0.01)
    assert abs(flow[..., 1].mean()) < 0.01
    # consistent with warp_image: warping the reference by the flow reproduces the frame
    # (up to interpolation error of the pixel-scale pattern), the unwarped one does not
    warped = F.warp_image(reference, F.deflection_field(reference, frame))
    err_warped = np.abs(interior(warped - frame)).mean()
    err_unwarped = np.abs(interior(reference - frame)).mean()
    assert err_warped < 0.1 * err_unwarped


def test_warp_image_is_exact_for_smooth_images():
    H, W = 48, 64
    y, x = np.mgrid[0:H, 0:W].astype(float)
    f = lambda x, y: np.sin(0.3 * x + 0.2 * y) + 0.5 * np.cos(0.17 * x - 0.25 * y)  # noqa: E731
    img = f(x, y).astype(np.float32)
    flow = np.stack([0.3 * np.sin(y / 9.0), -0.7 + 0.1 * np.cos(x / 7.0)], -1)
    out = F.warp_image(img, flow)
    expect = f(x + flow[..., 0], y + flow[..., 1])
    assert np.abs(out - expect)[4:-4, 4:-4].max() < 2e-3
    # identity warp returns the image (the B-spline interpolates)
    assert np.abs(F.warp_image(img, np.zeros_like(flow)) - img)[4:-4, 4:-4].max() < 1e-4
    # prefilter once, warp many times: same result
    np.testing.assert_array_equal(F.warp_coefficients(F.spline_coefficients(img), flow), out)


def _synthetic_plume(seed: int, shape: tuple[int, int], peak: float, width: float):
    """A noisy background rendered without and with a plume's deflection (px), and the true
    flow on the factor-3 flow grid: ``(reference, frame, truth, grid)``."""
    rng = np.random.default_rng(seed)
    bg = NoiseBackground(shape, rng=rng, feature_px=1.0)
    defl = plume_deflection(shape, peak=peak, width=width)
    ref = render(bg, shape, noise=1.0, rng=rng)
    frm = render(bg, shape, defl, noise=1.0, rng=rng)
    grid = FlowGrid((shape[1], shape[0]), 3)
    truth = F.downsample_flow(pixel_truth(defl, shape).astype(np.float32), grid)
    return ref, frm, truth, grid


@pytest.fixture(scope="module")
def plume_case():
    ref, frm, truth, grid = _synthetic_plume(5, (150, 201), peak=0.8, width=201 / 6)
    inside = np.linalg.norm(truth, axis=-1) > 0.02
    inside[:3], inside[-3:], inside[:, :3], inside[:, -3:] = False, False, False, False
    return ref, frm, truth, inside, grid


def test_lk_recovers_plume_and_beats_correlation(plume_case):
    ref, frm, truth, inside, grid = plume_case
    lk = F.deflection_stage(ref, frm, F.FlowParams())
    assert lk.shape == grid.shape + (2,)
    err_lk = F.endpoint_error(lk, truth, inside)
    err_corr = F.endpoint_error(F.deflection_stage(ref, frm, F.FlowParams(method="correlation")),
                                truth, inside)
    assert err_lk < 0.015
    assert err_lk < 0.5 * err_corr
    # the texture correction removes the first-order window bias of the varying plume field
    err_raw = F.endpoint_error(F.deflection_stage(
        ref, frm, F.FlowParams(texture_correction=False)), truth, inside)
    assert err_lk < 0.9 * err_raw, (err_lk, err_raw)
    sym = F.deflection_stage(ref, frm, F.FlowParams(gradient="symmetric"))
    assert F.endpoint_error(sym, truth, inside) < 0.02
    # plume sign: rays bend away from the axis (u > 0 right of it, u < 0 left of it)
    mid = truth.shape[1] // 2
    assert lk[40:45, mid + 5:mid + 15, 0].mean() > 0.1
    assert lk[40:45, mid - 15:mid - 5, 0].mean() < -0.1


@pytest.mark.parametrize("window", [17, 25])
def test_cell_solve_is_as_accurate_as_the_per_pixel_solve(plume_case, window):
    """The finest LK level solved per flow cell (``cell_solve``; ``auto`` from windows of 5
    cells) against the per-pixel solve averaged over each cell, both against the true flow.
    Measured when it was built (EPE in the plume, px): window 17: 0.0115 cell vs 0.0115
    pixel, window 25: 0.0163 vs 0.0167; the two fields differ by about 1 % of the plume's
    deflection. (Window 9, below auto's reach: 0.0160 vs 0.0151.)"""
    ref, frm, truth, inside, grid = plume_case
    cell = F.deflection_stage(ref, frm, F.FlowParams(window=window, cell_solve="on"))
    pixel = F.deflection_stage(ref, frm, F.FlowParams(window=window, cell_solve="off"))
    assert cell.shape == pixel.shape == grid.shape + (2,)
    e_cell, e_pixel = F.endpoint_error(cell, truth, inside), F.endpoint_error(pixel, truth, inside)
    assert e_cell < 1.05 * e_pixel, (e_cell, e_pixel)
    assert e_cell < 0.02
    diff = np.sqrt(np.mean((cell - pixel)[inside] ** 2))
    assert diff < 0.05 * np.sqrt(np.mean(truth[inside] ** 2)), diff
    # the path really differs (the per-pixel solve is not silently taken)
    assert diff > 0


def test_cell_solve_recovers_a_uniform_shift(background, reference):
    frame = render(background, SHAPE, shift(0.6, -0.35))
    flow = F.deflection_stage(reference, frame, F.FlowParams(window=13, smoothing_sigma=0, outlier_threshold=0,
                                                             cell_solve="on"))
    inner = flow[4:-4, 4:-4].reshape(-1, 2)
    assert np.abs(inner.mean(axis=0) - [0.6, -0.35]).max() < 0.01
    assert np.median(np.linalg.norm(inner - [0.6, -0.35], axis=-1)) < 0.02


def test_cell_solve_auto_needs_a_window_of_five_cells():
    assert F.CELL_SOLVE_MIN_CELLS == 5
    assert F.uses_cell_solve(F.FlowParams(window=25, factor=3))  # paper scale
    assert F.uses_cell_solve(F.FlowParams(window=15, factor=3))
    assert not F.uses_cell_solve(F.FlowParams(window=13, factor=3))  # the realistic family's 9-11 px
    assert F.uses_cell_solve(F.FlowParams(window=9, factor=3, cell_solve="on"))
    assert not F.uses_cell_solve(F.FlowParams(window=25, factor=3, cell_solve="off"))
    for other in (dict(gradient="symmetric"), dict(ici_gamma=2.0), dict(factor=1, window=25), dict(method="hs")):
        assert not F.uses_cell_solve(F.FlowParams(**{"window": 25, "factor": 3, **other}))


def test_prolong_kernel_is_opencvs_warp_bit_for_bit():
    """prolong_flow's float32 kernel returns exactly what cv2.warpAffine (x / 2, bilinear,
    edges replicated) times 2 returns, on even and odd sizes and down to a column (the
    OpenCV of deploy/constraints*.txt: its warp interpolates as lerps in x, then y)."""
    rng = np.random.default_rng(5)
    M = np.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for h, w, H, W in [(8, 9, 15, 17), (8, 9, 16, 18), (68, 91, 135, 181), (3, 4, 5, 7), (1, 5, 1, 9),
                       (2, 2, 9, 9), (5, 1, 9, 1)]:
        u = (rng.standard_normal((h, w)) * 10.0 ** rng.uniform(-3, 2, (h, w))).astype(np.float32)
        v = (rng.standard_normal((h, w)) * 0.1).astype(np.float32)
        u.flat[0] = -0.0
        uu, vv = F.prolong_flow(u, v, (H, W))
        for got, a in ((uu, u), (vv, v)):
            want = cv2.warpAffine(a, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE) * np.float32(2.0)
            assert got.dtype == np.float32 and got.shape == (H, W)
            np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))


def test_cell_helpers_block_moments_window_lines_and_upsampling():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(31, 44)).astype(np.float32)
    b = rng.normal(size=(31, 44)).astype(np.float32)
    out = np.empty((3, 10, 14, 2), np.float32)
    _kernels._block_moments_kernel(a, b, 3, out)  # k = 2: the inputs themselves
    off = np.arange(3) - 1.0  # offsets from the block centre
    for k, x in enumerate((a, b)):
        blocks = x[:30, :42].reshape(10, 3, 14, 3)
        np.testing.assert_allclose(out[0, ..., k], blocks.sum(axis=(1, 3)), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(out[1, ..., k], (blocks * off[None, None, None, :]).sum(axis=(1, 3)), atol=1e-5)
        np.testing.assert_allclose(out[2, ..., k], (blocks * off[None, :, None, None]).sum(axis=(1, 3)), atol=1e-5)
    # the window per block as a line: exact for a linear window, the block mean for A
    A, B = windows._block_window_linear_taps(25, "gaussian", 3)
    d = 3 * np.arange(-5, 6)[:, None] + np.arange(3)[None, :] - 1  # offsets of the 3 pixels of each block
    w = np.where(np.abs(d) <= 12, np.exp(-0.5 * (d / 6.25) ** 2), 0.0)  # 25 px window: sigma 6.25, half 12
    assert len(A) == 11 and np.allclose(A, w.mean(axis=1) / w.mean(axis=1).sum(), rtol=1e-6)  # the block means
    np.testing.assert_array_equal(windows._block_window_taps(25, "gaussian", 3), A)
    np.testing.assert_allclose(B, -B[::-1], atol=1e-9)  # odd: the window is symmetric
    assert B[len(B) // 2 + 2] < 0 < B[len(B) // 2 - 2]  # falling right of the centre
    # a linear field on the cell centres comes back linear on the pixels (interior)
    f = 3
    i, j = np.mgrid[0:10, 0:14].astype(np.float32)
    uc, vc = 0.1 * (f * j + 1) + 0.2, -0.05 * (f * i + 1) + 0.3  # cell centre = f * index + (f - 1) / 2
    u, v = lk._upsample_cells(uc.astype(np.float32), vc.astype(np.float32), f, (30, 42))
    y, x = np.mgrid[0:30, 0:42].astype(np.float32)
    np.testing.assert_allclose(u[2:-2, 2:-2], (0.1 * x + 0.2)[2:-2, 2:-2], atol=1e-4)
    np.testing.assert_allclose(v[2:-2, 2:-2], (-0.05 * y + 0.3)[2:-2, 2:-2], atol=1e-4)


def test_full_resolution_then_downsample_beats_downsampled_images(plume_case):
    ref, frm, truth, inside, grid = plume_case
    full = F.deflection_stage(ref, frm, F.FlowParams())
    f = grid.factor
    rows, cols = grid.shape

    def area(img):
        return cv2.resize(img[: rows * f, : cols * f], (cols, rows), interpolation=cv2.INTER_AREA)

    small = F.deflection_field(area(ref), area(frm), window=5) * f  # pixels of the original
    err_full = F.endpoint_error(full, truth, inside)
    err_small = F.endpoint_error(small, truth, inside)
    assert err_full < 0.6 * err_small, (err_full, err_small)


def test_prepared_reference_gives_identical_result(plume_case):
    ref, frm, *_ = plume_case
    p = F.FlowParams()
    prep = F.prepare_reference(ref, presmooth=p.presmooth, levels=p.levels)
    np.testing.assert_array_equal(F.deflection_stage(prep, frm, p), F.deflection_stage(ref, frm, p))
    with pytest.raises(ValueError, match="PreparedReference"):
        F.deflection_stage(prep, frm, F.FlowParams(levels=2))


def test_remove_outliers_replaces_spikes_and_keeps_smooth_field():
    rng = np.random.default_rng(2)
    H, W = 60, 80
    y, x = np.mgrid[0:H, 0:W]
    smooth = np.stack([0.5 * np.sin(x / 12.0), 0.3 * np.cos(y / 9.0)], -1).astype(np.float32)
    noisy = smooth + rng.normal(0, 0.003, smooth.shape).astype(np.float32)
    cleaned, flags = F.remove_outliers(noisy, threshold=3.0, epsilon=0.01)
    assert flags.mean() < 0.002  # essentially no false positives
    spikes = noisy.copy()
    idx = (rng.integers(2, H - 2, 30), rng.integers(2, W - 2, 30))
    spikes[idx] += np.float32(0.8)
    cleaned, flags = F.remove_outliers(spikes, threshold=3.0, epsilon=0.01)
    assert flags[idx].all()
    assert np.abs(cleaned[idx] - smooth[idx]).max() < 0.05
    assert spikes[idx][0, 0] != cleaned[idx][0, 0]  # input was not mutated: copies differ


def test_adaptive_smoothing_removes_noise_where_flow_is_smooth_and_keeps_structure():
    rng = np.random.default_rng(8)
    H, W = 120, 160
    y, x = np.mgrid[0:H, 0:W]
    bump = 0.5 * np.exp(-((x - 80) ** 2 + (y - 60) ** 2) / (2 * 3.0**2))  # sharp feature
    truth = np.stack([bump, -0.5 * bump], -1).astype(np.float32)
    noisy = truth + rng.normal(0, 0.01, truth.shape).astype(np.float32)
    small = cv2.GaussianBlur(noisy, (0, 0), 0.5)
    out = post._adaptive_smoothing(small, noisy, 3.0, 3.0)
    err_s = np.linalg.norm(small - truth, axis=-1)
    err_a = np.linalg.norm(out - truth, axis=-1)
    flat = bump < 1e-4
    feature = bump > 0.05
    assert err_a[flat].mean() < 0.5 * err_s[flat].mean()
    assert err_a[feature].mean() < 1.2 * err_s[feature].mean()
    # the large scale alone would flatten the feature
    large = cv2.GaussianBlur(noisy, (0, 0), 3.0)
    assert np.linalg.norm(large - truth, axis=-1)[feature].mean() > 3 * err_a[feature].mean()


def test_downsample_is_block_mean_with_crop():
    H, W, f = 10, 14, 3
    flow = np.random.default_rng(0).normal(size=(H, W, 2)).astype(np.float32)
    out = F.downsample_flow(flow, FlowGrid((W, H), f))
    assert out.shape == (3, 4, 2)
    expect = flow[:9, :12].reshape(3, 3, 4, 3, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(out, expect, atol=1e-6)
    with pytest.raises(ValueError):
        F.downsample_flow(flow, FlowGrid((H, W), f))


def test_stage_shape_dtype_and_input_not_mutated(reference, background):
    frame = render(background, SHAPE, shift(0.3, 0.0))
    before_r, before_f = reference.copy(), frame.copy()
    out = F.deflection_stage(reference, frame, F.FlowParams(factor=4))
    assert out.shape == (SHAPE[0] // 4, SHAPE[1] // 4, 2) and out.dtype == np.float32
    np.testing.assert_array_equal(reference, before_r)
    np.testing.assert_array_equal(frame, before_f)


def test_bad_inputs_are_rejected(reference):
    with pytest.raises(ValueError, match="method"):
        F.deflection_field(reference, reference, method="farneback")
    with pytest.raises(ValueError, match="shape"):
        F.deflection_field(reference, reference[:-1])
    with pytest.raises(ValueError):
        F.FlowParams(window=10)
    with pytest.raises(ValueError):
        F.FlowParams(method="nope")
    with pytest.raises(ValueError, match="gradient"):
        F.FlowParams(gradient="central")


# ---------------------------------------------------------------------------------------
# Invalid pixels (dead, clipped, NaN, textureless regions) must not spread garbage
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def big_plume_case():
    return _synthetic_plume(21, (300, 420), peak=0.6, width=420 / 5)


def _cells_near(grid, r0, r1, c0, c1, margin_px):
    """Flow-grid cells whose pixels come within ``margin_px`` of the pixel block [r0:r1, c0:c1]."""
    rows, cols = grid.shape
    f = grid.factor
    ri = np.arange(rows) * f
    ci = np.arange(cols) * f
    near_r = (ri + f > r0 - margin_px) & (ri < r1 + margin_px)
    near_c = (ci + f > c0 - margin_px) & (ci < c1 + margin_px)
    return near_r[:, None] & near_c[None, :]


def test_black_block_is_flagged_and_does_not_corrupt_its_surroundings(big_plume_case):
    """A dead 160x120 block in the frame: NaN there, the truth's accuracy 12 px beyond it."""
    ref, frm, truth, grid = big_plume_case
    clean = F.deflection_stage(ref, frm, F.FlowParams())
    r0, r1, c0, c1 = 90, 210, 130, 290
    bad = frm.copy()
    bad[r0:r1, c0:c1] = 0.0
    out = F.deflection_stage(ref, bad, F.FlowParams())
    inside = _cells_near(grid, r0 + 8, r1 - 8, c0 + 8, c1 - 8, 0)
    assert np.isnan(out[inside]).all()
    far = ~_cells_near(grid, r0, r1, c0, c1, 12)
    far[:3], far[-3:], far[:, :3], far[:, -3:] = False, False, False, False
    assert np.isfinite(out[far]).all()
    err = F.endpoint_error(out[far], truth[far])
    err_clean = F.endpoint_error(clean[far], truth[far])
    assert err < 1.3 * err_clean + 0.003, (err, err_clean)
    # without the check the block corrupts cells far beyond its edge (the old behaviour)
    raw = F.deflection_stage(ref, bad, F.FlowParams(invalid_check=False))
    ring = far & _cells_near(grid, r0, r1, c0, c1, 40)
    assert F.endpoint_error(raw[ring], truth[ring]) > 3 * F.endpoint_error(out[ring], truth[ring])


@pytest.mark.parametrize("method", ["lk", "hs"])
def test_nan_patch_stays_local(big_plume_case, method):
    """A 10x10 NaN patch (dead pixel map) in the reference and the frame: NaN only nearby."""
    ref, frm, truth, grid = big_plume_case
    r = ref.copy()
    f = frm.copy()
    r[150:160, 200:210] = np.nan
    f[40:50, 60:70] = np.nan
    out = F.deflection_stage(r, f, F.FlowParams(method=method))
    nan = np.isnan(out[..., 0])
    assert nan.any()
    near = _cells_near(grid, 150, 160, 200, 210, 12) | _cells_near(grid, 40, 50, 60, 70, 12)
    assert not nan[~near].any()
    assert nan.mean() < 0.02


def test_textureless_reference_region_is_invalid(big_plume_case):
    ref, frm, truth, grid = big_plume_case
    r = ref.copy()
    f = frm.copy()
    r[60:120, 300:400] = 128.0 + np.random.default_rng(0).normal(0, 1.0, (60, 100))  # noise only
    f[60:120, 300:400] = 128.0 + np.random.default_rng(1).normal(0, 1.0, (60, 100))
    inv = F.invalid_pixels(r)
    assert inv[70:110, 310:390].all() and not inv[200:, :200].any()
    out = F.deflection_stage(r, f, F.FlowParams())
    assert np.isnan(out[_cells_near(grid, 68, 112, 308, 392, 0)]).all()
    # an all-black frame carries nothing
    assert F.invalid_pixels(np.zeros((40, 50), np.float32)).all()


def test_correlation_peak_fit_never_returns_nan(big_plume_case):
    """Anti-correlated / flat windows used to give log(negative) = NaN in the peak fit."""
    ref, frm, truth, grid = big_plume_case
    f = frm.copy()
    f[:64, :64] = 255.0 - f[:64, :64]           # inverted contrast: the peak is negative
    f[200:264, 300:364] = 100.0                 # flat
    out = F.deflection_field(ref, f, method="correlation")
    assert np.isfinite(out).all()
    staged = F.deflection_stage(ref, f, F.FlowParams(method="correlation"))
    assert np.isnan(staged[_cells_near(grid, 210, 254, 310, 354, 0)]).all()


def test_ici_beats_every_fixed_window_across_structure_and_background():
    """Intersection of confidence intervals on a narrow plume in noise: in the plume's core
    it is as accurate as the best fixed window (small windows drown in noise, the large one
    blurs the peak); on the flat background it averages most of the noise away, as the
    large window does. No single fixed window achieves both."""
    rng = np.random.default_rng(8)
    shape = (160, 220)
    bg = NoiseBackground(shape, rng=rng, feature_px=1.0)
    narrow = plume_deflection(shape, peak=0.5, width=12.0)
    ref = render(bg, shape, noise=2.0, rng=rng)
    frm = render(bg, shape, narrow, noise=2.0, rng=rng)
    truth = pixel_truth(narrow, shape)
    mag = np.hypot(truth[..., 0], truth[..., 1])
    core = mag > 0.2
    flat = mag < 1e-3
    flat[:15], flat[-15:], flat[:, :15], flat[:, -15:] = False, False, False, False

    def err(f, m):
        return float(np.sqrt(np.mean((f[m] - truth[m]) ** 2)))

    fixed = {w: F.deflection_field(ref, frm, window=w, levels=2) for w in (5, 9, 25)}
    info = {}
    prep = F.prepare_reference(ref, levels=2)
    u, v = stage._flow_components(prep, frm, method="lk", window=25, window_type="gaussian", levels=2,
                              iterations=2, fine_iterations=1, presmooth=0.6, regularisation=1e-3,
                              gradient="frame", alpha=0.3, inner_iterations=30, dis_preset="medium",
                              corr_window=32, corr_step=16, corr_taper=False, ici_gamma=2.0,
                              ici_min_window=5, info=info)
    ici = np.stack([u, v], axis=-1)
    np.testing.assert_array_equal(ici, F.deflection_field(ref, frm, window=25, levels=2, ici_gamma=2.0))
    best_core = min(err(f, core) for f in fixed.values())
    assert err(ici, core) < 1.05 * best_core, (err(ici, core), best_core)
    assert err(fixed[25], core) > 1.3 * err(ici, core)
    assert err(ici, flat) < 0.7 * err(fixed[9], flat)
    assert info["noise"] > 0 and info["window_median"] in F.ici_windows(5, 25)
    assert sum(info["window_fraction"].values()) == pytest.approx(1.0)


def test_window_for_voxel():
    """Odd, 3.8 voxel footprints wide, within 5..25 px."""
    assert F.window_for_voxel(2.04, 3.8) == 9      # 7.75 -> 8 -> odd 9
    assert F.window_for_voxel(2.62, 3.8) == 11     # 9.96 -> 10 -> odd 11
    assert F.window_for_voxel(8.6, 3.8) == 25      # capped
    assert F.window_for_voxel(0.5, 3.8) == 5


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_nonfinite_cells_is_the_reduction_over_the_components(dtype):
    rng = np.random.default_rng(3)
    field = rng.normal(size=(3, 17, 23, 2)).astype(dtype)
    for value in (np.nan, np.inf, -np.inf):
        idx = tuple(rng.integers(0, n, 40) for n in field.shape)
        field[idx] = value
    want = ~np.isfinite(field).all(axis=-1)
    got = F.nonfinite_cells(field)
    assert got.dtype == bool and got.shape == want.shape
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(F.nonfinite_cells(field[0, ..., :1]), ~np.isfinite(field[0, ..., 0]))
