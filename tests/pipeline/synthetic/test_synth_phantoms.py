"""Phantoms: Gladstone-Dale, temperature ranges, time interpolation, plume dynamics."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.pipeline.synthetic.phantoms import (Phantom, buoyant_plume, gaussian_blob,
                                                   refractivity_from_temperature, tealight_plumes,
                                                   temperature_from_refractivity)

GRID = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.005)
MED = Medium()


def test_gladstone_dale_at_ambient_pressure():
    assert refractivity_from_temperature(MED.T_ambient, MED) == pytest.approx(MED.n_ambient - 1)
    assert refractivity_from_temperature(2 * MED.T_ambient, MED) == pytest.approx((MED.n_ambient - 1) / 2)
    T = np.array([300.0, 450.0, 600.0])
    np.testing.assert_allclose(temperature_from_refractivity(refractivity_from_temperature(T, MED), MED), T)


def test_blob_peak_and_ambient():
    ph = gaussian_blob(GRID, sigma=0.01, peak_temperature=400.0, centre=(0.0025, 0.0025, 0.1525))
    T = ph.temperature(0.0)
    assert T.max() == pytest.approx(400.0, rel=1e-9)
    assert T.min() == pytest.approx(MED.T_ambient, abs=1e-6)


def test_time_knots_are_linear():
    g = Grid((0, 0, 0), (0.01, 0.01, 0.01), 0.005)
    ph = Phantom(g, [0.0, 1.0], lambda i: np.full(g.shape, 1e-4 * (i + 1)))
    np.testing.assert_allclose(ph.refractivity(0.25), 1.25e-4)
    np.testing.assert_allclose(ph.refractivity(-1.0), 1e-4)
    np.testing.assert_allclose(ph.refractivity(5.0), 2e-4)
    assert list(ph.knots_covering(0.2, 0.3)) == [0, 1]


def test_knot_cache_keeps_the_last_knots_used():
    """Knot volumes are computed once while among the cache_size used last (LRU), read-only,
    and a volume of the wrong shape is refused every time (never cached)."""
    g = Grid((0, 0, 0), (0.01, 0.01, 0.01), 0.005)
    calls = []

    def knot(i):
        calls.append(i)
        return np.full(g.shape, 1e-4 * (i + 1))

    ph = Phantom(g, [0.0, 1.0, 2.0, 3.0], knot, cache_size=2)
    a = ph.knot_refractivity(0)
    assert ph.knot_refractivity(np.int64(0)) is a and not a.flags.writeable
    ph.knot_refractivity(1)
    ph.knot_refractivity(0)  # 0 is now the most recent: 1 goes when 2 comes
    ph.knot_refractivity(2)
    ph.knot_refractivity(0)
    ph.knot_refractivity(1)
    assert calls == [0, 1, 2, 1]
    bad = Phantom(g, [0.0], lambda i: np.zeros((1, 1, 1)))
    for _ in range(2):
        with pytest.raises(ValueError, match="knot volume shape"):
            bad.knot_refractivity(0)


def test_tealights_three_plumes_in_realistic_range():
    ph = tealight_plumes(GRID, knot_times=[0.0, 0.5])
    T = ph.temperature(0.0)
    assert 350.0 < T.max() < 600.0
    # three separate hot cores in a slice 5 cm above the floor
    k = int(round((0.05 - GRID.origin[2]) / GRID.voxel_size))
    sl = T[k]
    from scipy import ndimage
    lab, n = ndimage.label(sl > MED.T_ambient + 0.3 * (sl.max() - MED.T_ambient))
    assert n == 3
    # the sway moves the plumes sideways over time, more high up than near the flames
    x, y, z = GRID.axes()

    def centroid_x(T, k):
        w = T[k] - MED.T_ambient
        return (w.sum(axis=0) * x).sum() / w.sum()

    T1 = ph.temperature(0.5)
    top = int(round((0.25 - GRID.origin[2]) / GRID.voxel_size))
    low = int(round((0.035 - GRID.origin[2]) / GRID.voxel_size))
    shift_top = abs(centroid_x(T1, top) - centroid_x(T, top))
    shift_low = abs(centroid_x(T1, low) - centroid_x(T, low))
    assert shift_top > 2e-4 > shift_low * 4


def test_buoyant_plume_rises_and_changes():
    ph = buoyant_plume(GRID, duration=0.1, seed=1, t_start=0.0, spinup=0.15, sim_cell=0.01,
                       knot_dt=1 / 120)
    T0 = ph.temperature(0.0)
    T1 = ph.temperature(0.1)
    assert 350.0 < T0.max() < 650.0
    hot = lambda T: np.nonzero((T > MED.T_ambient + 5).any(axis=(1, 2)))[0].max()  # noqa: E731
    assert hot(T1) > hot(T0)                       # the head rises
    assert np.abs(T1 - T0).max() > 20.0            # non-stationary
    # not axisymmetric: the source is perturbed
    k = hot(T0) // 2
    assert np.abs(T0[k] - T0[k].T).max() > 1.0
