"""load_session: a valid session loads; every kind of bad input gets one precise line.

Each bad-input test breaks exactly one thing in a valid tiny session and checks the
error type, that the message names the file, the camera and the field, and that it is
a single line.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from schlieren.pipeline.geometry import Camera, rodrigues
from schlieren.storage.errors import SessionError
from schlieren.storage.session import BYTES_PER_VOXEL, load_session, parse_frame_range


def expect_error(target, *, file=None, camera=None, field=None, match=None, **kwargs) -> SessionError:
    """Load ``target`` expecting a SessionError that names file, camera and field."""
    with pytest.raises(SessionError) as info:
        load_session(target, **kwargs)
    err = info.value
    text = str(err)
    assert "\n" not in text, text
    if file is not None:
        assert err.file is not None, text
        assert Path(err.file).resolve() == Path(file).resolve(), text
        assert f"file {err.file}" in text
    if camera is not None:
        assert err.camera == camera, text
        assert f"camera {camera}" in text
    else:
        assert err.camera is None, text
    if field is not None:
        assert err.field == field, text
        assert f"field {field}" in text
    if match is not None:
        assert match.lower() in err.message.lower(), text
    return err


# ---------------------------------------------------------------------------------------
# valid sessions
# ---------------------------------------------------------------------------------------
def test_valid_session_loads_with_geometry_and_sources(session_builder):
    b = session_builder
    s = load_session(b.root)
    assert s.name == "tiny" and s.format == "schlieren-session/1"
    assert s.root == b.root.resolve()
    assert s.frame_rate == 60.0
    assert s.n_frames_available == 6 and s.frames == (0, 6) and s.n_frames == 6
    assert s.grid.shape == (10, 10, 10)
    np.testing.assert_allclose(s.grid.origin, [-0.045, -0.045, 0.005])
    assert s.medium.n_ambient == pytest.approx(1.00029)
    assert s.strobe_search is None
    assert s.camera_names == ["cam00", "cam01", "cam02"]
    for i, cam in enumerate(s.cameras):
        raw = b.camera(i)
        np.testing.assert_allclose(cam.R, raw["R"])
        np.testing.assert_allclose(cam.t, raw["t"])
        assert cam.time_offset == pytest.approx(raw["time_offset"])
        assert cam.line_time == pytest.approx(1e-5)
        # cameras look at the volume centre: it projects to the principal point
        np.testing.assert_allclose(cam.project(b.target), [(40 - 1) / 2, (30 - 1) / 2], atol=1e-9)
        # distance: 2 m -> plane perpendicular to the optical axis, 2 m in front
        assert cam.background_distance() == pytest.approx(2.0)
        np.testing.assert_allclose(cam.bg_normal, -cam.optical_axis)
    src = s.sources[1]
    assert src.name == "cam01" and src.frames_kind == "sequence" and src.reference_kind == "image"
    assert src.frames == str(b.root.resolve() / "cam01/frames/%05d.png")
    assert src.reference == str(b.root.resolve() / "cam01/reference.png")
    # manifest kept as loaded (plain data)
    assert s.manifest["cameras"][0]["name"] == "cam00"
    # also loadable by the manifest's own path
    assert load_session(b.path).camera_names == s.camera_names


def test_name_defaults_to_the_folder_name(session_builder):
    b = session_builder
    del b.manifest["name"]
    b.save()
    assert load_session(b.root).name == "session"


def test_reference_given_as_a_pattern(session_builder):
    b = session_builder
    refdir = b.root / "cam00" / "ref"
    refdir.mkdir()
    for k in range(3):
        cv2.imwrite(str(refdir / f"{k:03d}.png"), np.full((30, 40), k, np.uint8))
    b.camera(0)["reference"] = "cam00/ref/%03d.png"
    b.save()
    s = load_session(b.root)
    assert s.sources[0].reference_kind == "sequence"
    cv2.imwrite(str(refdir / "001.png"), np.zeros((30, 39), np.uint8))
    expect_error(b.root, file=refdir / "001.png", camera="cam00", field="cameras[0].reference", match="39x30")
    (refdir / "001.png").unlink()
    expect_error(b.root, file=refdir / "001.png", camera="cam00", field="cameras[0].reference[1]",
                 match="missing")


def test_frames_argument_overrides_manifest_range(session_builder):
    b = session_builder
    b.manifest["frames"] = [1, 5]
    b.save()
    assert load_session(b.root).frames == (1, 5)
    assert load_session(b.root, frames=(2, 4)).frames == (2, 4)
    assert load_session(b.root, frames="0:3").frames == (0, 3)
    s = load_session(b.root, frames=(np.int64(1), np.int64(2)))
    assert s.frames == (1, 2) and type(s.frames[0]) is int


def test_strobe_sync_makes_time_offsets_optional(session_builder):
    b = session_builder
    for cam in b.manifest["cameras"]:
        del cam["time_offset"]
    b.manifest["sync"] = {"strobe": {"search_frames": [0, 4]}}
    b.save()
    s = load_session(b.root)
    assert s.strobe_search == (0, 4)
    assert all(c.time_offset is None for c in s.cameras)


def test_rvec_is_an_alternative_to_R(session_builder):
    b = session_builder
    R = np.asarray(b.camera(1)["R"])
    rvec, _ = cv2.Rodrigues(R)
    del b.camera(1)["R"]
    b.camera(1)["rvec"] = rvec.ravel().tolist()
    b.save()
    s = load_session(b.root)
    np.testing.assert_allclose(s.cameras[1].R, R, atol=1e-12)
    np.testing.assert_allclose(rodrigues(rvec), R, atol=1e-12)


def test_background_point_normal_form(session_builder):
    b = session_builder
    R, t = np.asarray(b.camera(0)["R"]), np.asarray(b.camera(0)["t"])
    point, normal = Camera.background_from_distance(R, t, 2.0)
    b.camera(0)["background"] = {"point": point.tolist(), "normal": normal.tolist()}
    b.save()
    cam = load_session(b.root).cameras[0]
    np.testing.assert_allclose(cam.bg_point, point)
    assert cam.background_distance() == pytest.approx(2.0)


def test_check_files_false_needs_no_files(make_builder):
    b = make_builder("nofiles").save()  # manifest only, no frames
    s = load_session(b.root, check_files=False)
    assert s.n_frames_available is None and s.frames is None
    s2 = load_session(b.root, check_files=False, frames=(0, 4))
    assert s2.frames == (0, 4) and s2.n_frames == 4
    expect_error(b.root, file=b.root / "cam00/frames/%05d.png", camera="cam00", field="cameras[0].frames",
                 match="cannot be listed")


def test_frames_numbered_from_one_are_detected(make_builder):
    b = make_builder("one").write(first_index=1)
    s = load_session(b.root)
    assert s.n_frames_available == 6


def test_sixteen_bit_frames_are_accepted(make_builder):
    b = make_builder("u16").write(dtype=np.uint16)
    assert load_session(b.root).n_frames_available == 6


def test_external_paths_allowed_when_asked(session_builder, tmp_path):
    b = session_builder
    outside = tmp_path / "elsewhere"
    os.rename(b.root / "cam02", outside)
    b.camera(2)["frames"] = str(outside / "frames/%05d.png")
    b.camera(2)["reference"] = "../elsewhere/reference.png"
    b.manifest["allow_external_paths"] = True
    b.save()
    s = load_session(b.root)
    assert s.sources[2].frames == str(outside / "frames/%05d.png")
    assert Path(s.sources[2].reference) == outside / "reference.png"


@pytest.mark.parametrize("link", ["reference", "frame", "folder"])
def test_symlinks_out_of_the_session_folder_are_refused_before_anything_is_read(session_builder, tmp_path,
                                                                                 monkeypatch, link):
    """Paths are resolved, symbolic links included, before the containment check: a
    reference, a frame or a frame folder linked to a file outside is refused, naming the
    camera and field, and nothing outside is opened."""
    b = session_builder
    secret = tmp_path / "secret"
    secret.mkdir()
    cam = b.root / "cam01"
    if link == "reference":
        target = secret / "passwd.png"
        os.replace(cam / "reference.png", target)
        os.symlink(target, cam / "reference.png")
        field = "cameras[1].reference"
    elif link == "frame":
        target = secret / "00003.png"
        os.replace(cam / "frames" / "00003.png", target)
        os.symlink(target, cam / "frames" / "00003.png")
        field = "cameras[1].frames[3]"
    else:
        target = secret / "frames"
        os.replace(cam / "frames", target)
        os.symlink(target, cam / "frames")
        field = "cameras[1].frames"
    opened = []
    real_imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda f, *a: opened.append(f) or real_imread(f, *a))
    err = expect_error(b.root, file=b.root / "session.yaml", camera="cam01", field=field,
                       match="leads outside the session folder through a symbolic link")
    assert str(secret) in str(err)
    assert not any(str(secret) in os.path.realpath(f) for f in opened)
    # a link that stays inside the folder is fine, and allow_external_paths allows the rest
    b.manifest["allow_external_paths"] = True
    b.save()
    assert load_session(b.root).n_frames_available == 6


def test_a_symlink_inside_the_session_folder_is_fine(session_builder):
    b = session_builder
    cam = b.root / "cam00"
    os.replace(cam / "reference.png", cam / "background.png")
    os.symlink("background.png", cam / "reference.png")
    assert load_session(b.root).n_frames_available == 6


def test_parse_frame_range():
    assert parse_frame_range("3:9") == (3, 9)
    assert parse_frame_range((0, 5)) == (0, 5)
    with pytest.raises(ValueError):
        parse_frame_range("3-9")


# ---------------------------------------------------------------------------------------
# the manifest file
# ---------------------------------------------------------------------------------------
def test_missing_manifest(tmp_path):
    (tmp_path / "empty").mkdir()
    expect_error(tmp_path / "empty", file=tmp_path / "empty" / "session.yaml", match="no session.yaml")
    expect_error(tmp_path / "nowhere.yaml", file=tmp_path / "nowhere.yaml", match="not found")


def test_garbled_manifest(session_builder):
    b = session_builder
    b.save("format: schlieren-session/1\ncameras: [ {name: cam00, \n  frames: ]]\n")
    expect_error(b.root, file=b.path, match="not valid yaml at line")


def test_manifest_that_is_not_a_mapping(session_builder):
    b = session_builder
    b.save("- just\n- a list\n")
    expect_error(b.root, file=b.path, match="must be a mapping")
    b.save("")
    expect_error(b.root, file=b.path, match="empty")


def test_yaml_python_tag_is_rejected(session_builder):
    b = session_builder
    b.save("format: schlieren-session/1\nname: !!python/object/apply:os.system ['echo hacked']\n")
    err = expect_error(b.root, file=b.path, match="not allowed")
    assert "!!python/object/apply:os.system" in err.message


def test_duplicate_yaml_key_is_rejected(session_builder):
    b = session_builder
    b.save("format: schlieren-session/1\nname: a\nname: b\n")
    expect_error(b.root, file=b.path, match="duplicate key 'name'")


def test_unknown_format(session_builder):
    b = session_builder
    b.manifest["format"] = "schlieren-session/9"
    b.save()
    expect_error(b.root, file=b.path, field="format", match="unknown format")
    del b.manifest["format"]
    b.save()
    expect_error(b.root, file=b.path, field="format", match="missing")


def test_misspelled_top_level_field_suggests_the_right_one(session_builder):
    b = session_builder
    b.manifest["frame_rte"] = b.manifest.pop("frame_rate")
    b.save()
    err = expect_error(b.root, file=b.path, field="frame_rte")
    assert "unknown field 'frame_rte'" in err.message and "did you mean 'frame_rate'" in err.message


def test_misspelled_camera_field_names_camera_and_path(session_builder):
    b = session_builder
    b.camera(2)["refrence"] = b.camera(2).pop("reference")
    b.save()
    err = expect_error(b.root, file=b.path, camera="cam02", field="cameras[2].refrence")
    assert "did you mean 'reference'" in err.message


def test_misspelled_nested_field(session_builder):
    b = session_builder
    b.camera(1)["rolling_shutter"] = {"linetime": 1e-5}
    b.save()
    err = expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].rolling_shutter.linetime")
    assert "did you mean 'line_time'" in err.message


def test_no_cameras(session_builder):
    b = session_builder
    b.manifest["cameras"] = []
    b.save()
    expect_error(b.root, file=b.path, field="cameras", match="no cameras")


def test_duplicate_camera_names(session_builder):
    b = session_builder
    b.camera(2)["name"] = "cam00"
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[2].name", match="duplicate")


# ---------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------
def test_missing_K(session_builder):
    b = session_builder
    del b.camera(1)["K"]
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].K", match="missing")


@pytest.mark.parametrize("key, value, match", [
    ("K", [[60.0, 0.0, 19.5], [0.0, 60.0, 14.5]], "3x3"),
    ("K", [60.0, 0.0, 19.5, 0.0, 60.0, 14.5, 0.0, 0.0, 1.0], "3x3"),
    ("K", [[60.0, 0.0, 19.5], [0.0, 60.0], [0.0, 0.0, 1.0]], "3x3"),
    ("K", [[60.0, 0.0, 19.5], [0.0, 60.0, 14.5], [0.0, 1.0, 1.0]], "last row"),
    ("R", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "3x3"),
    ("t", [0.0, 0.0], "translation"),
    ("t", "far away", "translation"),
    ("dist", [0.0] * 6, "4, 5, 8, 12 or 14"),
    ("dist", [0.0] * 3, "4, 5, 8, 12 or 14"),
    ("image_size", [40], "width, height"),
    ("image_size", [40, -30], "positive"),
])
def test_misshaped_calibration(session_builder, key, value, match):
    b = session_builder
    b.camera(1)[key] = value
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field=f"cameras[1].{key}", match=match)


@pytest.mark.parametrize("n", [4, 8, 12, 14])
def test_every_opencv_distortion_length_is_accepted(session_builder, n):
    b = session_builder
    b.camera(0)["dist"] = [0.0] * n
    b.save()
    assert load_session(b.root).cameras[0].dist.shape == (n,)


def test_missing_dist(session_builder):
    b = session_builder
    del b.camera(0)["dist"]
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].dist", match="missing")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), "-.inf"])
def test_nan_or_inf_in_calibration(session_builder, bad):
    b = session_builder
    b.camera(2)["K"][1] = [0.0, bad, 14.5] if bad != "-.inf" else [0.0, float("-inf"), 14.5]
    b.save()
    err = expect_error(b.root, file=b.path, camera="cam02", field="cameras[2].K", match="finite")
    assert "[1][1]" in err.message


def test_nan_scalar_is_rejected(session_builder):
    b = session_builder
    b.camera(0)["time_offset"] = float("nan")
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].time_offset", match="finite")


def test_non_orthonormal_R(session_builder):
    b = session_builder
    R = np.asarray(b.camera(1)["R"])
    R[0, 0] += 1e-3
    b.camera(1)["R"] = R.tolist()
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].R", match="not orthonormal")


def test_R_within_tolerance_is_accepted(session_builder):
    b = session_builder
    R = np.asarray(b.camera(1)["R"])
    R[0, 0] += 2e-7
    b.camera(1)["R"] = R.tolist()
    b.save()
    load_session(b.root)


def test_reflection_R(session_builder):
    b = session_builder
    R = np.asarray(b.camera(0)["R"])
    b.camera(0)["R"] = (-R).tolist()
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].R", match="reflection")


def test_both_R_and_rvec(session_builder):
    b = session_builder
    b.camera(0)["rvec"] = [0.0, 0.0, 0.0]
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].R", match="either R or rvec")


def test_neither_R_nor_rvec(session_builder):
    b = session_builder
    del b.camera(0)["R"]
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].R", match="missing")


def test_misshaped_rvec(session_builder):
    b = session_builder
    del b.camera(0)["R"]
    b.camera(0)["rvec"] = [0.1, 0.2]
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].rvec", match="rotation vector")


# ---------------------------------------------------------------------------------------
# background, volume, timing
# ---------------------------------------------------------------------------------------
def test_background_plane_behind_camera(session_builder):
    b = session_builder
    R, t = np.asarray(b.camera(1)["R"]), np.asarray(b.camera(1)["t"])
    C, axis = -R.T @ t, R[2]
    b.camera(1)["background"] = {"point": (C - 1.0 * axis).tolist(), "normal": axis.tolist()}
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].background", match="behind the camera")


def test_background_plane_in_front_of_the_volume(session_builder):
    b = session_builder
    b.camera(2)["background"] = {"distance": 0.5}  # the volume centre is 1 m away
    b.save()
    expect_error(b.root, file=b.path, camera="cam02", field="cameras[2].background",
                 match="nearer than the volume centre")


def test_background_negative_distance(session_builder):
    b = session_builder
    b.camera(0)["background"] = {"distance": -2.0}
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].background.distance",
                 match="positive")


def test_background_both_forms(session_builder):
    b = session_builder
    b.camera(0)["background"] = {"distance": 2.0, "point": [0, 0, 0], "normal": [1, 0, 0]}
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].background", match="not both")


@pytest.mark.parametrize("vmax, field", [([0.05, -0.05, 0.1], "volume.max"), ([0.05, 0.05, -0.1], "volume.max")])
def test_empty_or_inverted_volume(session_builder, vmax, field):
    b = session_builder
    b.manifest["volume"]["max"] = vmax
    b.save()
    expect_error(b.root, file=b.path, field=field, match="empty or inverted")


def test_voxel_larger_than_volume(session_builder):
    b = session_builder
    b.manifest["volume"]["voxel_size"] = 0.5
    b.save()
    expect_error(b.root, file=b.path, field="volume.voxel_size", match="empty grid")


def test_non_positive_voxel_size(session_builder):
    b = session_builder
    b.manifest["volume"]["voxel_size"] = 0.0
    b.save()
    expect_error(b.root, file=b.path, field="volume.voxel_size", match="positive")


def test_voxel_size_needing_more_memory_than_the_machine(session_builder, monkeypatch):
    import psutil

    from schlieren.pipeline import resources

    class VM:
        total = 8 * 2**30

    monkeypatch.setattr(psutil, "virtual_memory", lambda: VM())
    b = session_builder
    b.manifest["volume"]["voxel_size"] = 1e-4  # 1000^3 voxels * the measured bytes per voxel
    b.save()
    err = expect_error(b.root, file=b.path, field="volume.voxel_size", match="more than this machine")
    need = 1000 ** 3 * BYTES_PER_VOXEL / 2**30
    assert f"{need:.1f} GiB" in err.message and "8.0 GiB" in err.message and "measured" in err.message
    assert BYTES_PER_VOXEL == max(a for _, a, _, _ in resources.TASK_MODEL.values()) > 100
    b.manifest["volume"]["voxel_size"] = 5e-4  # 200^3 voxels: fine
    b.save()
    load_session(b.root)


def test_volume_no_camera_sees(session_builder):
    b = session_builder
    b.manifest["volume"] = {"min": [5.0, 5.0, 5.0], "max": [5.1, 5.1, 5.1], "voxel_size": 0.01}
    b.save()
    expect_error(b.root, file=b.path, field="volume", match="no camera sees")


def test_camera_looking_away_is_only_a_warning(session_builder, caplog, look_at_fn):
    b = session_builder
    R, t = np.asarray(b.camera(2)["R"]), np.asarray(b.camera(2)["t"])
    C = -R.T @ t
    R2, t2 = look_at_fn(C, C + (C - b.target))  # turned around
    b.camera(2)["R"], b.camera(2)["t"] = R2.tolist(), t2.tolist()
    b.save()
    with caplog.at_level("WARNING", logger="schlieren.storage.session"):
        s = load_session(b.root)
    assert "camera cam02 does not see the volume" in caplog.text
    assert s.camera_names == ["cam00", "cam01", "cam02"]


def test_sees_volume_when_the_box_covers_the_image_without_a_corner_inside():
    from schlieren.pipeline.geometry import Grid
    from schlieren.storage.session.checks import _sees_volume

    K = [[60.0, 0, 19.5], [0, 60.0, 14.5], [0, 0, 1]]
    cam = Camera("c", K, np.zeros(5), np.eye(3), np.zeros(3), (40, 30), [0, 0, 10], [0, 0, -1])
    box = Grid((-10.0, -10.0, 2.0), (2.0, 2.0, 3.0), 0.5)
    uv = cam.project(np.vstack([box.corners(), box.center]))
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= 39.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= 29.5)
    assert not inside.any()  # the premise: no corner nor the centre is in the image
    assert _sees_volume(cam, box)
    assert not _sees_volume(cam, Grid((20.0, 20.0, 2.0), (22.0, 22.0, 3.0), 0.5))
    assert not _sees_volume(cam, Grid((-1.0, -1.0, -3.0), (1.0, 1.0, -2.0), 0.5))  # behind
    assert _sees_volume(cam, Grid((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0.5))  # camera inside


def test_non_positive_frame_rate(session_builder):
    b = session_builder
    b.manifest["frame_rate"] = 0
    b.save()
    expect_error(b.root, file=b.path, field="frame_rate", match="positive")
    b.manifest["frame_rate"] = -30.0
    b.save()
    expect_error(b.root, file=b.path, field="frame_rate", match="positive")


def test_no_sync_and_no_time_offset(session_builder):
    b = session_builder
    del b.camera(1)["time_offset"]
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].time_offset", match="sync.strobe")


def test_negative_line_time(session_builder):
    b = session_builder
    b.camera(2)["rolling_shutter"] = {"line_time": -1e-5}
    b.save()
    expect_error(b.root, file=b.path, camera="cam02", field="cameras[2].rolling_shutter.line_time",
                 match=">= 0")


# ---------------------------------------------------------------------------------------
# frame ranges
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("rng, match", [([3, 3], "empty"), ([4, 2], "empty"), ([-1, 3], "negative"),
                                        ([0, 7], "beyond the 6 frames"), ([0.5, 3], "two integers")])
def test_bad_manifest_frame_range(session_builder, rng, match):
    b = session_builder
    b.manifest["frames"] = rng
    b.save()
    expect_error(b.root, file=b.path, field="frames", match=match)


@pytest.mark.parametrize("rng, match", [((2, 2), "empty"), ((-2, 3), "negative"), ((5, 9), "beyond"),
                                        ("1-3", "A:B")])
def test_bad_requested_frame_range(session_builder, rng, match):
    b = session_builder
    expect_error(b.root, file=b.path, field="frames", match=match, frames=rng)


def test_strobe_search_beyond_frames(session_builder):
    b = session_builder
    b.manifest["sync"] = {"strobe": {"search_frames": [0, 30]}}
    b.save()
    expect_error(b.root, file=b.path, field="sync.strobe.search_frames", match="beyond the 6 frames")


# ---------------------------------------------------------------------------------------
# paths and files
# ---------------------------------------------------------------------------------------
def test_path_escaping_the_folder(session_builder):
    b = session_builder
    b.camera(1)["frames"] = "../cam01/frames/%05d.png"
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].frames", match="escapes")
    b.camera(1)["frames"] = "cam01/../../x/%05d.png"
    b.save()
    expect_error(b.root, file=b.path, camera="cam01", field="cameras[1].frames", match="escapes")


def test_absolute_path(session_builder):
    b = session_builder
    b.camera(0)["reference"] = str(b.root / "cam00" / "reference.png")
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].reference", match="absolute")


def test_frames_that_are_neither_pattern_nor_video(session_builder):
    b = session_builder
    b.camera(0)["frames"] = "cam00/frames/00000.png"
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].frames", match="printf pattern")


def test_missing_frames_folder(session_builder):
    b = session_builder
    b.camera(2)["frames"] = "cam02/nothing/%05d.png"
    b.save()
    expect_error(b.root, file=b.root / "cam02/nothing/%05d.png", camera="cam02",
                 field="cameras[2].frames", match="cannot be listed")


def test_missing_frame_in_the_middle_is_a_dropped_frame(session_builder, caplog):
    b = session_builder
    (b.root / "cam01" / "frames" / "00003.png").unlink()
    with caplog.at_level("WARNING"):
        s = load_session(b.root)
    assert s.dropped_frames == {"cam01": (3,)}
    assert s.n_frames_available == len(s.sources[0].open_frames())  # the slot is kept
    assert "cam01 frame(s) 3" in caplog.text


def test_corrupt_frame_names_its_index(session_builder):
    b = session_builder
    bad = b.root / "cam02" / "frames" / "00004.png"
    bad.write_bytes(b"this is not a png at all")
    expect_error(b.root, file=bad, camera="cam02", field="cameras[2].frames[4]",
                 match="cannot decode")


def test_truncated_last_frame_names_its_index(session_builder):
    b = session_builder
    bad = b.root / "cam00" / "frames" / "00005.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    expect_error(b.root, file=bad, camera="cam00", field="cameras[0].frames[5]",
                 match="truncated: the PNG ends before its IEND chunk")


def test_a_truncated_frame_anywhere_is_refused_before_work(session_builder):
    """Every frame's file is checked for completeness, not only the first and last."""
    b = session_builder
    bad = b.root / "cam02" / "frames" / "00003.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) - 5])
    expect_error(b.root, file=bad, camera="cam02", field="cameras[2].frames[3]", match="is truncated")
    bad.write_bytes(data)
    ref = b.root / "cam01" / "reference.png"
    ref.write_bytes(ref.read_bytes()[:-3])
    expect_error(b.root, file=ref, camera="cam01", field="cameras[1].reference", match="reference is truncated")


