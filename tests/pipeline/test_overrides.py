"""The one log line of a derived value: requested -> effective, unit, from what."""

from __future__ import annotations

from schlieren.pipeline.overrides import Override


def test_the_line_names_the_parameter_both_values_and_the_source():
    o = Override("flow.window", 17, [9, 9, 9, 9], "px", "window_per_voxel 3.8 x 2.18 px per voxel")
    assert o.line() == "flow.window 17 -> 9 px from window_per_voxel 3.8 x 2.18 px per voxel"
    o = Override("flow.window", 17, [9, 11, 9], "px", "window_per_voxel 3.8 x 2.04..2.62 px per voxel")
    assert o.line() == "flow.window 17 -> 9..11 px per camera from window_per_voxel 3.8 x 2.04..2.62 px per voxel"
    assert Override("volume.voxel_size", None, 0.0025, "m", "x").line() == "volume.voxel_size (not given) -> 0.0025 m from x"


def test_two_different_values_are_never_shown_alike():
    o = Override("tomography.n_ambient", 1.00029, 1.000293, "1", "the session's medium.n_ambient")
    assert o.line() == "tomography.n_ambient 1.00029 -> 1.000293 from the session's medium.n_ambient"
    same = Override("tomography.n_ambient", 1.00029, 1.00029, "1", "the session's medium.n_ambient")
    assert same.line() == "tomography.n_ambient 1.00029 -> 1.00029 from the session's medium.n_ambient"
    assert Override("tomography.reg_weight", 0.1, 0.16119701234, "1", "x").line() == \
        "tomography.reg_weight 0.1 -> 0.161197 from x"
