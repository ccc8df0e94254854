"""``schlieren init`` scaffolding (storage/scaffold/): videos + calibration -> a session
that storage.session.load_session accepts, and refusals that name the camera."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
import yaml

from schlieren.pipeline.calibration import BoardSpec, CameraCalibration, RigCalibration
from schlieren.storage.calibration_io import read_calibration, write_calibration
from schlieren.storage.errors import SchlierenInputError
from schlieren.storage.scaffold import find_videos, probe_video, scaffold_session
from schlieren.storage.frames import read_reference
from schlieren.storage.session import load_session

SIZE = (64, 48)
N_FRAMES = 12
FPS = 25.0
VOLUME = dict(volume_min=(-0.1, -0.1, 0.0), volume_max=(0.1, 0.1, 0.2), voxel_size=0.01)


def look_at(C, target=(0.0, 0.0, 0.1)):
    z = np.asarray(target) - C
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ C


def make_calibration(path, names=("cam0", "cam1", "cam2"), size=SIZE, background=True):
    cams = []
    for i, n in enumerate(names):
        a = np.radians(-90 + 40 * i)
        R, t = look_at(2.5 * np.array([np.cos(a), np.sin(a), 0.2]))
        K = np.array([[80.0, 0, size[0] / 2 - 0.5], [0, 80.0, size[1] / 2 - 0.5], [0, 0, 1]])
        bg = {"distance": 5.0} if background else None
        cams.append(CameraCalibration(n, size, K, np.zeros(5), R, t, rms=0.1, n_views=20, background=bg))
    return write_calibration(path, RigCalibration(tuple(cams)), board=BoardSpec((10, 7), 0.03, 0.022))


def make_video(path, n=N_FRAMES, size=SIZE, fps=FPS, seed=0):
    """Lossless (FFV1) video of a random grey pattern whose brightness changes per frame."""
    rng = np.random.default_rng(seed)
    base = rng.integers(40, 200, (size[1], size[0])).astype(np.int32)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, size)
    assert w.isOpened()
    for i in range(n):
        g = np.clip(base + 3 * i, 0, 255).astype(np.uint8)
        w.write(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
    w.release()
    return str(path)


def decoded_grey(path):
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        out.append(cv2.cvtColor(img.astype(np.float32), cv2.COLOR_BGR2GRAY))
    return np.stack(out)


@pytest.fixture
def rig(tmp_path):
    session = tmp_path / "session"
    (session / "cams").mkdir(parents=True)
    videos = {f"cam{i}": make_video(session / "cams" / f"cam{i}.avi", seed=i) for i in range(3)}
    calib = make_calibration(tmp_path / "calibration.yaml")
    return session, videos, calib


def test_scaffolded_session_loads_with_its_reference_frames(rig):
    session, videos, calib = rig
    found = find_videos([str(session / "cams" / "*.avi")])
    assert found == videos
    path = scaffold_session(session, found, calib, reference_frames=(0, 4), frames=(8, 12),
                            strobe_frames=(4, 8), line_times=1.5e-5, **VOLUME)
    doc = yaml.safe_load(path.read_text())
    assert doc["format"] == "schlieren-session/1" and "allow_external_paths" not in doc
    assert doc["cameras"][0]["frames"] == "cams/cam0.avi"  # relative to the session folder
    assert doc["cameras"][0]["reference"] == "cam0/reference/%05d.png"

    s = load_session(session)
    assert s.camera_names == ["cam0", "cam1", "cam2"]
    assert s.frame_rate == pytest.approx(FPS)
    assert s.frames == (8, 12) and s.n_frames_available == N_FRAMES
    assert s.strobe_search == (4, 8)
    assert s.grid.shape == (20, 20, 20)
    calib_doc = yaml.safe_load(open(calib))
    for cam, entry in zip(s.cameras, calib_doc["cameras"]):
        np.testing.assert_array_equal(cam.K, entry["K"])
        np.testing.assert_array_equal(cam.R, entry["R"])
        np.testing.assert_array_equal(cam.t, entry["t"])
        assert cam.line_time == 1.5e-5
        assert cam.background_distance() == pytest.approx(5.0)
    # The reference is the average of the video's first four frames, on the frames' scale.
    for name in videos:
        ref = read_reference(s.source(name))
        expected = decoded_grey(videos[name])[0:4].mean(axis=0)
        np.testing.assert_allclose(ref, expected, atol=1e-4)
        frame5 = s.source(name).open_frames().read(5)
        np.testing.assert_allclose(frame5, decoded_grey(videos[name])[5], atol=1e-4)


def test_videos_outside_the_session_are_referenced_or_copied(tmp_path):
    outside = tmp_path / "capture"
    outside.mkdir()
    videos = {f"cam{i}": make_video(outside / f"cam{i}.avi", seed=i) for i in range(3)}
    calib = make_calibration(tmp_path / "calibration.yaml")
    s1 = tmp_path / "s1"
    scaffold_session(s1, videos, calib, reference_frames=(0, 3), time_offsets=0.0, **VOLUME)
    doc = yaml.safe_load((s1 / "session.yaml").read_text())
    assert doc["allow_external_paths"] is True
    assert doc["cameras"][1]["frames"] == os.path.abspath(videos["cam1"])
    assert [c["time_offset"] for c in doc["cameras"]] == [0.0, 0.0, 0.0]
    assert load_session(s1).n_frames_available == N_FRAMES

    s2 = tmp_path / "s2"
    scaffold_session(s2, videos, calib, reference_frames=(0, 3),
                     time_offsets={"cam0": 0.0, "cam1": 0.001, "cam2": -0.002}, copy_videos=True, **VOLUME)
    doc = yaml.safe_load((s2 / "session.yaml").read_text())
    assert "allow_external_paths" not in doc
    assert doc["cameras"][2]["frames"] == "cam2/cam2.avi"
    assert [c.time_offset for c in load_session(s2).cameras] == [0.0, 0.001, -0.002]


def test_background_distance_fills_a_calibration_without_planes(tmp_path):
    session = tmp_path / "s"
    session.mkdir()
    videos = {f"cam{i}": make_video(session / f"cam{i}.avi", seed=i) for i in range(3)}
    calib = make_calibration(tmp_path / "c.yaml", background=False)
    with pytest.raises(SchlierenInputError, match="no background plane") as info:
        scaffold_session(session, videos, calib, reference_frames=(0, 3), time_offsets=0.0, **VOLUME)
    assert info.value.camera == "cam0" and info.value.field == "background"
    scaffold_session(session, videos, calib, reference_frames=(0, 3), time_offsets=0.0,
                     background_distance={"cam0": 4.0, "cam1": 4.5, "cam2": 5.0}, **VOLUME)
    s = load_session(session)
    assert [round(c.background_distance(), 9) for c in s.cameras] == [4.0, 4.5, 5.0]


def _replace_video(session, name, **kw):
    path = session / "cams" / f"{name}.avi"
    os.remove(path)
    make_video(path, **kw)


@pytest.mark.parametrize("change, camera, field, words", [
    (lambda s: _replace_video(s, "cam1", n=N_FRAMES - 1), "cam1", "frames", "has 11 frames"),
    (lambda s: _replace_video(s, "cam2", size=(48, 64)), "cam2", "image_size", "48x64"),
    (lambda s: _replace_video(s, "cam1", fps=30.0), "cam1", "frame_rate", "30 fps"),
])
def test_disagreeing_videos_name_the_camera(rig, change, camera, field, words):
    session, videos, calib = rig
    change(session)
    with pytest.raises(SchlierenInputError) as info:
        scaffold_session(session, videos, calib, reference_frames=(0, 4), strobe_frames=(4, 8), **VOLUME)
    err = info.value
    assert (err.camera, err.field) == (camera, field)
    assert words in str(err) and err.file.endswith(f"{camera}.avi")
    assert not (session / "session.yaml").exists()


def test_other_refusals(rig, tmp_path):
    session, videos, calib = rig
    kw = dict(reference_frames=(0, 4), strobe_frames=(4, 8), **VOLUME)
    with pytest.raises(SchlierenInputError, match="no camera of that name") as info:
        scaffold_session(session, {**videos, "cam9": videos["cam0"]}, calib, **kw)
    assert info.value.camera == "cam9"
    with pytest.raises(SchlierenInputError, match="--strobe-frames A:B") as info:
        scaffold_session(session, videos, calib, reference_frames=(0, 4), **VOLUME)
    assert info.value.field == "time_offset"
    with pytest.raises(SchlierenInputError, match="beyond the 12 frames"):
        scaffold_session(session, videos, calib, reference_frames=(0, 40), strobe_frames=(4, 8), **VOLUME)
    with pytest.raises(SchlierenInputError, match="no camera sees the volume"):
        scaffold_session(session, videos, calib, reference_frames=(0, 4), strobe_frames=(4, 8),
                         volume_min=(5.0, 5.0, 5.0), volume_max=(5.2, 5.2, 5.2), voxel_size=0.01)
    with pytest.raises(SchlierenInputError, match="frame rate must be positive"):
        scaffold_session(session, videos, calib, frame_rate=-1.0, **kw)
    scaffold_session(session, videos, calib, **kw)
    with pytest.raises(SchlierenInputError, match="already exists"):
        scaffold_session(session, videos, calib, **kw)
    scaffold_session(session, videos, calib, overwrite=True, **kw)
    with pytest.raises(SchlierenInputError, match="no video, image sequence or multi-page TIFF matches"):
        find_videos([str(tmp_path / "nothing" / "*.mp4")])


def test_probe_video_counts(rig):
    _, videos, _ = rig
    info = probe_video(videos["cam0"], count_frames=True)
    assert (info.frame_count, info.size, info.fps) == (N_FRAMES, SIZE, FPS)
    with pytest.raises(SchlierenInputError, match="not found"):
        probe_video("/nonexistent/cam.mp4", camera="camX")
    with open(videos["cam1"], "wb") as fh:
        fh.write(b"\x00garbage" * 100)
    with pytest.raises(SchlierenInputError, match="cannot") as info:
        probe_video(videos["cam1"], camera="cam1")
    assert info.value.camera == "cam1" and info.value.file == videos["cam1"]


# ---- image sequences, the automatic voxel and the strobe window (issue 36) -----------------
def make_sequences(session, names=("cam0", "cam1", "cam2"), n=N_FRAMES, size=SIZE):
    """One folder of numbered PNG frames per camera, ``session/<name>/frames/00000.png``..."""
    out = {}
    for i, name in enumerate(names):
        d = session / name / "frames"
        d.mkdir(parents=True)
        rng = np.random.default_rng(i)
        base = rng.integers(40, 200, (size[1], size[0]))
        for k in range(n):
            assert cv2.imwrite(str(d / f"{k:05d}.png"), np.clip(base + 3 * k, 0, 255).astype(np.uint8))
        out[name] = str(d)
    return out


def test_a_folder_sequence_with_a_missing_file_is_a_dropped_frame(tmp_path):
    """A file missing between numbered files of a folder is a frame the camera dropped
    (its slot keeps the timing), not "14 frames but 15: trim the videos"."""
    session = tmp_path / "s"
    folders = make_sequences(session)
    os.remove(session / "cam1" / "frames" / "00005.png")
    os.remove(session / "cam2" / "frames" / "00002.png")  # inside the reference frames
    calib = make_calibration(tmp_path / "calibration.yaml")
    scaffold_session(session, folders, calib, reference_frames=(0, 4), frames=(4, 12), frame_rate=FPS,
                     time_offsets=0.0, **VOLUME)
    s = load_session(session)
    assert s.n_frames_available == N_FRAMES and s.dropped_frames == {"cam1": (5,), "cam2": (2,)}
    src = s.source("cam1").open_frames()
    np.testing.assert_array_equal(src.read(6), cv2.imread(str(session / "cam1" / "frames" / "00006.png"), 0))
    # cam2's reference: the three frames of 0:4 that exist
    ref = read_reference(s.source("cam2"))
    want = np.mean([cv2.imread(str(session / "cam2" / "frames" / f"{k:05d}.png"), 0).astype(np.float64)
                    for k in (0, 1, 3)], axis=0)
    np.testing.assert_allclose(ref, want, atol=1e-4)


def test_image_sequences_are_not_called_videos(tmp_path):
    session = tmp_path / "s"
    folders = make_sequences(session)
    os.remove(session / "cam1" / "frames" / f"{N_FRAMES - 1:05d}.png")  # the last one: a shorter recording
    calib = make_calibration(tmp_path / "calibration.yaml")
    with pytest.raises(SchlierenInputError) as info:
        scaffold_session(session, folders, calib, reference_frames=(0, 4), frame_rate=FPS, time_offsets=0.0,
                         **VOLUME)
    text = str(info.value)
    assert info.value.camera == "cam1" and info.value.field == "frames"
    assert "image sequence has 11 frames" in text and "video" not in text, text
    with pytest.raises(SchlierenInputError) as info:
        scaffold_session(session, folders, calib, reference_frames=(0, 40), frame_rate=FPS, time_offsets=0.0,
                         **VOLUME)
    assert "video" not in str(info.value), str(info.value)


def test_init_without_voxel_size_uses_the_automatic_voxel(rig, tmp_path, capsys):
    from schlieren.pipeline.geometry import auto_voxel_size
    from schlieren.workers.cli import main

    session, videos, calib = rig
    code = main(["init", str(session), "--videos", str(session / "cams" / "*.avi"), "--calibration", str(calib),
                 "--reference-frames", "0:4", "--frames", "8:12", "--strobe-frames", "4:8",
                 "--volume=-0.1,-0.1,0.0,0.1,0.1,0.2"])
    out = capsys.readouterr()
    assert code == 0, out.err
    doc = yaml.safe_load((session / "session.yaml").read_text())
    assert "voxel_size" not in doc["volume"]
    s = load_session(session)
    voxel, _ = auto_voxel_size(s.cameras, (-0.1, -0.1, 0.0), (0.1, 0.1, 0.2))
    assert s.grid.voxel_size == pytest.approx(voxel)
    assert "chosen from the cameras" in out.out


def test_a_strobe_window_overlapping_the_processed_frames_is_refused(rig):
    session, videos, calib = rig
    with pytest.raises(SchlierenInputError, match="overlap") as info:
        scaffold_session(session, videos, calib, reference_frames=(0, 4), frames=(6, 12), strobe_frames=(4, 8),
                         **VOLUME)
    assert info.value.field == "sync.strobe.search_frames" and "\n" not in str(info.value)
    assert not (session / "session.yaml").exists()
    # without --frames, the frames processed are those after the strobe window
    scaffold_session(session, videos, calib, reference_frames=(0, 4), strobe_frames=(4, 8), **VOLUME)
    assert yaml.safe_load((session / "session.yaml").read_text())["frames"] == [8, 12]
    assert load_session(session).frames == (8, 12)


def test_init_refuses_a_camera_inside_the_volume_and_a_bad_name(tmp_path):
    session = tmp_path / "s"
    folders = make_sequences(session)
    calib_path = make_calibration(tmp_path / "calibration.yaml")
    doc = yaml.safe_load(open(calib_path))
    R = np.asarray(doc["cameras"][1]["R"])
    doc["cameras"][1]["t"] = (-R @ np.array([0.0, 0.0, 0.1])).tolist()  # centre in the box
    (tmp_path / "inside.yaml").write_text(yaml.safe_dump(doc))
    kw = dict(reference_frames=(0, 4), frame_rate=FPS, time_offsets=0.0, **VOLUME)
    with pytest.raises(SchlierenInputError, match="inside the volume") as info:
        scaffold_session(session, folders, str(tmp_path / "inside.yaml"), **kw)
    assert info.value.camera == "cam1" and info.value.field == "cameras[1].t"
    assert info.value.file == str(tmp_path / "inside.yaml")  # the calibration the user gave
    with pytest.raises(SchlierenInputError, match="camera name") as info:
        scaffold_session(session, {"cam 0": folders["cam0"]}, calib_path, **kw)
    assert len(str(info.value)) < 400


def test_init_refuses_a_calibration_in_millimetres_naming_it(tmp_path):
    """Issue 33: t and the background in mm were accepted (all cameras) or refused naming
    the temporary manifest (one camera); now refused naming the calibration and the unit."""
    session = tmp_path / "s"
    folders = make_sequences(session)
    doc = yaml.safe_load(open(make_calibration(tmp_path / "calibration.yaml")))
    kw = dict(reference_frames=(0, 4), frame_rate=FPS, time_offsets=0.0, **VOLUME)
    for only_t in (False, True):
        for c in doc["cameras"]:
            c["t"] = [1000.0 * v for v in c["t"]]
            c["background"] = {"distance": 5.0 if only_t else 5000.0}
        path = tmp_path / f"mm{only_t}.yaml"
        path.write_text(yaml.safe_dump(doc))
        with pytest.raises(SchlierenInputError, match="calibration in millimetres") as info:
            scaffold_session(session, folders, str(path), **kw)
        assert info.value.file == str(path) and info.value.camera == "cam0" and ".tmp" not in str(info.value)
        assert not (session / "session.yaml").exists()
        doc = yaml.safe_load(open(tmp_path / "calibration.yaml"))


def test_an_error_of_the_session_reader_names_the_users_files(tmp_path):
    from schlieren.storage.errors import SessionError
    from schlieren.storage.scaffold.build import _named_for_user

    calib = read_calibration(make_calibration(tmp_path / "calibration.yaml"))

    class Plan:
        pass

    plan = Plan()
    plan.calib, plan.manifest_path = calib, tmp_path / "s" / "session.yaml"
    tmp = tmp_path / "s" / "session.yaml.tmp"
    geo = _named_for_user(SessionError("bad", file=str(tmp), camera="cam2", field="cameras[1].background"), tmp, plan)
    assert (geo.file, geo.camera, geo.field) == (calib.path, "cam2", "cameras[2].background")
    other = _named_for_user(SessionError("bad", file=str(tmp), field="frames"), tmp, plan)
    assert other.file == str(plan.manifest_path) and isinstance(other, SessionError)
    elsewhere = SessionError("bad", file=str(tmp_path / "x.png"), camera="cam2", field="cameras[1].frames")
    assert _named_for_user(elsewhere, tmp, plan) is elsewhere