def test_frame_corrupt_past_its_header_needs_decode_all_frames(session_builder):
    b = session_builder
    bad = b.root / "cam01" / "frames" / "00002.png"
    data = bad.read_bytes()
    broken = bytearray(data)
    for k in range(len(data) // 2, len(data) // 2 + 8):
        broken[k] ^= 0x5A  # header intact, file complete, pixel data broken
    bad.write_bytes(bytes(broken))
    s = load_session(b.root)  # headers only: accepted here, reported when a task reads it
    with pytest.raises(SessionError, match="cannot decode") as info:
        s.sources[1].open_frames().read(2)
    assert info.value.field == "frames[2]" and info.value.camera == "cam01"
    expect_error(b.root, file=bad, camera="cam01", field="cameras[1].frames[2]", match="cannot decode",
                 decode_all_frames=True)
    bad.write_bytes(data)
    assert load_session(b.root, decode_all_frames=True).n_frames_available == 6


def test_cameras_with_different_frame_counts(session_builder):
    b = session_builder
    (b.root / "cam02" / "frames" / "00005.png").unlink()
    expect_error(b.root, file=b.root / "cam02/frames/%05d.png", camera="cam02", field="cameras[2].frames",
                 match="has 5 frames but camera cam00 has 6")


def test_image_size_disagreeing_with_files(session_builder):
    b = session_builder
    b.camera(1)["image_size"] = [48, 30]
    b.save()
    expect_error(b.root, file=b.root / "cam01/frames/00000.png", camera="cam01", field="cameras[1].image_size",
                 match="image_size is [48, 30]")


def test_one_frame_of_another_size(session_builder):
    b = session_builder
    odd = b.root / "cam00" / "frames" / "00002.png"
    cv2.imwrite(str(odd), np.zeros((30, 41), np.uint8))
    expect_error(b.root, file=odd, camera="cam00", field="cameras[0].image_size", match="frame 2 is 41x30")


def test_missing_reference_field(session_builder):
    b = session_builder
    del b.camera(0)["reference"]
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].reference", match="missing")


