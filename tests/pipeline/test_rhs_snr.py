"""rhs_snr: the signal the seen rays carry, over the noise measured on the quiet ones."""

import numpy as np

from schlieren.pipeline.tomography import rhs_noise, rhs_snr


def test_known_signal_and_noise_are_recovered():
    rng = np.random.default_rng(5)
    C, h, w = 4, 60, 80
    sigma = np.array([2e-6, 3e-6, 5e-6])
    amp = np.array([3e-5, 1.5e-5, 5e-6])  # RMS signal: SNR 15, 5, 1
    seen = np.zeros((C, h, w), bool)
    seen[:, 20:40, 30:50] = True
    signal = np.zeros((C, h, w, 3))
    signal[seen] = rng.normal(size=(int(seen.sum()), 3)) * amp
    rhs = signal + rng.normal(size=signal.shape) * sigma
    rhs[0, 25, 35] = np.nan  # unreadable rays are skipped
    noise = rhs_noise(rhs, ~seen)
    np.testing.assert_allclose(noise, sigma, rtol=0.05)
    snr = rhs_snr(rhs, seen, noise)
    np.testing.assert_allclose(snr, amp / sigma, rtol=0.1)


def test_pure_noise_has_zero_snr_and_no_rays_give_nan():
    rng = np.random.default_rng(6)
    rhs = rng.normal(size=(2, 30, 30, 3)) * 1e-6
    seen = np.zeros((2, 30, 30), bool)
    seen[:, :15] = True
    snr = rhs_snr(rhs, seen, np.full(3, 1.2e-6))  # the noise overstated: no signal left
    assert np.all(snr == 0.0)
    assert np.all(np.isnan(rhs_snr(rhs, np.zeros_like(seen), np.full(3, 1e-6))))
    assert np.isnan(rhs_snr(rhs, seen, np.array([1e-6, 0.0, 1e-6]))[1])
