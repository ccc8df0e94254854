"""Every common input (issue 15, item 3): image sequences in every form, multi-page TIFF,
interlaced fields, one container list, calibration import, the printable board, and an
init that leaves nothing behind when it fails."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest
import yaml

from schlieren.storage.errors import SchlierenInputError, SessionError
from schlieren.storage.frames import (ImageFiles, ImageSequence, InterlacedFields, MultiPageTiff, frames_kind,
                                      open_frames, read_reference)
from schlieren.storage.session import load_session


# ---- frame readers ------------------------------------------------------------------------
def test_pattern_glob_and_folder_read_the_same_frames_in_natural_order(tmp_path):
    d = tmp_path / "cam00" / "frames"
    d.mkdir(parents=True)
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 65536, (12, 6, 8)).astype(np.uint16)
    for k, f in enumerate(frames):
        cv2.imwrite(str(d / f"img{k}.png"), f)  # img10 sorts after img9 in natural order
    pattern = ImageSequence(str(d / "img%d.png"))
    for src in (pattern, ImageFiles(str(d / "img*.png")), ImageFiles(str(d)),
                open_frames(str(d) + "/"), open_frames(str(d / "*.png"))):
        assert len(src) == 12
        for k in (0, 9, 10, 11):
            np.testing.assert_array_equal(src.read(k), frames[k].astype(np.float32))  # 16-bit values kept
    assert [frames_kind(s) for s in (str(d / "%05d.png"), str(d / "*.png"), str(d), "a/cam.MTS", "x.m2ts",
                                     "stack.tif", "ref.png")] == \
        ["sequence", "glob", "folder", "video", "video", "tiff", "image"]


def test_multi_page_tiff_frames(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(2)
    pages = rng.integers(0, 65536, (4, 5, 7)).astype(np.uint16)
    path = tmp_path / "stack.tif"
    Image.fromarray(pages[0]).save(path, save_all=True, append_images=[Image.fromarray(p) for p in pages[1:]])
    src = open_frames(str(path), camera_name="cam00")
    assert isinstance(src, MultiPageTiff) and len(src) == 4 and src.size == (7, 5)
    for k in range(4):
        np.testing.assert_array_equal(src.read(k), pages[k].astype(np.float32))
    np.testing.assert_allclose(read_reference(str(path)), pages.mean(axis=0), rtol=1e-6)
    with pytest.raises(SessionError, match="outside the 4 frames"):
        src.read(4)


class _Frames:
    """A frame source of known frames (for the field splitter)."""

    path = "mem"
    camera_name = "cam00"

    def __init__(self, frames):
        self.frames = frames

    def __len__(self):
        return len(self.frames)

    def read(self, i):
        return self.frames[i]

    def file_of(self, i):
        return "mem"


def test_interlaced_fields_keep_their_rows_and_interpolate_the_others():
    H, W = 8, 3
    r = np.arange(H, dtype=np.float32)[:, None] * np.ones((1, W), np.float32)
    frame = np.where((np.arange(H) % 2 == 0)[:, None], r, 1000 + r)  # even rows r, odd rows 1000 + r
    top = InterlacedFields(_Frames([frame, frame + 1]), "top_first")
    assert len(top) == 4 and top.file_of(3) == "mem"
    f0, f1, f2 = top.read(0), top.read(1), top.read(2)
    np.testing.assert_array_equal(f0[0::2], frame[0::2])          # field 0: the even rows
    np.testing.assert_array_equal(f0[1:-1:2], r[1:-1:2])           # odd rows: mean of r-1 and r+1
    np.testing.assert_array_equal(f0[-1], frame[-2])                # last row repeats its neighbour
    np.testing.assert_array_equal(f1[1::2], frame[1::2])          # field 1: the odd rows
    np.testing.assert_array_equal(f1[2::2], 1000 + r[2::2])
    np.testing.assert_array_equal(f2, f0 + 1)                       # field 2 = frame 1's first field
    bottom = InterlacedFields(_Frames([frame]), "bottom_first")
    np.testing.assert_array_equal(bottom.read(0), f1)


def test_one_container_list_for_every_reader():
    from schlieren.storage import calibration_io, frames

    assert set(calibration_io.VIDEO_EXTENSIONS) == set(frames.VIDEO_EXTENSIONS) >= {".mts", ".m2ts", ".mp4"}
    assert set(calibration_io.IMAGE_EXTENSIONS) == set(frames.IMAGE_EXTENSIONS)


# ---- the session manifest -------------------------------------------------------------------
def test_sessions_take_globs_and_folders(session_builder):
    b = session_builder
    b.camera(0)["frames"] = "cam00/frames/*.png"
    b.camera(1)["frames"] = "cam01/frames/"
    b.save()
    s = load_session(b.root)
    assert s.n_frames_available == b.n_frames
    np.testing.assert_array_equal(s.sources[1].open_frames().read(3), b.frames["cam01"][3].astype(np.float32))


def test_interlaced_session_doubles_the_frame_rate_and_halves_the_line_time(session_builder):
    b = session_builder
    for c in b.manifest["cameras"]:
        c["interlaced"] = "top_first"
    b.save()
    s = load_session(b.root)
    assert s.frame_rate == 120.0 and s.n_frames_available == 2 * b.n_frames
    assert all(c.line_time == pytest.approx(0.5e-5) for c in s.cameras)
    assert isinstance(s.sources[0].open_frames(), InterlacedFields)
    b.camera(2)["interlaced"] = None
    b.save()
    with pytest.raises(SessionError, match="some cameras are interlaced") as info:
        load_session(b.root)
    assert info.value.camera == "cam02" and info.value.field == "cameras[2].interlaced"


def test_cameras_of_different_sizes_are_refused_before_any_work(session_builder):
    b = session_builder
    name = b.camera(1)["name"]
    for f in sorted((b.root / name / "frames").glob("*.png")) + [b.root / name / "reference.png"]:
        cv2.imwrite(str(f), np.zeros((30, 48), np.uint8))
    b.camera(1)["image_size"] = [48, 30]
    b.save()
    with pytest.raises(SessionError, match=r"image_size \[48, 30\] differs from camera cam00's \[40, 30\]") as info:
        load_session(b.root)
    assert (info.value.camera, info.value.field) == ("cam01", "cameras[1].image_size")


def test_a_strobe_window_too_short_is_refused(session_builder):
    b = session_builder
    b.manifest["sync"] = {"strobe": {"search_frames": [0, 2]}}
    b.save()
    with pytest.raises(SessionError, match="at least 3") as info:
        load_session(b.root)
    assert info.value.field == "sync.strobe.search_frames"


# ---- calibration import -----------------------------------------------------------------------
def _rig(n=3):
    from test_scaffold import look_at

    out = []
    for i in range(n):
        a = np.radians(-90 + 40 * i)
        R, t = look_at(2.5 * np.array([np.cos(a), np.sin(a), 0.2]))
        out.append((f"cam{i}", R, t))
    return out


def write_opencv(path, K, dist, R, t, size, *, rvec=False):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(size[0]))
    fs.write("image_height", int(size[1]))
    fs.write("camera_matrix", np.asarray(K, np.float64))
    fs.write("distortion_coefficients", np.asarray(dist, np.float64).reshape(1, -1))
    if rvec:
        fs.write("rvec", cv2.Rodrigues(np.asarray(R, np.float64))[0])
    else:
        fs.write("R", np.asarray(R, np.float64))
    fs.write("T", np.asarray(t, np.float64).reshape(3, 1))
    fs.release()
    return path


@pytest.mark.parametrize("ext, rvec", [("yml", False), ("xml", True)])
def test_opencv_filestorage_import(tmp_path, ext, rvec):
    from schlieren.storage.calibration_io import import_calibration

    K = [[500.0, 0, 319.5], [0, 505.0, 239.5], [0, 0, 1]]
    files = []
    for name, R, t in _rig():
        files.append(write_opencv(tmp_path / f"{name}.{ext}", K, [0.1, -0.05, 1e-3, 2e-3, 0.01], R, t, (640, 480),
                                  rvec=rvec))
    cal = import_calibration([str(tmp_path / f"*.{ext}")])
    assert cal.names == ["cam0", "cam1", "cam2"]
    for (name, R, t), entry in zip(_rig(), cal.cameras):
        assert entry["image_size"] == [640, 480] and entry["K"] == K
        np.testing.assert_allclose(entry["R"], R, atol=1e-9)
        np.testing.assert_allclose(entry["t"], t, atol=1e-12)
        np.testing.assert_allclose(entry["dist"], [0.1, -0.05, 1e-3, 2e-3, 0.01])
    named = import_calibration([f"left={files[0]}"])
    assert named.names == ["left"]
    fs = cv2.FileStorage(str(tmp_path / "nopose.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.asarray(K))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    with pytest.raises(SchlierenInputError, match="no camera pose") as info:
        import_calibration([str(tmp_path / "nopose.yml")])
    assert info.value.camera == "nopose" and info.value.field == "R"


def test_kalibr_camchain_import(tmp_path):
    from schlieren.storage.calibration_io import import_calibration

    rig = _rig(3)
    doc = {}
    prev = np.eye(4)
    for i, (name, R, t) in enumerate(rig):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        if i == 0:  # Kalibr's world is cam0: express every camera relative to it
            T0inv = np.linalg.inv(T)
        rel = T @ T0inv
        entry = {"camera_model": "pinhole", "intrinsics": [400.0, 401.0, 320.0, 240.0],
                 "distortion_model": "radtan", "distortion_coeffs": [0.01, -0.02, 1e-4, 2e-4],
                 "resolution": [640, 480], "rostopic": f"/{name}/image_raw"}
        if i:
            entry["T_cn_cnm1"] = (rel @ np.linalg.inv(prev)).tolist()
        prev = rel
        doc[f"cam{i}"] = entry
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(doc))
    cal = import_calibration(str(tmp_path / "camchain.yaml"))
    assert cal.names == ["cam0", "cam1", "cam2"]
    np.testing.assert_allclose(cal.cameras[0]["R"], np.eye(3), atol=1e-12)
    for (name, R, t), entry in zip(rig, cal.cameras):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        rel = T @ T0inv  # the camera's pose in cam0's frame
        np.testing.assert_allclose(entry["R"], rel[:3, :3], atol=1e-9)
        np.testing.assert_allclose(entry["t"], rel[:3, 3], atol=1e-9)
        assert entry["K"] == [[400.0, 0.0, 320.0], [0.0, 401.0, 240.0], [0.0, 0.0, 1.0]]
        assert entry["dist"] == [0.01, -0.02, 1e-4, 2e-4]


def test_documented_json_form(tmp_path):
    from schlieren.storage.calibration_io import import_calibration

    name, R, t = _rig(1)[0]
    doc = {"format": "schlieren-calibration/1",
           "cameras": [{"name": "cam0", "image_size": [640, 480], "K": [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]],
                        "dist": [0, 0, 0, 0, 0], "R": R.tolist(), "t": t.tolist(), "background": {"distance": 4.0}}]}
    (tmp_path / "rig.json").write_text(json.dumps(doc))
    cal = import_calibration(str(tmp_path / "rig.json"))
    assert cal.names == ["cam0"] and cal.camera("cam0")["background"] == {"distance": 4.0}


# ---- init ---------------------------------------------------------------------------------
def _sequence_rig(root, n=12, size=(64, 48)):
    """Three cameras recorded as PNG folders, calibrated as OpenCV YAML files."""
    from test_scaffold import make_calibration

    rng = np.random.default_rng(0)
    seqs = {}
    for i in range(3):
        d = root / "capture" / f"cam{i}" / "frames"
        d.mkdir(parents=True)
        base = rng.integers(40, 200, (size[1], size[0]))
        stack = np.stack([np.clip(base + 3 * k, 0, 255) for k in range(n)]).astype(np.uint8)
        for k in range(n):
            cv2.imwrite(str(d / f"{k:04d}.png"), stack[k])
        seqs[f"cam{i}"] = stack
    cal = yaml.safe_load(open(make_calibration(root / "cal.yaml", size=size)))
    for c in cal["cameras"]:
        write_opencv(root / f"{c['name']}.yml", c["K"], c["dist"], c["R"], c["t"], size)
    return seqs


def test_init_from_image_sequences_and_opencv_calibration(tmp_path, capsys):
    from schlieren.workers.cli import main

    seqs = _sequence_rig(tmp_path)
    session = tmp_path / "session"
    code = main(["init", str(session), "--images", str(tmp_path / "capture" / "cam0" / "frames"),
                 str(tmp_path / "capture" / "cam1" / "frames" / "%04d.png"),
                 str(tmp_path / "capture" / "cam2" / "frames" / "*.png"),
                 "--calibration", str(tmp_path / "cam*.yml"), "--reference-frames", "0:4",
                 "--frame-rate", "25", "--time-offset", "0", "--background-distance", "5",
                 "--volume=-0.1,-0.1,0,0.1,0.1,0.2", "--voxel-size", "0.01", "--copy-videos"])
    assert code == 0, capsys.readouterr().err
    s = load_session(session)
    assert s.camera_names == ["cam0", "cam1", "cam2"] and s.frame_rate == 25.0 and s.n_frames_available == 12
    doc = yaml.safe_load((session / "session.yaml").read_text())
    assert [c["frames"] for c in doc["cameras"]] == ["cam0/frames/", "cam1/frames/%04d.png", "cam2/frames/*.png"]
    for name, stack in seqs.items():
        np.testing.assert_allclose(read_reference(s.source(name)), stack[:4].mean(axis=0), atol=1e-4)
        np.testing.assert_array_equal(s.source(name).open_frames().read(7), stack[7].astype(np.float32))


def test_a_failed_init_leaves_nothing_behind(tmp_path, capsys):
    from schlieren.workers.cli import main

    _sequence_rig(tmp_path)
    bad = tmp_path / "capture" / "cam2" / "frames" / "0002.png"
    good = bad.read_bytes()
    bad.write_bytes(b"not a png")  # in the reference range: found while extracting the reference
    session = tmp_path / "session"
    args = ["init", str(session), "--images"] + [str(tmp_path / "capture" / f"cam{i}" / "frames") for i in range(3)] + [
        "--calibration", str(tmp_path / "cam*.yml"), "--reference-frames", "0:4", "--frame-rate", "25",
        "--time-offset", "0", "--background-distance", "5", "--volume=-0.1,-0.1,0,0.1,0.1,0.2",
        "--voxel-size", "0.01"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "0002.png" in err and "cam2" in err
    assert not session.exists()
    bad.write_bytes(good)
    assert main(args) == 0  # the retry is not refused
    assert (session / "session.yaml").is_file()


# ---- the printable board ------------------------------------------------------------------------
def test_board_prints_a_detectable_charuco_at_the_stated_dpi(tmp_path, capsys):
    from PIL import Image

    from schlieren.pipeline.calibration import BoardSpec, detect_board
    from schlieren.workers.cli import main

    assert main(["board", str(tmp_path), "--dpi", "100", "--background", "0.1x0.05",
                 "--feature-size", "0.002"]) == 0
    out = capsys.readouterr().out
    assert "charuco.png" in out and "background.png" in out
    with Image.open(tmp_path / "charuco.png") as im:
        assert im.info["dpi"] == pytest.approx((100, 100), abs=0.01)
        img = np.asarray(im)
    det = detect_board(img, BoardSpec((10, 7), 0.03, 0.022))
    assert len(det) == 9 * 6  # every inner corner found
    with Image.open(tmp_path / "background.png") as im:
        assert im.size == (round(0.1 / 0.0254 * 100), round(0.05 / 0.0254 * 100))
        bg = np.asarray(im, dtype=float)
    assert bg.std() > 20  # a textured pattern, not a flat page