def test_missing_reference_file(session_builder):
    b = session_builder
    ref = b.root / "cam01" / "reference.png"
    ref.unlink()
    expect_error(b.root, file=ref, camera="cam01", field="cameras[1].reference", match="not found")


def test_reference_of_the_wrong_size(session_builder):
    b = session_builder
    ref = b.root / "cam01" / "reference.png"
    cv2.imwrite(str(ref), np.zeros((31, 40), np.uint8))
    expect_error(b.root, file=ref, camera="cam01", field="cameras[1].reference", match="40x31")


def test_missing_voxel_size_is_chosen_from_the_pixel_footprint(session_builder):
    """No volume.voxel_size: the voxel spans 2 image pixels at the volume centre."""
    from schlieren.pipeline.geometry import auto_voxel_size, pixel_footprint

    b = session_builder
    b.manifest["volume"].pop("voxel_size")
    b.save()
    s = load_session(b.root)
    centre = 0.5 * (np.asarray(s.grid.vmin) + np.asarray(s.grid.vmax))
    fp = float(np.median([pixel_footprint(c, centre) for c in s.cameras]))
    v, info = auto_voxel_size(s.cameras, s.grid.vmin, s.grid.vmax)
    assert s.grid.voxel_size == pytest.approx(v)
    assert info["limited_by"] == "footprint" and 2.0 <= s.grid.voxel_size / fp < 2.0 + 5e-5 / fp + 1e-9
    # an explicit voxel_size stays an override
    b.manifest["volume"]["voxel_size"] = 0.01
    b.save()
    assert load_session(b.root).grid.voxel_size == 0.01


