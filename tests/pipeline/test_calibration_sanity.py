"""Calibration sanity (issue 33 item 5): each unit or placement mistake is refused with its
one-line message naming the camera; the clean rig passes; a camera seeing little of the
volume is a warning."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schlieren.pipeline.calibration.sanity import MM_HINT, RigSanityParams, rig_problems, visible_fraction
from schlieren.pipeline.geometry import Camera, Grid
from schlieren.pipeline.synthetic.rig import look_at, make_rig

VMIN, VMAX = (-0.075, -0.075, 0.0), (0.075, 0.075, 0.3)
GRID = Grid(VMIN, VMAX, 0.0025)


def rig(n=4, **kw):
    return make_rig(n, grid=GRID, image_size=(640, 480), **kw)


def scaled(cam: Camera, *, t=1.0, background=1.0, K=1.0, name=None) -> Camera:
    """``cam`` with its translation, background distance and focal lengths scaled (a unit mistake)."""
    d = cam.background_distance() * background
    tt = cam.t * t
    point, normal = Camera.background_from_distance(cam.R, tt, d)
    Kx = cam.K.copy()
    Kx[0, 0] *= K
    Kx[1, 1] *= K
    return Camera(name or cam.name, Kx, cam.dist, cam.R, tt, cam.image_size, point, normal)


def only_fatal(problems):
    fatal = [p for p in problems if p.fatal]
    assert len(fatal) >= 1, problems
    return fatal[0]


def test_the_clean_rig_has_no_problem():
    assert rig_problems(rig(16), VMIN, VMAX) == []
    assert rig_problems(rig(8, ring="full"), VMIN, VMAX) == []


def test_a_calibration_in_millimetres_is_refused_naming_the_unit():
    cams = [scaled(c, t=1000.0, background=1000.0) for c in rig()]
    p = only_fatal(rig_problems(cams, VMIN, VMAX))
    assert p.camera == "cam00" and p.field == "t"
    assert MM_HINT in p.message and " m from the volume centre, " in p.message
    assert "\n" not in p.message


def test_one_camera_in_millimetres_with_its_background_in_metres():
    cams = rig()
    cams[2] = scaled(cams[2], t=1000.0)
    problems = rig_problems(cams, VMIN, VMAX)
    assert [p.camera for p in problems] == ["cam02"]
    assert problems[0].fatal and MM_HINT in problems[0].message


def test_a_focal_length_that_puts_the_volume_at_a_fraction_of_a_pixel():
    cams = [scaled(c, K=1e-3) for c in rig()]  # a focal length in metres-per-pixel confusion
    p = only_fatal(rig_problems(cams, VMIN, VMAX))
    assert p.field == "K" and "px in this camera's image" in p.message and "millimetres?" in p.message
    span = float(p.message.split("spans ")[1].split(" px")[0])
    assert span < 1.0


def test_a_focal_length_that_puts_the_volume_beyond_the_sensor():
    cams = [scaled(c, K=100.0) for c in rig()]
    p = only_fatal(rig_problems(cams, VMIN, VMAX))
    assert p.field == "K" and "times the sensor's diagonal" in p.message


def test_a_background_nearer_than_the_volume():
    cams = rig()
    c = cams[1]
    point, normal = Camera.background_from_distance(c.R, c.t, 1.0)  # the volume centre is 2.5 m away
    cams[1] = Camera(c.name, c.K, c.dist, c.R, c.t, c.image_size, point, normal)
    p = only_fatal(rig_problems(cams, VMIN, VMAX))
    assert (p.camera, p.field) == ("cam01", "background")
    assert "nearer than the volume centre" in p.message and "millimetres" not in p.message
    # the background in millimetres-confused metres (5 mm): the hint
    point, normal = Camera.background_from_distance(c.R, c.t, 5e-3)
    cams[1] = Camera(c.name, c.K, c.dist, c.R, c.t, c.image_size, point, normal)
    assert MM_HINT in only_fatal(rig_problems(cams, VMIN, VMAX)).message


def test_a_camera_inside_or_touching_the_volume():
    cams = rig()
    R, t = look_at(np.array([0.0, 0.0, 0.15]), np.array([1.0, 0.0, 0.15]))
    c = cams[0]
    cams[0] = Camera(c.name, c.K, c.dist, R, t, c.image_size, *Camera.background_from_distance(R, t, 3.0))
    assert "inside the volume" in only_fatal(rig_problems(cams, VMIN, VMAX)).message
    # 2 mm outside the face x = 0.075, looking in
    C = np.array([0.077, 0.0, 0.15])
    R, t = look_at(C, np.array([0.0, 0.0, 0.15]))
    cams[0] = Camera(c.name, c.K, c.dist, R, t, c.image_size, *Camera.background_from_distance(R, t, 3.0))
    p = only_fatal(rig_problems(cams, VMIN, VMAX))
    assert p.field == "t" and "2 mm from the volume's surface" in p.message


def test_cameras_that_do_not_see_the_volume_are_warnings_until_none_does():
    cams = rig()
    c = cams[3]
    C = c.center
    R, t = look_at(C, C + (C - GRID.center))  # turned around
    cams[3] = Camera(c.name, c.K, c.dist, R, t, c.image_size, *Camera.background_from_distance(R, t, 5.0))
    problems = rig_problems(cams, VMIN, VMAX)
    assert [(p.camera, p.fatal) for p in problems] == [("cam03", False)]
    assert problems[0].message.startswith("does not see the volume")
    turned = []
    for c in cams:
        R, t = look_at(c.center, c.center + (c.center - GRID.center))
        turned.append(Camera(c.name, c.K, c.dist, R, t, c.image_size, *Camera.background_from_distance(R, t, 5.0)))
    p = only_fatal(rig_problems(turned, VMIN, VMAX))
    assert p.camera is None and "no camera sees the volume" in p.message


def test_a_camera_seeing_a_part_of_the_volume_is_a_warning():
    cams = rig()
    c = cams[0]
    aim = np.array([0.0, 0.0, 0.15]) + np.array([0.0, 0.0, 0.25])  # looking over the top of the box
    R, t = look_at(c.center, aim)
    cams[0] = Camera(c.name, c.K, c.dist, R, t, c.image_size, *Camera.background_from_distance(R, t, 5.0))
    frac = visible_fraction(cams[0], VMIN, VMAX)
    assert 0 < frac < 0.5
    (p,) = rig_problems(cams, VMIN, VMAX)
    assert not p.fatal and p.message.startswith(f"sees only {100 * frac:.0f} % of the volume")


def test_a_volume_in_millimetres():
    p = only_fatal(rig_problems(rig(), np.array(VMIN) * 1e3, np.array(VMAX) * 1e3))
    assert p.camera is None and p.field == "volume" and "volume in millimetres?" in p.message


def test_the_thresholds_are_the_params_defaults():
    defaults = {f.name: f.default for f in dataclasses.fields(RigSanityParams)}
    import inspect

    sig = inspect.signature(rig_problems)
    assert {k: sig.parameters[k].default for k in defaults} == defaults


@pytest.mark.parametrize("radius", [0.3, 2.5, 25.0])
def test_plausible_rigs_pass_at_any_scale(radius):
    """Close, paper-like and telephoto rigs (the focal length filling the frame) pass."""
    assert [p for p in rig_problems(rig(radius=radius), VMIN, VMAX) if p.fatal] == []
