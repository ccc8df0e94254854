"""The PhiFlow plume/jet simulation behind the realistic benchmark family (optional extra)."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.pipeline.synthetic.cfd import CFDParams, cfd_available, cfd_phantom, simulate_cfd

pytestmark = pytest.mark.skipif(not cfd_available(), reason="PhiFlow (extra 'bench') is not installed")


def test_buoyant_plume_rises_from_its_source_and_stays_physical():
    grid = Grid((-0.02, -0.02, 0.0), (0.02, 0.02, 0.08), 0.005)      # 8 x 8 x 16 cells
    p = CFDParams(kind="plume", excess_temperature=50.0, source_radius=0.008, dt=1.0 / 60.0, spinup=0.1,
                  perturbation=0.2)
    r = simulate_cfd(grid, p, n_knots=6, t_first=-0.05, seed=1)
    assert r.excess.shape == (6,) + grid.shape and r.excess.dtype == np.float32
    np.testing.assert_allclose(r.knot_times, -0.05 + np.arange(6) / 60.0)
    e = r.excess.astype(np.float64)
    assert e.min() >= 0.0 and e.max() <= 50.0 * 1.2 * (1 + 3 * 0.2)     # source temperature bounds it
    z = np.arange(grid.shape[0])[:, None, None]
    height = [(ek * z).sum() / ek.sum() for ek in e]
    assert height[-1] > height[0] + 0.2                              # the hot air rises (cells)
    assert e[-1, -4:].sum() < e[-1, :4].sum()                        # the source at the floor is the hottest
    # the phantom: ambient refractivity where there is no excess, lower where it is hot
    ph = cfd_phantom(r, medium=Medium())
    vol = ph.knot_refractivity(5)
    amb = Medium().refractivity_ambient
    assert vol.max() == pytest.approx(amb) and vol.min() < amb * 0.9
    assert ph.grid == grid


def test_seeds_decorrelate_and_repeat():
    grid = Grid((-0.02, -0.02, 0.0), (0.02, 0.02, 0.06), 0.005)
    p = CFDParams(kind="jet", source_radius=0.005, inflow_velocity=0.8, dt=1.0 / 60.0, spinup=0.05)
    a = simulate_cfd(grid, p, n_knots=2, seed=3).excess
    b = simulate_cfd(grid, p, n_knots=2, seed=3).excess
    c = simulate_cfd(grid, p, n_knots=2, seed=4).excess
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3