# ---------------------------------------------------------------------------------------
# issue 36: the strobe window, hostile YAML, camera names and positions
# ---------------------------------------------------------------------------------------
def _strobe(b, window, frames=None):
    for cam in b.manifest["cameras"]:
        cam.pop("time_offset", None)
    b.manifest["sync"] = {"strobe": {"search_frames": list(window)}}
    if frames is not None:
        b.manifest["frames"] = list(frames)
    b.save()


def test_a_strobe_window_overlapping_the_processed_frames_is_refused(session_builder):
    b = session_builder
    _strobe(b, (0, 3), frames=(2, 6))
    err = expect_error(b.root, file=b.path, field="sync.strobe.search_frames", match="overlap")
    assert "[2, 6)" in err.message and "[0, 3)" in err.message
    _strobe(b, (0, 3), frames=(3, 6))
    assert load_session(b.root).frames == (3, 6)
    expect_error(b.root, file=b.path, field="sync.strobe.search_frames", match="overlap", frames=(1, 4))


def test_without_frames_a_strobe_window_leaves_the_frames_beside_it(session_builder):
    b = session_builder
    _strobe(b, (0, 3))
    assert load_session(b.root).frames == (3, 6)
    _strobe(b, (3, 6))  # a flash at the end of the recording
    assert load_session(b.root).frames == (0, 3)
    _strobe(b, (1, 4))  # frames on both sides: those after it
    assert load_session(b.root).frames == (4, 6)


