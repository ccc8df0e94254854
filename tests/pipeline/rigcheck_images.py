"""Synthetic images with known defects for the rig check's tests: a band-limited random
texture rendered at any sub-pixel shift exactly (a Fourier phase ramp, no interpolation),
with known blur, sensor noise, hot pixels and clipped regions."""

from __future__ import annotations

import numpy as np


class Texture:
    """A periodic band-limited texture ``T`` (mean 128, standard deviation ``contrast``);
    :meth:`render` gives ``T(p + d)`` blurred by a Gaussian of ``blur`` pixels."""

    def __init__(self, shape=(120, 160), *, seed=0, sigma=1.0, contrast=40.0, period=None):
        rng = np.random.default_rng(seed)
        H, W = shape
        if period:  # a tiled pattern: the tile repeats every `period` pixels
            tile = rng.standard_normal((period, period))
            n = np.tile(tile, (H // period + 1, W // period + 1))[:H, :W]
        else:
            n = rng.standard_normal(shape)
        self.fy = np.fft.fftfreq(H)[:, None]
        self.fx = np.fft.fftfreq(W)[None, :]
        self.F = np.fft.fft2(n) * self._gauss(sigma)
        base = np.real(np.fft.ifft2(self.F))
        self.scale = contrast / base.std()
        self.shape = shape

    def _gauss(self, sigma):
        return np.exp(-2 * (np.pi * sigma) ** 2 * (self.fx ** 2 + self.fy ** 2))

    def render(self, du=0.0, dv=0.0, *, blur=0.0):
        ramp = np.exp(2j * np.pi * (self.fx * du + self.fy * dv))
        return 128.0 + self.scale * np.real(np.fft.ifft2(self.F * ramp * self._gauss(blur)))


def noisy(img, sigma, rng, *, quantise=False):
    out = img + rng.normal(0.0, sigma, img.shape)
    return np.clip(np.rint(out), 0, 255) if quantise else out
