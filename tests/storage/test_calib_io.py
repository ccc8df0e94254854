"""Calibration file round trip and validation; reading board views (storage/calibration_io/)."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
import yaml

from schlieren.pipeline.calibration import BoardSpec, CameraCalibration, RigCalibration
from schlieren.pipeline.geometry import rodrigues
from schlieren.storage.calibration_io import (
    CALIBRATION_FORMAT,
    iter_board_frames,
    read_calibration,
    resolve_source,
    write_calibration,
)
from schlieren.storage.errors import SchlierenInputError

BOARD = BoardSpec((10, 7), 0.03, 0.022)


def make_rig():
    cams = []
    for i in range(3):
        R = rodrigues([0.1 * i, 0.5 - 0.3 * i, 0.02])
        t = np.array([0.01 * i, -0.02, 2.5])
        K = np.array([[1500.0 + i, 0.0, 480.5], [0.0, 1501.0, 359.25], [0.0, 0.0, 1.0]])
        bg = ({"distance": 4.0} if i == 2 else
              {"point": -R.T @ t + 5.0 * R[2], "normal": -R[2]})
        cams.append(CameraCalibration(f"cam{i:02d}", (960, 720), K, np.array([-0.1, 0.05, 1e-3, -2e-4, 0.0]),
                                      R, t, rms=0.08 + 0.01 * i, n_views=20 + i, n_points=900,
                                      rms_intrinsic=0.07, background=bg))
    return RigCalibration(tuple(cams), {}, 0, "flat", 0.09)


def test_round_trip_keeps_every_number(tmp_path):
    rig = make_rig()
    path = write_calibration(tmp_path / "sub" / "calibration.yaml", rig, board=BOARD,
                             sources={"cam00": "calib/cam00.mp4"})
    doc = yaml.safe_load(path.read_text())
    assert doc["format"] == CALIBRATION_FORMAT
    assert doc["board"]["squares"] == [10, 7] and doc["board"]["dictionary"] == "DICT_5X5_100"
    assert doc["cameras"][0]["source"] == "calib/cam00.mp4"
    cf = read_calibration(path)
    assert cf.names == ["cam00", "cam01", "cam02"]
    for c in rig.cameras:
        e = cf.camera(c.name)
        np.testing.assert_array_equal(e["K"], c.K)  # repr round trip of float64 is exact
        np.testing.assert_array_equal(e["R"], c.R)
        np.testing.assert_array_equal(e["t"], c.t)
        np.testing.assert_array_equal(e["dist"], c.dist)
        assert e["image_size"] == [960, 720]
        assert e["n_views"] == c.n_views and e["rms"] == pytest.approx(c.rms, abs=1e-5)
        cam = cf.camera_object(c.name)
        X = np.array([[0.1, -0.05, 0.2], [0.0, 0.0, 0.0]])
        uv, _ = cv2.projectPoints(X, cv2.Rodrigues(c.R)[0], c.t, c.K, c.dist)
        np.testing.assert_allclose(cam.project(X), uv.reshape(-1, 2), atol=1e-9)
        assert cam.background_distance() > 0
    assert cf.camera("cam02")["background"] == {"distance": 4.0}
    c2 = rig.cameras[2]
    np.testing.assert_allclose(cf.camera_object("cam02").bg_point, c2.center + 4.0 * c2.R[2])


def _behind(entry):
    R, t = np.asarray(entry["R"]), np.asarray(entry["t"])
    return (-R.T @ t - 3.0 * R[2]).tolist()


def _write(tmp_path, mutate):
    path = write_calibration(tmp_path / "c.yaml", make_rig(), board=BOARD)
    doc = yaml.safe_load(path.read_text())
    mutate(doc)
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize("mutate, camera, field, words", [
    (lambda d: d.update(format="schlieren-calibration/9"), None, "format", "unknown format"),
    (lambda d: d["cameras"][1].update(R=(2 * np.eye(3)).tolist()), "cam01", "cameras[1].R", "not a rotation"),
    (lambda d: d["cameras"][1].update(R=np.diag([1.0, 1.0, -1.0]).tolist()), "cam01", "cameras[1].R",
     "not a rotation"),
    (lambda d: d["cameras"][2].update(dist=[0.1, 0.2, 0.3]), "cam02", "cameras[2].dist", "got 3"),
    (lambda d: d["cameras"][0].pop("t"), "cam00", "cameras[0].t", "missing"),
    (lambda d: d["cameras"][0].update(K=[[1.0, 0.0], [0.0, 1.0]]), "cam00", "cameras[0].K", "shape"),
    (lambda d: d["cameras"][0].update(image_size=[960]), "cam00", "cameras[0].image_size", "width, height"),
    (lambda d: d["cameras"][1].update(name="cam00"), "cam00", "cameras", "duplicate"),
    (lambda d: d["cameras"][0]["background"].update(point=_behind(d["cameras"][0])), "cam00",
     "cameras[0].background", "behind the camera"),
    (lambda d: d["cameras"][2].update(background={"distance": -1.0}), "cam02",
     "cameras[2].background.distance", "positive"),
])
def test_bad_calibration_files_name_camera_and_field(tmp_path, mutate, camera, field, words):
    path = _write(tmp_path, mutate)
    with pytest.raises(SchlierenInputError) as info:
        read_calibration(path)
    err = info.value
    assert err.camera == camera and err.field == field and err.file == str(path)
    assert words in str(err)
    assert "\n" not in str(err)


def test_rvec_is_accepted_instead_of_R(tmp_path):
    rig = make_rig()

    def to_rvec(d):
        d["cameras"][0]["rvec"] = cv2.Rodrigues(np.asarray(d["cameras"][0].pop("R")))[0].ravel().tolist()

    cf = read_calibration(_write(tmp_path, to_rvec))
    np.testing.assert_allclose(cf.camera("cam00")["R"], rig.cameras[0].R, atol=1e-12)
    assert "rvec" not in cf.camera("cam00")


def test_unreadable_calibration_files(tmp_path):
    with pytest.raises(SchlierenInputError, match="not found"):
        read_calibration(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cameras: [\n  - {name: a\n")
    with pytest.raises(SchlierenInputError, match="not valid YAML at line"):
        read_calibration(bad)


# ----------------------------------------------------------------------------------
# board views
# ----------------------------------------------------------------------------------
def _frame(i, size=(32, 24)):
    img = np.zeros((size[1], size[0], 3), np.uint8)
    img[:, :, 1] = 10 * i
    return img


def test_sources_from_folders_globs_videos_and_names(tmp_path):
    d = tmp_path / "calib" / "cam03"
    d.mkdir(parents=True)
    for i in range(5):
        cv2.imwrite(str(d / f"img{i:02d}.png"), _frame(i))
    (d / "notes.txt").write_text("not an image")
    s = resolve_source(str(d))
    assert s.name == "cam03" and s.kind == "images" and len(s.paths) == 5
    s = resolve_source(str(tmp_path / "calib" / "cam03" / "img*.png"))
    assert s.name == "cam03" and len(s.paths) == 5
    s = resolve_source("left=" + str(d))
    assert s.name == "left"
    s = resolve_source("calib/cam03", base=tmp_path)
    assert s.name == "cam03"
    with pytest.raises(SchlierenInputError, match="one image is not enough"):
        resolve_source(str(d / "img00.png"))
    assert resolve_source(str(d / "img00.png"), single_image=True).name == "img00"
    with pytest.raises(SchlierenInputError, match="no such") as info:
        resolve_source("side=" + str(tmp_path / "missing"))
    assert info.value.camera == "side"
    with pytest.raises(SchlierenInputError, match="matches no image"):
        resolve_source(str(tmp_path / "calib" / "*.jpg"))

    views = list(iter_board_frames(resolve_source(str(d)), step=2))
    assert [v for v, _ in views] == [0, 1, 2]
    assert [int(img[0, 0, 1]) for _, img in views] == [0, 20, 40]  # images 0, 2, 4


def test_video_views_with_step(tmp_path):
    path = str(tmp_path / "cam07.avi")
    w = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"FFV1"), 10.0, (32, 24))
    for i in range(7):
        w.write(_frame(i))
    w.release()
    s = resolve_source(path)
    assert s.name == "cam07" and s.kind == "video"
    views = list(iter_board_frames(s, step=3))
    assert [v for v, _ in views] == [0, 1, 2]
    assert [int(round(img[..., 1].mean())) for _, img in views] == [0, 30, 60]  # frames 0, 3, 6
    assert len(list(iter_board_frames(s, max_views=2))) == 2


def test_unreadable_or_mismatched_images_are_named(tmp_path):
    d = tmp_path / "cam01"
    d.mkdir()
    cv2.imwrite(str(d / "a.png"), _frame(0))
    cv2.imwrite(str(d / "b.png"), _frame(1, size=(40, 24)))
    with pytest.raises(SchlierenInputError, match="differs from the first") as info:
        list(iter_board_frames(resolve_source(str(d))))
    assert info.value.camera == "cam01" and info.value.file.endswith("b.png")
    os.remove(d / "b.png")
    (d / "c.png").write_bytes(b"not a png")
    with pytest.raises(SchlierenInputError, match="cannot read the image") as info:
        list(iter_board_frames(resolve_source(str(d))))
    assert info.value.file.endswith("c.png")


def test_layering_of_the_calibration_modules():
    """pipeline.calibration imports neither storage nor dask/zarr; the storage modules no dask."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import schlieren.pipeline.calibration\n"
        "a = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'zarr')\n"
        "           or m.startswith(('schlieren.storage', 'schlieren.workers')))\n"
        "import schlieren.storage.calibration_io, schlieren.storage.scaffold\n"
        "b = sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed'})\n"
        "print(','.join(a) + '|' + ','.join(b))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "|"
