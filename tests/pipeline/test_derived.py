"""Derived quantities: Gladstone-Dale density and ideal-gas temperature."""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.derived import density, temperature
from schlieren.pipeline.geometry import Medium


def test_ambient_and_hot_air():
    m = Medium()
    r_amb = m.refractivity_ambient
    r = np.array([r_amb, r_amb / 2, r_amb * 293.15 / 600.0])
    T = temperature(r, m)
    np.testing.assert_allclose(T, [m.T_ambient, 2 * m.T_ambient, 600.0 * m.T_ambient / 293.15])
    rho = density(r, m)
    np.testing.assert_allclose(rho, r / m.gladstone_dale)
    # Ambient air: Gladstone-Dale density ~1.28 kg/m^3 (air at 20 C is ~1.2).
    assert 1.1 < rho[0] < 1.4
    # Ideal gas at constant pressure: rho * T is constant.
    np.testing.assert_allclose(rho * T, rho[0] * T[0])


def test_guards_non_positive_refractivity_and_keeps_input():
    r = np.array([[2.9e-4, 0.0], [-1e-5, 1e-4]], dtype=np.float32)
    r0 = r.copy()
    T = temperature(r)
    rho = density(r)
    assert np.isnan(T[0, 1]) and np.isnan(T[1, 0]) and np.isnan(rho[0, 1]) and np.isnan(rho[1, 0])
    assert np.isfinite(T[0, 0]) and np.isfinite(rho[1, 1]) and T.dtype == np.float64
    np.testing.assert_array_equal(r, r0)


def test_custom_medium():
    m = Medium(n_ambient=1.0003, T_ambient=300.0, gladstone_dale=2.0e-4)
    np.testing.assert_allclose(temperature(np.array([3e-4]), m), 300.0)
    np.testing.assert_allclose(density(np.array([3e-4]), m), 1.5)
