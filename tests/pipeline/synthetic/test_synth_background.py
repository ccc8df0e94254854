"""Wavelet Noise (Cook and DeRose 2005): band limits and statistics."""

import numpy as np

from schlieren.pipeline.synthetic.background import (background_image, make_background, noise_values,
                                                     wavelet_noise_tile)


def _spectrum(img):
    F = np.abs(np.fft.fft2(img - img.mean())) ** 2
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    return F, np.hypot(fx, fy)


def test_tile_is_band_limited_and_unit_variance():
    n = 128
    tile = wavelet_noise_tile(n, seed=1)
    bg = make_background(np.zeros(3), np.array([0.0, 1.0, 0.0]), spacing=1.0, tile=tile, bands=1, seed=0)
    # evaluate one band on a grid 4 samples per coefficient over the whole periodic tile
    s = (np.arange(4 * n) + 0.5) / 4.0
    A, B = np.meshgrid(s, s)
    v = noise_values(bg, np.stack([A, B], axis=-1))
    assert abs(v.std() - 1.0) < 0.05
    F, f = _spectrum(v)
    # frequencies in cycles per coefficient: the band sits between ~1/4 and 1/2; the part
    # below 1/8 (a coarser band's territory) holds little energy, and above 1 nearly nothing
    total = F.sum()
    low = F[f * 4 < 1 / 8].sum() / total
    band = F[(f * 4 >= 1 / 8) & (f * 4 <= 0.75)].sum() / total
    assert low < 0.005, low
    assert band > 0.9, band
    # the projection removes most of the coarse part that the B-spline evaluation of plain
    # white coefficients R has
    raw = make_background(np.zeros(3), np.array([0.0, 1.0, 0.0]), spacing=1.0,
                          tile=np.random.default_rng(1).normal(size=(n, n)), bands=1, seed=0)
    Fr, _ = _spectrum(noise_values(raw, np.stack([A, B], axis=-1)))
    assert low < 0.05 * Fr[f * 4 < 1 / 8].sum() / Fr.sum()


def test_tile_is_periodic_and_deterministic():
    t1 = wavelet_noise_tile(64, seed=5)
    t2 = wavelet_noise_tile(64, seed=5)
    np.testing.assert_array_equal(t1, t2)
    bg = make_background(np.zeros(3), np.array([0.0, 1.0, 0.0]), spacing=0.01, tile=t1, bands=1, seed=0)
    p = np.array([[0.123, 0.456]])
    np.testing.assert_allclose(noise_values(bg, p), noise_values(bg, p + 64 * 0.01), atol=1e-12)


def test_printable_image_statistics():
    tile = wavelet_noise_tile(128, seed=0)
    bg = make_background(np.zeros(3), np.array([0.0, 1.0, 0.0]), spacing=3e-4, tile=tile, bands=3, seed=0)
    img = background_image(bg, 200, 150, pixel_size=1e-4)
    assert img.shape == (150, 200)
    assert abs(img.mean() - 128) < 8
    assert 30 < img.std() < 45  # contrast 40 grey levels, a little lost to pixel-area averaging
    assert img.min() >= 0 and img.max() <= 255
