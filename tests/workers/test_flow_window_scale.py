"""``tomography.flow_window_scale``: the modelled flow averaging is measurement_sigma times it."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from schlieren.pipeline.flow import windows as flowwin
from schlieren.pipeline.params import ParamsError, validate
from schlieren.pipeline.stages import RunConfig
from schlieren.workers import tasks


def _ctx(config: RunConfig, cameras: int = 3, factor: int = 2):
    # what flow_params reads of a RunContext: the per-camera pre-smoothing (the capture
    # stage's choice) and the per-process cache
    return SimpleNamespace(config=config, cameras=[object()] * cameras,
                           flow_grid=SimpleNamespace(factor=factor), presmooth=lambda c: 0.6,
                           once=lambda key, make: make())


@pytest.mark.parametrize("scale", [1.0, 0.5, 1.4])
def test_the_window_is_the_flow_averaging_times_the_scale(scale):
    flow = dataclasses.replace(RunConfig().flow, window=9, window_per_voxel=0.0, factor=1)
    cfg = dataclasses.replace(RunConfig(), flow=flow,
                              tomography=dataclasses.replace(RunConfig().tomography, flow_window_scale=scale))
    got = tasks.choose_flow_window(_ctx(cfg, factor=1))
    # at factor 1 (no block mean, no cell solve) the width is the LK window's, from its
    # taps, and the smoothing's, added in quadrature
    taps = flowwin._window_taps(9, flow.window_type).astype(np.float64)
    x = np.arange(len(taps)) - (len(taps) - 1) / 2.0
    var = np.sum(taps * x * x) / np.sum(taps) + flow.smoothing_sigma ** 2
    assert var > 1.0
    np.testing.assert_allclose(got, np.full(3, scale * np.sqrt(var)), rtol=1e-12)


def test_no_window_model_gives_zero_widths_whatever_the_scale():
    cfg = dataclasses.replace(RunConfig(), tomography=dataclasses.replace(
        RunConfig().tomography, model_flow_window=False, flow_window_scale=2.0))
    assert not tasks.choose_flow_window(_ctx(cfg)).any()


@pytest.mark.parametrize("bad", [0.0, -1.0, 11.0])
def test_a_scale_out_of_range_is_refused_naming_the_field(bad):
    with pytest.raises(ParamsError, match="flow_window_scale"):
        validate(RunConfig, {"tomography": {"flow_window_scale": bad}})
