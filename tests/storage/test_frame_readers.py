"""Frame readers: image sequences (8/16-bit PNG, TIFF, colour), videos, references.

Ground truth: the arrays written to disk. Lossless codecs (PNG, TIFF, FFV1, PNG-in-AVI)
must read back exactly; lossy ones (MJPG, mp4v) must return the right frame (closer to
the frame written at that index than to any other).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from schlieren.storage import frames as frames_module
from schlieren.storage.readers import video as video_module
from schlieren.storage.errors import DroppedFrame, SessionError
from schlieren.storage.frames import (
    ImageSequence,
    VideoFrames,
    open_frames,
    read_image,
    read_reference,
)
from schlieren.storage.session import CameraSource, load_session

H, W = 30, 40


def write_sequence(folder: Path, stack: np.ndarray, *, ext: str = "png", first: int = 0) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(stack):
        assert cv2.imwrite(str(folder / f"{k + first:05d}.{ext}"), img)
    return str(folder / f"%05d.{ext}")


def write_video(path: Path, stack: np.ndarray, fourcc: str) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = stack.shape[1:3]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (w, h), True)
    assert vw.isOpened(), f"this OpenCV build cannot write {fourcc}"
    for img in stack:
        vw.write(img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    vw.release()
    return str(path)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def grey8(rng):
    return rng.integers(0, 256, size=(7, H, W)).astype(np.uint8)


# ---------------------------------------------------------------------------------------
# image sequences
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", ["png", "tif"])
def test_8bit_sequence_reads_exactly_in_any_order(tmp_path, grey8, ext):
    pattern = write_sequence(tmp_path / "f", grey8, ext=ext)
    src = open_frames(pattern, camera_name="cam00")
    assert isinstance(src, ImageSequence)
    assert len(src) == 7 and src.first == 0
    assert src.size == (W, H) and src.raw_dtype == np.uint8
    for i in [6, 0, 3, 3, 1]:
        img = src.read(i)
        assert img.dtype == np.float32 and img.shape == (H, W)
        np.testing.assert_array_equal(img, grey8[i].astype(np.float32))
    assert src.one_channel  # the grey levels are the samples (frame quality takes them as uint8)


@pytest.mark.parametrize("ext", ["png", "tif"])
def test_16bit_values_are_kept_as_numbers(tmp_path, rng, ext):
    stack = rng.integers(0, 65536, size=(3, H, W)).astype(np.uint16)
    stack[0, 0, 0] = 65535
    src = open_frames(write_sequence(tmp_path / "f", stack, ext=ext), camera_name="c")
    assert src.raw_dtype == np.uint16
    img = src.read(0)
    assert img[0, 0] == 65535.0
    np.testing.assert_array_equal(src.read(2), stack[2].astype(np.float32))


def test_colour_frames_become_unrounded_grey(tmp_path, rng):
    stack = rng.integers(0, 256, size=(2, H, W, 3)).astype(np.uint8)
    src = open_frames(write_sequence(tmp_path / "f", stack), camera_name="c")
    b, g, r = (stack[1, ..., k].astype(np.float64) for k in range(3))
    expected = 0.299 * r + 0.587 * g + 0.114 * b
    img = src.read(1)
    assert img.shape == (H, W)
    np.testing.assert_allclose(img, expected, atol=1e-3)
    assert np.any(np.abs(img - np.round(img)) > 0.01)  # not rounded to integers
    assert not src.one_channel
    # grey frames, then one in colour: from that read on the source no longer says one channel
    mixed = write_sequence(tmp_path / "m", [stack[0, ..., 0], stack[1, ..., 0], stack[1]])
    src = open_frames(mixed, camera_name="c")
    assert not src.one_channel  # nothing read yet: unknown
    src.read(0)
    src.read(1)
    assert src.one_channel
    src.read(2)
    assert not src.one_channel
    src.read(0)
    assert not src.one_channel


def test_sixteen_bit_colour_tiff(tmp_path, rng):
    stack = rng.integers(0, 65536, size=(1, H, W, 3)).astype(np.uint16)
    src = open_frames(write_sequence(tmp_path / "f", stack, ext="tif"), camera_name="c")
    b, g, r = (stack[0, ..., k].astype(np.float64) for k in range(3))
    np.testing.assert_allclose(src.read(0), 0.299 * r + 0.587 * g + 0.114 * b, rtol=1e-5, atol=0.05)


def test_first_index_one_is_detected(tmp_path, grey8):
    src = open_frames(write_sequence(tmp_path / "f", grey8, first=1), camera_name="c")
    assert src.first == 1 and len(src) == 7
    np.testing.assert_array_equal(src.read(0), grey8[0])
    assert src.file_of(0).endswith("00001.png")


def test_sequence_with_a_gap_is_a_dropped_frame(tmp_path, grey8):
    """A missing number between numbered files: the camera dropped that frame. Its slot is
    kept (index = capture time), reading it says so naming the file, camera and frame."""
    pattern = write_sequence(tmp_path / "f", grey8)
    Path(pattern % 4).unlink()
    Path(pattern % 5).unlink()
    src = open_frames(pattern, camera_name="cam03")
    assert len(src) == 7 and src.dropped == (4, 5) and src.present() == [0, 1, 2, 3, 6]
    np.testing.assert_array_equal(src.read(6), grey8[6])  # after the gap: still frame 6
    with pytest.raises(DroppedFrame) as info:
        src.read(4)
    err = info.value
    assert err.file == pattern % 4 and err.camera == "cam03" and err.field == "frames[4]"
    assert "\n" not in str(err) and "dropped" in str(err)
    # the reference of such a sequence averages the frames that exist
    ref = read_reference(pattern)
    np.testing.assert_allclose(ref, grey8[[0, 1, 2, 3, 6]].astype(np.float64).mean(axis=0), atol=1e-4)


@pytest.mark.parametrize("steps, slots", [
    ([40] * 5, [0, 1, 2, 3, 4, 5]),
    ([40, 40, 80, 40, 120, 40], [0, 1, 2, 4, 5, 8, 9]),  # one, then two frames dropped
    ([33, 34, 33, 67, 33, 34, 33], [0, 1, 2, 3, 5, 6, 7, 8]),  # 29.97 frames/s in milliseconds
    ([40, 59, 41, 40], [0, 1, 2, 3, 4]),  # jitter below 1.5 intervals is no drop
    ([0, 0, 0, 0], [0, 1, 2, 3, 4]),  # no timestamps: no timing to tell drops by
])
def test_slots_of_timestamps(steps, slots):
    ms = np.concatenate([[0.0], np.cumsum(steps)])
    assert frames_module.slots_of_timestamps(ms).tolist() == slots


def _video_with_a_gap(tmp_path, stack, drop: int, fps: int = 25) -> str:
    """A lossless video of ``stack`` whose frame ``drop`` is missing: the frames after it
    keep their presentation times (``setpts``), as a camera that dropped it writes them."""
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")  # the ffmpeg binary (extra bench)
    import subprocess

    kept = [k for k in range(len(stack)) if k != drop]
    pattern = write_sequence(tmp_path / "kept", stack[kept])
    out = tmp_path / "gap.mkv"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-framerate", str(fps),
                    "-i", pattern, "-vf", f"setpts='(N+gte(N,{drop}))/({fps}*TB)'", "-fps_mode", "passthrough",
                    "-c:v", "ffv1", "-pix_fmt", "gray", str(out)], check=True)
    return str(out)


def test_video_timestamp_gap_is_a_dropped_frame(tmp_path, grey8):
    path = _video_with_a_gap(tmp_path, grey8, drop=3)
    src = VideoFrames(path, camera_name="cam02")
    assert len(src) == 7 and src.dropped == (3,)
    for k in (6, 2, 4, 5, 0):  # random access: each slot's own frame
        np.testing.assert_array_equal(src.read(k), grey8[k])
    with pytest.raises(DroppedFrame, match="dropped") as info:
        src.read(3)
    assert info.value.camera == "cam02" and info.value.field == "frames[3]"
    got = list(VideoFrames(path).iter_sequential())
    np.testing.assert_array_equal(np.stack(got), grey8[[0, 1, 2, 4, 5, 6]])
    # a worker given the scan does not decode the video for it, and agrees
    again = VideoFrames(path, slots=src.scan())
    np.testing.assert_array_equal(again.read(5), grey8[5])
    assert pickle.loads(pickle.dumps(again)).dropped == (3,)


def test_sequence_without_first_frame(tmp_path, grey8):
    pattern = write_sequence(tmp_path / "f", grey8, first=2)
    with pytest.raises(SessionError, match="no frame file found"):
        open_frames(pattern, camera_name="c")


def test_corrupt_frame_raises_with_its_index(tmp_path, grey8):
    pattern = write_sequence(tmp_path / "f", grey8)
    Path(pattern % 2).write_bytes(b"\x89PNG garbage")
    src = open_frames(pattern, camera_name="cam01")
    np.testing.assert_array_equal(src.read(1), grey8[1])
    with pytest.raises(SessionError) as info:
        src.read(2)
    assert info.value.field == "frames[2]" and info.value.file == pattern % 2
    assert info.value.camera == "cam01" and "cannot decode" in str(info.value)


def test_index_out_of_range(tmp_path, grey8):
    src = open_frames(write_sequence(tmp_path / "f", grey8), camera_name="c")
    for i in (-1, 7):
        with pytest.raises(SessionError, match="outside the 7 frames"):
            src.read(i)


def test_neither_pattern_nor_video(tmp_path):
    with pytest.raises(SessionError, match="printf pattern"):
        open_frames(tmp_path / "frames.png", camera_name="c")


def test_sequence_source_pickles(tmp_path, grey8):
    src = open_frames(write_sequence(tmp_path / "f", grey8), camera_name="c")
    clone = pickle.loads(pickle.dumps(src))
    np.testing.assert_array_equal(clone.read(5), grey8[5])


# ---------------------------------------------------------------------------------------
# videos
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("grab_limit", [0, 16])  # 0: every jump seeks; 16: short jumps decode forward
@pytest.mark.parametrize("name, fourcc", [("v.avi", "FFV1"), ("v.mkv", "FFV1"), ("v.avi", "png ")])
def test_lossless_video_random_access_is_exact(tmp_path, grey8, name, fourcc, grab_limit, monkeypatch):
    monkeypatch.setattr(video_module, "FORWARD_GRAB_LIMIT", grab_limit)
    path = write_video(tmp_path / name, grey8, fourcc)
    src = open_frames(path, camera_name="cam00")
    assert isinstance(src, VideoFrames)
    assert len(src) == 7 and src.size == (W, H) and src.raw_dtype == np.uint8
    for i in [5, 2, 6, 0, 1, 2, 3, 4]:  # backwards seeks, repeats and sequential runs
        np.testing.assert_array_equal(src.read(i), grey8[i].astype(np.float32), err_msg=f"frame {i}")


@pytest.mark.parametrize("name, fourcc", [("v.avi", "MJPG"), ("v.mp4", "mp4v")])
def test_lossy_video_returns_the_right_frame(tmp_path, rng, name, fourcc):
    # smooth, very different frames so that compression noise cannot confuse them
    yy, xx = np.mgrid[0:48, 0:64]
    stack = np.stack([(127 + 100 * np.sin(xx / (3 + k) + yy / (5 + 2 * k))).astype(np.uint8)
                      for k in range(8)])
    src = open_frames(write_video(tmp_path / name, stack, fourcc), camera_name="c")
    assert len(src) == 8
    for i in [6, 1, 7, 0, 3, 4]:
        img = src.read(i)
        errs = [np.abs(img - s.astype(np.float32)).mean() for s in stack]
        assert int(np.argmin(errs)) == i and errs[i] < 6.0, (i, errs)


def test_sequential_fallback_when_seek_is_refused(tmp_path, grey8, monkeypatch):
    monkeypatch.setattr(video_module, "FORWARD_GRAB_LIMIT", 0)
    src = open_frames(write_video(tmp_path / "v.avi", grey8, "FFV1"), camera_name="c")
    src.read(0)
    real_open = src._open

    def refusing_open():
        cap = real_open()

        class NoSeek:
            def set(self, prop, value):
                return False

            def __getattr__(self, name):
                return getattr(cap, name)

        return NoSeek()

    monkeypatch.setattr(src, "_open", refusing_open)
    src.close()
    np.testing.assert_array_equal(src.read(4), grey8[4])
    np.testing.assert_array_equal(src.read(2), grey8[2])


def _corrupt_png_avi(tmp_path, stack, bad_index):
    path = write_video(tmp_path / "bad.avi", stack, "png ")
    data = bytearray(Path(path).read_bytes())
    sig = b"\x89PNG"
    starts = [i for i in range(len(data) - 3) if data[i:i + 4] == sig]
    assert len(starts) == len(stack)
    data[starts[bad_index]:starts[bad_index] + 200] = bytes(200)  # wipe header and data start
    Path(path).write_bytes(bytes(data))
    return path


def test_corrupt_frame_in_the_middle_of_a_video(tmp_path, grey8):
    path = _corrupt_png_avi(tmp_path, grey8, 3)
    src = open_frames(path, camera_name="cam02")
    assert len(src) == 7
    np.testing.assert_array_equal(src.read(2), grey8[2])
    with pytest.raises(SessionError) as info:
        src.read(3)
    err = info.value
    assert err.file == path and err.camera == "cam02" and err.field == "frames[3]"
    assert "cannot decode frame 3" in err.message and "\n" not in str(err)
    np.testing.assert_array_equal(src.read(1), grey8[1])  # recovers after the error


def test_video_source_pickles_without_its_decoder(tmp_path, grey8):
    src = open_frames(write_video(tmp_path / "v.avi", grey8, "FFV1"), camera_name="c")
    src.read(3)
    clone = pickle.loads(pickle.dumps(src))
    np.testing.assert_array_equal(clone.read(4), grey8[4])
    np.testing.assert_array_equal(clone.read(0), grey8[0])


def test_missing_video(tmp_path):
    with pytest.raises(SessionError, match="video file not found") as info:
        open_frames(tmp_path / "none.mp4", camera_name="cam00")
    assert info.value.camera == "cam00"


# ---------------------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------------------
def test_reference_single_image(tmp_path, grey8):
    p = tmp_path / "ref.png"
    cv2.imwrite(str(p), grey8[0])
    ref = read_reference(p, camera_name="c")
    assert ref.dtype == np.float32
    np.testing.assert_array_equal(ref, grey8[0])


def test_reference_pattern_is_averaged_in_float64(tmp_path, rng):
    stack = rng.integers(0, 65536, size=(5, H, W)).astype(np.uint16)
    pattern = write_sequence(tmp_path / "ref", stack)
    ref = read_reference(pattern, camera_name="c")
    expected = stack.astype(np.float64).mean(axis=0).astype(np.float32)
    np.testing.assert_array_equal(ref, expected)


def test_reference_video_is_averaged(tmp_path, grey8):
    path = write_video(tmp_path / "ref.avi", grey8, "FFV1")
    ref = read_reference(path, camera_name="c")
    np.testing.assert_array_equal(ref, grey8.astype(np.float64).mean(axis=0).astype(np.float32))


def test_reference_from_camera_source(tmp_path, grey8):
    pattern = write_sequence(tmp_path / "f", grey8)
    cv2.imwrite(str(tmp_path / "ref.png"), grey8[3])
    src = CameraSource("camX", pattern, str(tmp_path / "ref.png"), "sequence", "image")
    np.testing.assert_array_equal(read_reference(src), grey8[3])
    frames = open_frames(src)
    assert frames.camera_name == "camX" and len(frames) == 7
    np.testing.assert_array_equal(src.open_frames().read(6), grey8[6])


@pytest.mark.parametrize("kind", ["image", "sequence", "video"])
def test_reference_frames_average_to_the_reference_bit_for_bit(tmp_path, grey8, rng, kind):
    from schlieren.storage.frames import ReferenceMean, reference_frames

    if kind == "image":
        path = tmp_path / "ref.png"
        cv2.imwrite(str(path), grey8[2])
        want = [grey8[2]]
    elif kind == "sequence":
        stack = rng.integers(0, 65536, size=(5, H, W)).astype(np.uint16)
        path, want = write_sequence(tmp_path / "ref", stack), stack
    else:
        path, want = write_video(tmp_path / "ref.avi", grey8, "FFV1"), grey8
    got = list(reference_frames(path, camera_name="c"))
    assert len(got) == len(want)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    mean = ReferenceMean(str(path), "c")
    for img in got:
        mean.add(img)
    np.testing.assert_array_equal(mean.result(), read_reference(path, camera_name="c"))
    with pytest.raises(SessionError, match="no frames"):
        ReferenceMean(str(path), "c").result()


def test_reference_corrupt_video_names_the_frame(tmp_path, grey8):
    path = _corrupt_png_avi(tmp_path, grey8, 5)
    with pytest.raises(SessionError) as info:
        read_reference(path, camera_name="cam01")
    assert info.value.field == "frames[5]" and info.value.camera == "cam01"


def test_read_image_missing(tmp_path):
    with pytest.raises(SessionError, match="file not found"):
        read_image(tmp_path / "nope.png", camera_name="c")


# ---------------------------------------------------------------------------------------
# sessions made of videos
# ---------------------------------------------------------------------------------------
def test_session_of_videos_loads_and_reports_corrupt_video_frames(make_builder):
    b = make_builder("vid", n_frames=5)
    rng = np.random.default_rng(7)
    W_, H_ = b.size
    truth = {}
    for i, cam in enumerate(b.manifest["cameras"]):
        stack = rng.integers(0, 256, size=(5, H_, W_)).astype(np.uint8)
        truth[cam["name"]] = stack
        write_video(b.root / cam["name"] / "capture.avi", stack, "png ")
        write_video(b.root / cam["name"] / "reference.avi", stack[:2], "FFV1")
        cam["frames"] = f"{cam['name']}/capture.avi"
        cam["reference"] = f"{cam['name']}/reference.avi"
    b.save()
    s = load_session(b.root)
    assert s.n_frames_available == 5 and s.sources[0].frames_kind == "video"
    assert s.sources[0].reference_kind == "video"
    np.testing.assert_array_equal(open_frames(s.sources[1]).read(3), truth["cam01"][3])
    np.testing.assert_array_equal(read_reference(s.sources[2]),
                                  truth["cam02"][:2].astype(np.float64).mean(0).astype(np.float32))

    # corrupt frame 4 (the last one, which load_session decodes) of cam01's video
    path = b.root / "cam01" / "capture.avi"
    data = bytearray(path.read_bytes())
    starts = [k for k in range(len(data) - 3) if data[k:k + 4] == b"\x89PNG"]
    data[starts[4]:starts[4] + 200] = bytes(200)
    path.write_bytes(bytes(data))
    for decode_all in (False, True):
        with pytest.raises(SessionError) as info:
            load_session(b.root, decode_all_frames=decode_all)
        err = info.value
        assert err.file == str(path.resolve()) and err.camera == "cam01"
        assert err.field == "cameras[1].frames[4]" and "\n" not in str(err)


def test_session_with_different_video_lengths(make_builder):
    b = make_builder("vid2", n_frames=4)
    rng = np.random.default_rng(8)
    W_, H_ = b.size
    for i, cam in enumerate(b.manifest["cameras"]):
        n = 4 if i != 1 else 3
        write_video(b.root / cam["name"] / "capture.avi",
                    rng.integers(0, 256, size=(n, H_, W_)).astype(np.uint8), "FFV1")
        cv2.imwrite(str(b.root / cam["name"] / "reference.png"), np.zeros((H_, W_), np.uint8))
        cam["frames"] = f"{cam['name']}/capture.avi"
    b.save()
    with pytest.raises(SessionError) as info:
        load_session(b.root)
    assert info.value.camera == "cam01" and info.value.field == "cameras[1].frames"
    assert "has 3 frames but camera cam00 has 4" in info.value.message


# ---------------------------------------------------------------------------------------
# structural completeness (no pixel decoding): truncated files are found before any work
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", [".png", ".jpg", ".tif"])
def test_image_incomplete_finds_truncated_files(tmp_path, ext):
    import cv2

    from schlieren.storage.frames import image_header, image_incomplete

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (48, 64), dtype=np.uint8)
    whole = tmp_path / f"whole{ext}"
    cv2.imwrite(str(whole), img)
    assert image_incomplete(whole) is None
    data = whole.read_bytes()
    cut = tmp_path / f"cut{ext}"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    if ext != ".tif":  # (OpenCV writes a TIFF's directory after the pixels: cut, it is gone too)
        assert image_header(cut) == (64, 48)  # the header alone looks fine
    why = image_incomplete(cut)
    assert why is not None and {".png": "PNG", ".jpg": "JPEG", ".tif": "TIFF"}[ext] in why


# ---------------------------------------------------------------------------------------
# issue 36: numbered folders, images whose header declares an absurd size
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("spec", ["folder", "glob"])
def test_a_numbered_folder_with_a_gap_is_a_dropped_frame(tmp_path, grey8, spec):
    pattern = write_sequence(tmp_path / "f", grey8, first=3)
    Path(pattern % 5).unlink()
    src = open_frames(str(tmp_path / "f") + "/" if spec == "folder" else str(tmp_path / "f" / "*.png"),
                      camera_name="cam01")
    assert len(src) == 7 and src.dropped == (2,) and src.present() == [0, 1, 3, 4, 5, 6]
    np.testing.assert_array_equal(src.read(3), grey8[3])  # after the gap: still its own slot
    with pytest.raises(DroppedFrame) as info:
        src.read(2)
    assert info.value.file.endswith("00005.png") and info.value.field == "frames[2]"


def test_folders_without_one_numbering_keep_name_order(tmp_path, grey8):
    d = tmp_path / "f"
    d.mkdir()
    for k, name in enumerate(["a1.png", "a3.png", "b7.png"]):
        cv2.imwrite(str(d / name), grey8[k])
    src = open_frames(str(d) + "/")
    assert len(src) == 3 and src.dropped == ()
    np.testing.assert_array_equal(src.read(2), grey8[2])


def _png_declaring(path: Path, width: int, height: int) -> None:
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    body = zlib.compress(b"\x00" * (width + 1) * 4)  # a few rows of pixels only
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", body) + chunk(b"IEND", b""))


def test_a_png_declaring_an_enormous_size_is_refused_in_one_line(make_builder):
    """Frame 0 (decoded when the camera is opened), a later frame (its header read) and the
    reference: each refused in one line naming the file and the camera, before any decoding."""
    for where, field in (("frames/00000.png", "cameras[1].image_size"), ("frames/00004.png", "cameras[1].image_size"),
                         ("reference.png", "cameras[1].reference")):
        b = make_builder(where.replace("/", "_")).write()
        _png_declaring(b.root / "cam01" / where, 100_000, 100_000)
        with pytest.raises(SessionError) as info:
            load_session(b.root)
        err = info.value
        assert err.camera == "cam01" and err.field == field and err.file.endswith(where.split("/")[-1])
        assert "100000x100000" in str(err) and "\n" not in str(err)
