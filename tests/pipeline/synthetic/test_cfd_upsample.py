"""upsample_cfd: the realistic family's truth is the CFD knots' cubic spline, traced and scored alike."""

import numpy as np
import pytest

from schlieren.pipeline.geometry import Grid
from schlieren.pipeline.synthetic.cfd import CFDResult, upsample_cfd

GRID = Grid((-0.02, -0.02, 0.0), (0.02, 0.02, 0.08), 0.0025)          # 32 x 16 x 16 cells


def _result(fn, n_knots=2):
    z, y, x = np.meshgrid(*GRID.axes()[::-1], indexing="ij")
    ex = np.stack([fn(x, y, z, k) for k in range(n_knots)]).astype(np.float32)
    return CFDResult(grid=GRID, knot_times=np.arange(n_knots) / 120.0, excess=ex, params={"kind": "test"})


def _fine_coords(grid):
    return np.meshgrid(*grid.axes()[::-1], indexing="ij")


def test_linear_field_is_reproduced_at_the_fine_voxel_centres():
    # a spline reproduces a linear field; the fine centres sit at +-h/4 of the coarse ones
    r = _result(lambda x, y, z, k: 10.0 + 100.0 * x - 50.0 * y + 200.0 * z + k)
    up = upsample_cfd(r, 2)
    assert up.grid.voxel_size == pytest.approx(GRID.voxel_size / 2)
    assert up.grid.vmin == GRID.vmin and up.grid.vmax == GRID.vmax
    assert up.excess.shape == (2,) + tuple(2 * n for n in GRID.shape) and up.excess.dtype == np.float32
    np.testing.assert_array_equal(up.knot_times, r.knot_times)
    assert up.params["upsample"] == 2 and up.params["kind"] == "test"
    z, y, x = _fine_coords(up.grid)
    want = 10.0 + 100.0 * x - 50.0 * y + 200.0 * z
    inner = (slice(12, -12),) * 3   # the faces extend the field as constant (felt a few cells in)
    for k in range(2):
        np.testing.assert_allclose(up.excess[k][inner], (want + k)[inner], rtol=0, atol=5e-4)


def test_grid_scale_structure_survives_the_tracers_differences():
    # a wave of four coarse cells: central differences on the coarse grid keep sin(pi/2)/(pi/2) = 0.64 of
    # its gradient; on the field upsampled twice they keep about 0.9 (the interpolant costs a little)
    h = GRID.voxel_size
    kz = 2 * np.pi / (4 * h)
    r = _result(lambda x, y, z, k: 5.0 + np.sin(kz * z), n_knots=1)
    up = upsample_cfd(r, 2)

    def gain(field, grid):   # least-squares gain of the differences against the exact gradient
        z = _fine_coords(grid)[0]
        num = np.gradient(field.astype(np.float64), grid.voxel_size, axis=0)
        exact = kz * np.cos(kz * z)
        m = (slice(8, -8), slice(None), slice(None))
        return float((num[m] * exact[m]).sum() / (exact[m] ** 2).sum())

    g_coarse, g_fine = gain(r.excess[0], GRID), gain(up.excess[0], up.grid)
    assert g_coarse == pytest.approx(2 / np.pi, rel=0.01)
    assert 0.8 < g_fine < 0.9 + 1e-6 and g_fine > g_coarse + 0.15


def test_sharp_edges_ring_a_little_and_factor_one_is_identity():
    # a hot slab: the spline is not clipped again (a kink would be finer than the CFD grid); its ringing
    # at the edges stays a small fraction of the step
    step = _result(lambda x, y, z, k: np.where(np.abs(x) < 0.005, 40.0, 0.0), n_knots=1)
    up = upsample_cfd(step, 2)
    assert -0.12 * 40.0 < up.excess.min() < 0.0 and 40.0 < up.excess.max() < 1.12 * 40.0   # cubic: ~10 %
    far = up.excess[0][:, :, :4]                                           # 3 CFD cells from the edge
    assert np.abs(far).max() < 0.01 * 40.0
    assert upsample_cfd(step, 1) is step
    with pytest.raises(ValueError, match="positive integer"):
        upsample_cfd(step, 0)
