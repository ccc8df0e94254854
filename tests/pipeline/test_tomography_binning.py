"""Tomography ray binning (pipeline/tomography/binning.py): one ray per block of flow cells
where the cells oversample the voxels. Block means and widths against their definitions,
the ray grid's image points against the cells they replace, the automatic choice against
the voxel footprint, and a reconstruction against an analytic field: binned rays recover it
within a few tenths of a dB of one ray per cell, from a quarter of the rows."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.poisson import PoissonParams, integrate
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.pipeline.tomography import (
    MeasurementBlur,
    TomoParams,
    bin_cells,
    bin_quiet,
    binned_sigma,
    build_geometry,
    ray_binning,
    ray_grid,
    solve_gradient,
    volume_sigma,
)
from schlieren.pipeline.tomography.binning import MIN_RAYS_PER_VOXEL, cells_per_voxel
from tests.pipeline.test_tomography import blob_field, ring_cameras

R_AMB = 2.9e-4


def test_block_means_skip_invalid_cells_and_drop_mostly_invalid_blocks():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((2, 7, 9, 3))  # 7 x 9 cells: the partial last row / column of blocks is cut
    a[0, 0, 0, 1] = np.nan  # one invalid cell (one component is enough) in block (0, 0)
    a[1, 2:4, 2:4] = np.nan
    a[1, 2, 3] = 5.0  # block (1, 1) of camera 1: 3 of 4 cells invalid
    out = bin_cells(a, 2)
    assert out.shape == (2, 3, 4, 3)
    want = a[:, :6, :8].reshape(2, 3, 2, 4, 2, 3).mean(axis=(2, 4))
    np.testing.assert_allclose(out[0, 1:], want[0, 1:])
    np.testing.assert_allclose(out[0, 0, 0], a[0, [0, 1, 1], [1, 0, 1]].mean(axis=0))  # mean of the 3 valid
    assert np.all(np.isnan(out[1, 1, 1]))  # 1 valid cell of 4 < half
    assert np.all(np.isfinite(np.delete(out[1].reshape(-1, 3), 1 * 4 + 1, axis=0)))
    assert bin_cells(a, 1) is a
    quiet = np.ones((1, 4, 4), bool)
    quiet[0, 3, 0] = False
    np.testing.assert_array_equal(bin_quiet(quiet, 2), [[[True, True], [False, True]]])


@pytest.mark.parametrize("sigma,b", [(0.8, 2), (1.5, 3), (0.0, 2)])
def test_binned_width_is_the_width_of_the_window_then_the_block_mean(sigma, b):
    """The flow averaging (a Gaussian of ``sigma`` cells) followed by the block mean of
    ``b`` cells: the composite kernel's standard deviation, in blocks."""
    h = 0.01  # cells: the kernels sampled finely
    x = np.arange(-2000, 2001) * h
    g = np.exp(-x ** 2 / (2 * sigma ** 2)) if sigma > 0 else (np.abs(x) < h / 2).astype(float)
    shifts = np.zeros(round((b - 1) / h) + 1)
    shifts[::round(1 / h)] = 1.0 / b  # the mean of b cells one cell apart
    k = np.convolve(g / g.sum(), shifts)
    xs = np.arange(k.size) * h
    mean = (xs * k).sum()
    std = np.sqrt(((xs - mean) ** 2 * k).sum()) / b
    got = float(binned_sigma(np.array([sigma]), b)[0])
    if sigma == 0:
        assert got == 0.0  # no window model: nothing to widen
    else:
        assert got == pytest.approx(std, rel=1e-6)
    np.testing.assert_array_equal(binned_sigma(np.array([sigma]), 1), [sigma])


def test_each_ray_points_at_the_centre_of_its_block_of_cells():
    fg = FlowGrid((200, 151), 3)  # 50 x 66 cells
    for b in (2, 3):
        rg = ray_grid(fg, b)
        assert rg.shape == (fg.shape[0] // b, fg.shape[1] // b)
        np.testing.assert_allclose(rg.pixel_centres(), bin_cells(fg.pixel_centres()[None], b)[0])
    with pytest.raises(ValueError):
        ray_grid(fg, 0)


def test_automatic_binning_keeps_at_least_the_minimum_rays_per_voxel_edge():
    grid = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.0025)
    cases = {(810, 1440): 2,  # paper scale, 16 cameras: 3.0 cells per voxel edge
             (480, 360): 1,   # 0.9 cells per voxel edge
             (1620, 2880): 4}
    for size, want in cases.items():
        cams = make_rig(16, ring="half", grid=grid, image_size=size)
        fg = FlowGrid(size, 3)
        c = cells_per_voxel(cams, grid, fg)
        b = ray_binning(cams, grid, fg)
        assert b == want, (size, c, b)
        assert c / (b + 1) < MIN_RAYS_PER_VOXEL  # one more cell per ray would be too coarse
        if b > 1:
            assert c / b >= MIN_RAYS_PER_VOXEL
    assert ray_binning(cams, grid, fg, 1) == 1 and ray_binning(cams, grid, fg, 3) == 3