def _alias_bomb(levels: int = 9, width: int = 9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "\n".join(lines) + "\n"


@pytest.fixture
def deadline():
    """Fail (instead of hanging) when the test body runs longer than 20 s."""
    import signal

    def expired(*_):
        raise TimeoutError("still running after 20 s")

    old = signal.signal(signal.SIGALRM, expired)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def test_a_yaml_alias_bomb_is_refused_at_once(session_builder, deadline):
    import time

    b = session_builder
    text = b.path.read_text() + _alias_bomb().replace("a", "x_a")
    b.save(text)
    t0 = time.perf_counter()
    err = expect_error(b.root, file=b.path, match="aliases")
    assert time.perf_counter() - t0 < 5 and len(str(err)) < 400


def test_a_params_file_with_an_alias_bomb_is_refused_by_the_same_rule(tmp_path, deadline):
    from schlieren.storage.errors import SchlierenInputError
    from schlieren.storage.params_io import read_params

    p = tmp_path / "params.yaml"
    p.write_text(_alias_bomb())
    with pytest.raises(SchlierenInputError, match="aliases") as info:
        read_params(p)
    assert info.value.file == str(p)


@pytest.mark.parametrize("name", ["x" * 1_000_000, "cam 1", "cam/1", "", "-cam", "ca\tm", "c" * 65])
def test_a_camera_name_must_be_a_short_printable_identifier(session_builder, name):
    b = session_builder
    b.camera(1)["name"] = name
    b.save()
    with pytest.raises(SessionError) as info:
        load_session(b.root)
    text = str(info.value)
    assert info.value.field == "cameras[1].name" and len(text) < 400 and "\n" not in text, text[:500]
    assert info.value.file == str(b.path.resolve())


@pytest.mark.parametrize("name", ["cam-01", "left_cam.2", "C" * 64, "0"])
def test_short_camera_names_are_accepted(session_builder, name):
    b = session_builder
    b.camera(1)["name"] = name
    b.save()
    assert load_session(b.root, check_files=False).camera_names[1] == name


def test_a_camera_inside_the_volume_is_refused(session_builder):
    b = session_builder
    R = np.asarray(b.camera(0)["R"])
    inside = np.array([0.01, 0.0, 0.05])  # the box is [-0.05, 0.05] x [-0.05, 0.05] x [0, 0.1]
    b.camera(0)["t"] = (-R @ inside).tolist()
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].t", match="inside the volume")


def test_a_manifest_in_millimetres_is_refused_before_any_work(session_builder):
    """Translations and background distances in mm, the volume in metres (issue 33)."""
    b = session_builder
    for i in range(3):
        b.camera(i)["t"] = (1000.0 * np.asarray(b.camera(i)["t"])).tolist()
        b.camera(i)["background"] = {"distance": 1000.0 * b.camera(i)["background"]["distance"]}
    b.save()
    err = expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].t", match="calibration in millimetres?")
    assert "\n" not in str(err)
    del b.manifest["volume"]["voxel_size"]
    b.save()
    expect_error(b.root, file=b.path, camera="cam00", field="cameras[0].t", match="calibration in millimetres?")
