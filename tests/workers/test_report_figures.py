"""Report figures checked against what they must show: colour-wheel hues, arrow positions,
world extents of slices, the data each panel holds (workers/report/figures.py,
volume_figures.py)."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.pipeline.geometry import FlowGrid
from schlieren.workers.report import figures, volume_figures

from report_volumes import GRID, blob


# -- colour coding --------------------------------------------------------------------------

def test_flow_colours_follow_the_middlebury_wheel():
    flow = np.array([[[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [np.nan, 0.0]]])
    rgb = figures.flow_to_rgb(flow, max_magnitude=1.0)[0].astype(int)
    assert rgb[0].tolist() == [255, 255, 255]          # no flow: white
    assert rgb[1][0] == 255 and rgb[1][1] == 0 and rgb[1][2] < 50  # right: red
    assert rgb[2][0] == 0 and rgb[2][2] == 255          # left: cyan-blue
    assert rgb[3][0] == 255 and rgb[3][2] == 0 and 100 < rgb[3][1] < 255  # down: orange-yellow
    assert rgb[4][2] == 255 and rgb[4][1] == 0          # up: blue-violet
    assert rgb[5].tolist() == [0, 0, 0]                 # invalid: black


def test_flow_colour_saturation_grows_with_magnitude_and_wheel_has_no_seam():
    mags = np.linspace(0, 1, 11)
    flow = np.stack([mags * np.cos(0.7), mags * np.sin(0.7)], axis=-1)[None]
    rgb = figures.flow_to_rgb(flow, max_magnitude=1.0)[0].astype(float)
    dist_from_white = np.linalg.norm(255 - rgb, axis=-1)
    assert np.all(np.diff(dist_from_white) > 0)
    over = figures.flow_to_rgb(np.array([[[2.0, 0.0]]]), max_magnitude=1.0)[0, 0]
    assert over.max() == round(0.75 * 255)  # saturated beyond the range, darkened
    ang = np.linspace(-np.pi, np.pi, 3601)
    ring = figures.flow_to_rgb(np.stack([np.cos(ang), np.sin(ang)], -1)[None], max_magnitude=1.0)[0].astype(int)
    assert np.abs(np.diff(ring, axis=0)).max() <= 12  # continuous hue, including across +-pi
    wheel = figures.flow_wheel(51)
    assert wheel[25, 25].tolist() == [255, 255, 255] and wheel[0, 0].tolist() == [255, 255, 255]


def test_flow_to_rgb_default_scale_and_input_untouched():
    rng = np.random.default_rng(1)
    flow = rng.normal(size=(8, 9, 2)).astype(np.float32)
    before = flow.copy()
    a = figures.flow_to_rgb(flow)
    b = figures.flow_to_rgb(flow, max_magnitude=float(np.hypot(flow[..., 0], flow[..., 1]).max()))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(flow, before)
    with pytest.raises(ValueError):
        figures.flow_to_rgb(np.zeros((4, 4)))


# -- figures ----------------------------------------------------------------------------------

def test_quiver_arrows_start_at_flow_grid_centres():
    fg = FlowGrid((61, 46), 3)  # image 61 x 46 px -> flow 15 x 20 (a remainder column and row)
    rng = np.random.default_rng(2)
    flow = rng.normal(0, 0.2, fg.shape + (2,))
    fig = figures.quiver_figure(rng.random((46, 61)), flow, step=4)
    q = fig.axes[0].collections[0]
    centres = fg.pixel_centres()
    rows = np.arange(2, fg.shape[0], 4)
    cols = np.arange(2, fg.shape[1], 4)
    want_xy = centres[np.ix_(rows, cols)].reshape(-1, 2)
    np.testing.assert_allclose(q.XY, want_xy)
    np.testing.assert_allclose(q.U, flow[np.ix_(rows, cols)][..., 0].ravel())
    np.testing.assert_allclose(q.V, flow[np.ix_(rows, cols)][..., 1].ravel())
    assert "arrows x" in fig.axes[0].get_title()


def test_deflection_figure_shows_the_colour_coding_and_mask():
    fg = FlowGrid((64, 48), 2)
    yy, xx = np.mgrid[0:fg.shape[0], 0:fg.shape[1]]
    flow = np.stack([(xx - 16.0) / 16, (yy - 12.0) / 16], axis=-1) * 0.3
    mask = np.hypot(flow[..., 0], flow[..., 1]) < 0.1
    fig = figures.deflection_figure(np.zeros((48, 64)), flow, mask=mask, potential=flow[..., 0], step=4,
                                    max_magnitude=0.3)
    coded = fig.axes[1].images[0].get_array()
    np.testing.assert_array_equal(np.asarray(coded), figures.flow_to_rgb(flow, max_magnitude=0.3))
    mask_ax = [ax for ax in fig.axes if ax.get_title().startswith("mask")][0]
    np.testing.assert_array_equal(np.asarray(mask_ax.images[0].get_array()), mask)
    labels = [a.get_ylabel() for a in fig.axes]
    assert "integrated deflection (px$^2$)" in labels and "|deflection| (px)" in labels
    assert figures.figure_to_rgb(fig).shape[2] == 3


def test_slice_figure_world_extent_units_and_values():
    vol = blob((0.004, -0.01, 0.02))
    fig = volume_figures.slice_figure(vol * 1e6, GRID, axis="y", index=8, label="refractivity", units="1e-6")
    ax = fig.axes[0]
    img = ax.images[0]
    assert img.get_extent() == pytest.approx([-20.0, 20.0, 0.0, 50.0])  # x and z in mm
    np.testing.assert_allclose(np.asarray(img.get_array()), vol[:, 8, :] * 1e6)
    assert ax.get_xlabel() == "x (mm)" and ax.get_ylabel() == "z (mm)"
    assert fig.axes[1].get_ylabel() == "refractivity (1e-6)"  # colour bar
    assert ax.get_title() == f"y = {GRID.axes()[1][8] * 1e3:.1f} mm"
    with pytest.raises(IndexError):
        volume_figures.slice_figure(vol, GRID, axis="x", index=16)


def test_orthoslices_share_one_colour_range():
    vol = blob((0.0, 0.0, 0.02))
    fig = volume_figures.orthoslices_figure(vol, GRID, index=(8, 12, 8), label="T", units="K")
    ims = [ax.images[0] for ax in fig.axes if ax.images]
    assert len(ims) == 3
    assert len({im.get_clim() for im in ims}) == 1
    np.testing.assert_allclose(np.asarray(ims[0].get_array()), vol[8])
    assert fig.axes[-1].get_ylabel() == "T (K)"


def test_gradient_arrows_point_outward_from_a_hot_blob():
    """Arrows are the in-plane gradient components at voxel centres (mm): for a refractivity
    dip the gradient points away from the centre on every slice through it."""
    c = (0.0025 * 0.5, 0.0025 * 0.5, 0.02 + 0.0025 * 0.5)  # a voxel centre
    vol = blob(c, sigma=0.006)
    gz, gy, gx = np.gradient(vol, GRID.voxel_size)
    vec = np.stack([gx, gy, gz], axis=-1)
    idx = tuple(int(round(v)) for v in GRID.world_to_index(np.asarray(c))[::-1])  # (iz, iy, ix)
    fig = volume_figures.orthoslices_figure(np.linalg.norm(vec, axis=-1), GRID, index=idx, vectors=vec, vector_step=2)
    centre_mm = np.asarray(c) * 1e3
    for ax, (h, v) in zip(fig.axes[:3], ((0, 1), (0, 2), (1, 2))):
        q = ax.collections[0]
        rel = q.XY - centre_mm[[h, v]]
        uv = np.stack([q.U, q.V], axis=-1)
        big = np.hypot(*uv.T) > 0.2 * np.hypot(*uv.T).max()
        cos = np.sum(rel[big] * uv[big], axis=1) / (np.linalg.norm(rel[big], axis=1) * np.linalg.norm(uv[big], axis=1))
        assert big.sum() > 8 and np.all(cos > 0.95)


def test_residual_and_hull_figures_show_their_data():
    rng = np.random.default_rng(4)
    meas = rng.normal(0, 0.1, (10, 12, 2))
    pred = meas + 0.02
    fig = figures.residual_figure(meas, pred)
    assert fig.axes[2].get_title() == f"residual (RMS {np.sqrt(2) * 0.02:.3g} px)"
    hull = np.zeros(GRID.shape, bool)
    hull[5:15, 8:16, 4:10] = True
    fig = volume_figures.hull_figure(hull, GRID)
    silhouettes = [np.asarray(ax.images[0].get_array()) for ax in fig.axes[1:4]]
    np.testing.assert_allclose(silhouettes[0], hull.mean(axis=0))
    np.testing.assert_allclose(silhouettes[2], hull.mean(axis=2))
    fig = figures.timings_figure({"flow": 3.0, "tomography": 5.5})
    assert [p.get_width() for p in fig.axes[0].patches] == [3.0, 5.5]


# -- layering ---------------------------------------------------------------------------------

def _modules_loaded_by(imports: str) -> list[str]:
    import subprocess
    import sys

    code = ("import sys\n" + imports + "\n"
            "print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'zarr',\n"
            "                      'matplotlib') or m.startswith(('schlieren.storage', 'schlieren.workers')))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return [m for m in out.stdout.strip().split(",") if m]


def test_figures_and_renderer_load_no_dask_and_never_pyplot():
    """The report's drawing modules run in the report builder, without Dask and without pyplot's
    global state; pipeline.residuals (the re-projection they show) stays a pure kernel."""
    loaded = _modules_loaded_by("import schlieren.workers.report.figures, schlieren.workers.report.volume_figures\n"
                                "import schlieren.workers.report.volume_render")
    assert not [m for m in loaded if m.split(".")[0] in ("dask", "distributed") or m == "matplotlib.pyplot"]
    assert not _modules_loaded_by("import schlieren.pipeline.residuals")


def test_the_kernel_layer_draws_nothing():
    """No pipeline module loads matplotlib (the figures and the renderer live in workers/report/)."""
    loaded = _modules_loaded_by(
        "import importlib, pkgutil, schlieren.pipeline\n"
        "for m in pkgutil.walk_packages(schlieren.pipeline.__path__, 'schlieren.pipeline.'):\n"
        "    importlib.import_module(m.name)")
    assert not loaded, loaded