def test_automatic_flow_grid_is_the_coarsest_with_a_cell_per_voxel_edge():
    """flow.auto_factor: the largest factor up to the configured one whose grid leaves at
    least MIN_CELLS_PER_VOXEL cells per voxel edge (checked against every factor), 1 at
    least; binding a configuration takes it, twice gives the same, and off leaves it."""
    import dataclasses

    from schlieren.pipeline.stages import RunConfig, bind_flow_factor
    from schlieren.pipeline.tomography.binning import MIN_CELLS_PER_VOXEL, auto_flow_factor

    grid = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.0025)
    seen = set()
    for size in [(1440, 1080), (480, 360), (240, 180), (120, 90), (60, 45)]:
        cams = make_rig(8, ring="half", grid=grid, image_size=size)
        for largest in (1, 2, 3, 5):
            f = auto_flow_factor(cams, grid, largest)
            ok = [g for g in range(1, largest + 1)
                  if cells_per_voxel(cams, grid, FlowGrid(size, g)) >= MIN_CELLS_PER_VOXEL]
            assert f == (max(ok) if ok else 1), (size, largest, f)
            seen.add(f)
        cfg = bind_flow_factor(RunConfig(), cams, grid)
        assert cfg.flow_factor == auto_flow_factor(cams, grid, 3)
        assert bind_flow_factor(cfg, cams, grid) == cfg
        off = dataclasses.replace(RunConfig().flow, auto_factor=False)
        assert bind_flow_factor(dataclasses.replace(RunConfig(), flow=off), cams, grid).flow_factor == 3
    assert {1, 2, 3} <= seen  # coarse, paper-like and fine rigs all occur above
    # the paper scale keeps factor 3; the 480x360 rigs of Table 1 and the demo take 2
    cams = make_rig(16, ring="half", grid=grid, image_size=(1440, 1080))
    assert auto_flow_factor(cams, grid, 3) == 3
    cams = make_rig(16, ring="half", grid=grid, image_size=(480, 360))
    assert auto_flow_factor(cams, grid, 3) == 2


def test_binned_rays_recover_an_analytic_field_nearly_as_well_as_one_ray_per_cell():
    """Cells finer than the voxels (3.6 per voxel edge): the reconstruction of a Gaussian
    blob (sigma 3.2 voxels) from noisy, window-averaged cell data, once from every cell's
    ray and once from the block means on the binned rays (a quarter of the rows). The
    binned model (the ray through each block's centre) misses the sub-block variation of the
    basis functions' line integrals: measured 49.15 dB from every cell, 48.90 binned; with
    structure at the voxel (sigma 2 voxels) 53.3 vs 52.5 dB, noise-free (docs/tuning.md, "Rays per flow cell")."""
    grid = Grid((-0.04, -0.04, 0.0), (0.04, 0.04, 0.08), 0.0025)  # 32^3
    size = (384, 288)
    cams = ring_cameras(8, grid, image_size=size)
    fg = FlowGrid(size, 2)
    assert ray_binning(cams, grid, fg) == 2
    params = TomoParams(reg_weight=0.01, max_iter=200, tol=1e-4)
    fine = build_geometry(cams, grid, fg, params=params)
    coarse = build_geometry(cams, grid, ray_grid(fg, 2), params=params)
    assert coarse.n_rays * 4 == fine.n_rays
    centre, sig, amp = np.array([0.002, -0.001, 0.04]), 0.008, -8e-5
    r_true, g_true = blob_field(grid, centre, sig, amp)
    r_true = R_AMB + r_true
    cell_sigma = np.full(len(cams), 0.8)
    cells = np.stack([fine.S @ g_true[..., k].ravel() for k in range(3)], axis=1).reshape(*fine.flow_shape, 3)
    cells = MeasurementBlur(fine.flow_shape, cell_sigma).apply(cells).astype(np.float64)
    cells += np.random.default_rng(1).normal(scale=0.02 * np.abs(cells).max(), size=cells.shape)
    hull = np.linalg.norm(grid.centres() - centre, axis=-1) < 3 * sig

    def psnr(geom, rhs, cell_w, factor):
        g, _ = solve_gradient(geom, rhs, hull, params=params,
                              volume_blur=volume_sigma(cell_w, cams, grid, factor))
        r, _ = integrate(g, hull, grid, r_ambient=R_AMB, params=PoissonParams(alpha=1.0))
        return 20 * np.log10((r_true.max() - r_true.min()) / np.sqrt(np.mean((r - r_true) ** 2)))

    p_fine = psnr(fine, cells, cell_sigma, fg.factor)
    p_binned = psnr(coarse, bin_cells(cells, 2), binned_sigma(cell_sigma, 2), fg.factor * 2)
    assert p_fine > 45
    assert p_binned > p_fine - 0.4, (p_fine, p_binned)
