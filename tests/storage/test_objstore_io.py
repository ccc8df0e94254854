"""Sessions and result stores on object storage (moto's S3 server on 127.0.0.1).

* a session uploaded to a bucket loads like its folder: same cameras, frame counts and
  pixels (image frames fetched and decoded in memory, videos staged to a local file);
* bad input at a URL is one line naming the URL, camera and field;
* a store's chunks on S3 are byte for byte the chunk files of a folder store;
* background writes: a failed chunk write fails the flush with its name and its marker
  is never stored.
"""

from __future__ import annotations

import functools

import os
import pickle

import fsspec.asyn
import numpy as np
import pytest
import zarr

from schlieren.storage import location
from schlieren.storage.errors import SessionError, StoreError
from schlieren.storage.frames import open_frames, read_reference
from schlieren.storage.layout import result_layout, stage_markers
from schlieren.storage.session import load_session
from schlieren.storage.store import ResultStore, fingerprint
from schlieren.pipeline.geometry import Grid

from test_frame_readers import write_video


@pytest.fixture
def cache(tmp_path, monkeypatch):
    d = tmp_path / "stage-cache"
    monkeypatch.setenv(location.CACHE_ENV, str(d))
    return d


# ---------------------------------------------------------------------------------------
# sessions
# ---------------------------------------------------------------------------------------
def test_a_session_on_s3_loads_and_reads_like_its_folder(s3_server, session_builder, cache):
    url = s3_server.upload(session_builder.root, s3_server.bucket() + "/capture")
    local = load_session(session_builder.root)
    for spec in (url, url + "/", url + "/session.yaml"):
        remote = load_session(spec)
        assert remote.root == url and remote.manifest_path == url + "/session.yaml"
        assert remote.name == local.name and remote.camera_names == local.camera_names
        assert remote.n_frames_available == local.n_frames_available == session_builder.n_frames
        assert remote.frames == local.frames
    src = remote.sources[1]
    assert src.frames == url + "/cam01/frames/%05d.png" and src.reference == url + "/cam01/reference.png"
    frames = open_frames(src)
    assert len(frames) == session_builder.n_frames
    for k in (0, 3, 5):
        np.testing.assert_array_equal(frames.read(k), session_builder.frames["cam01"][k].astype(np.float32))
    np.testing.assert_array_equal(read_reference(src), session_builder.references["cam01"].astype(np.float32))
    assert not cache.exists() or not any(cache.rglob("*.png"))  # image frames are never staged to disk


def test_frames_prefetched_together_are_read_without_further_requests(s3_server, session_builder, monkeypatch):
    url = s3_server.upload(session_builder.root, s3_server.bucket() + "/capture")
    frames = open_frames(load_session(url, check_files=False).sources[2])
    frames.prefetch([1, 2, 3, 99])  # an index beyond the frames is ignored

    def no_request(*a, **k):
        raise AssertionError("a prefetched frame was fetched again")

    monkeypatch.setattr(location, "read_bytes", no_request)
    for k in (1, 2, 3):
        np.testing.assert_array_equal(frames.read(k), session_builder.frames["cam02"][k].astype(np.float32))
    with pytest.raises(AssertionError, match="fetched again"):
        frames.read(4)


def test_a_session_of_videos_on_s3_stages_each_video_once(s3_server, make_builder, cache):
    b = make_builder("vid", n_frames=5)
    rng = np.random.default_rng(11)
    W, H = b.size
    truth = {}
    for cam in b.manifest["cameras"]:
        stack = rng.integers(0, 256, size=(5, H, W)).astype(np.uint8)
        truth[cam["name"]] = stack
        write_video(b.root / cam["name"] / "capture.avi", stack, "FFV1")
        write_video(b.root / cam["name"] / "reference.avi", stack[:2], "FFV1")
        cam["frames"], cam["reference"] = f"{cam['name']}/capture.avi", f"{cam['name']}/reference.avi"
    b.save()
    url = s3_server.upload(b.root, s3_server.bucket() + "/videos")
    s = load_session(url)
    assert s.sources[0].frames_kind == "video" and s.n_frames_available == 5
    src = open_frames(s.sources[2])
    np.testing.assert_array_equal(src.read(3), truth["cam02"][3])
    np.testing.assert_array_equal(read_reference(s.sources[2]),
                                  truth["cam02"][:2].astype(np.float64).mean(0).astype(np.float32))
    # one local copy per video, whatever opened it (load_session, the reader, a pickled reader)
    again = pickle.loads(pickle.dumps(src))
    np.testing.assert_array_equal(again.read(4), truth["cam02"][4])
    staged = sorted(p.name for p in cache.rglob("*.avi"))
    assert staged == ["capture.avi"] * 3 + ["reference.avi"] * 3


def test_bad_sessions_at_urls_are_one_line_naming_the_url(s3_server, session_builder):
    bucket = s3_server.bucket()
    with pytest.raises(SessionError) as info:
        load_session(bucket + "/nothing-here")
    assert info.value.file == bucket + "/nothing-here/session.yaml" and "manifest not found" in str(info.value)

    url = s3_server.upload(session_builder.root, bucket + "/capture")
    location.remove(url + "/cam02/reference.png")
    with pytest.raises(SessionError) as info:
        load_session(url)
    err = info.value
    assert (err.file, err.camera, err.field) == (url + "/cam02/reference.png", "cam02", "cameras[2].reference")
    assert "\n" not in str(err)

    # a manifest may not point outside its folder (here: at another bucket) unless allowed
    session_builder.camera(0)["frames"] = "s3://elsewhere/cam00/%05d.png"
    session_builder.save()
    url2 = s3_server.upload(session_builder.root, bucket + "/capture2")
    with pytest.raises(SessionError, match="URL 's3://elsewhere/cam00/%05d.png' is not allowed") as info:
        load_session(url2, check_files=False)
    assert info.value.field == "cameras[0].frames"


@pytest.mark.parametrize("head_bytes", [None, 100], ids=["whole-files", "ranged-ends"])
def test_truncated_frames_and_references_at_urls_are_refused(s3_server, session_builder, monkeypatch, head_bytes):
    """As in a folder (test_session_manifest): a frame or a reference cut short anywhere is
    refused before work, naming it. Small files come whole in the header batch; with a
    header window shorter than the files their ends are fetched by ranged requests."""
    from schlieren.storage.readers import decoding  # the one HEADER_BYTES every header read uses

    if head_bytes is not None:
        monkeypatch.setattr(decoding, "HEADER_BYTES", head_bytes)
    b = session_builder
    bucket = s3_server.bucket()
    frame = b.root / "cam02" / "frames" / "00003.png"
    good = frame.read_bytes()
    frame.write_bytes(good[:-5])
    url = s3_server.upload(b.root, bucket + "/cut-frame")
    with pytest.raises(SessionError, match="is truncated") as info:
        load_session(url)
    assert (info.value.file, info.value.camera, info.value.field) == \
        (url + "/cam02/frames/00003.png", "cam02", "cameras[2].frames[3]")
    frame.write_bytes(good)
    ref = b.root / "cam01" / "reference.png"
    ref.write_bytes(ref.read_bytes()[:-3])
    url = s3_server.upload(b.root, bucket + "/cut-reference")
    with pytest.raises(SessionError, match="reference is truncated") as info:
        load_session(url)
    assert (info.value.file, info.value.camera, info.value.field) == \
        (url + "/cam01/reference.png", "cam01", "cameras[1].reference")


# ---------------------------------------------------------------------------------------
# stores
# ---------------------------------------------------------------------------------------
GRID = Grid((-0.05, -0.04, 0.0), (0.05, 0.04, 0.06), 0.02)


def _layout():
    return result_layout(camera_names=["a", "b"], n_frames=3, flow_shape=(5, 6), grid=GRID, first_frame=0)


ATTRS = {"fingerprint": fingerprint("objstore-test"), "session": {"name": "t"}}


def _fill(store: ResultStore) -> None:
    rng = np.random.default_rng(5)
    store.write("flow", (1, 2), rng.normal(size=(5, 6, 2)).astype(np.float32))
    store.write("flow", (0, 0), np.full((5, 6, 2), np.nan, np.float32))  # the fill value: stored too
    store.write("mask", (0, 1), rng.random((5, 6)) > 0.5)
    store.write("refractivity", (2,), rng.normal(size=GRID.shape).astype(np.float32))
    store.write("time", (), np.array([0.1, 0.2, 0.3]))
    store.mark_done("resample", (1, 2))
    store.mark_done("integrate", (2,))
    store.flush()


def test_chunks_on_s3_are_the_bytes_of_a_folder_store(s3_server, tmp_path):
    url = s3_server.bucket() + "/run.zarr"
    folder = tmp_path / "run.zarr"
    for where in (url, folder):
        _fill(ResultStore.create(where, _layout(), attrs=ATTRS, markers=stage_markers()))
    files = {str(p.relative_to(folder)).replace(os.sep, "/"): p.read_bytes()
             for p in folder.rglob("*") if p.is_file() and p.name != "zarr.json"}
    remote = {k: location.read_bytes(f"{url}/{k}") for k in location.find(url) if not k.endswith("zarr.json")}
    # data arrays store fill-valued chunks too (storage/integrity.py), on both kinds of store
    assert sorted(remote) == sorted(files) and "flow/c/1/2/0/0/0" in files and "flow/c/0/0/0/0/0" in files
    assert all(remote[k] == files[k] for k in files)
    again = ResultStore.open(url, mode="r")
    assert again.is_done("resample", (1, 2)) and not again.is_done("resample", (0, 0))
    np.testing.assert_array_equal(again.read("refractivity", (2,)),
                                  ResultStore.open(folder, mode="r").read("refractivity", (2,)))


def test_read_many_returns_what_single_reads_return(s3_server, tmp_path):
    url = s3_server.bucket() + "/run.zarr"
    for where in (url, tmp_path / "run.zarr"):
        _fill(ResultStore.create(where, _layout(), attrs=ATTRS, markers=stage_markers()))
        fresh = ResultStore.open(where, mode="r")  # nothing in memory: every chunk is requested
        keys = [(1, 2), (0, 0), (1, 1)]
        many = fresh.read_many("flow", keys)
        for k, a in zip(keys, many):
            np.testing.assert_array_equal(a, fresh.read("flow", k))
        assert np.isnan(many[1]).all() and np.isfinite(many[0]).all()


def test_a_failed_background_write_fails_the_flush_and_leaves_its_marker_unset(s3_server, monkeypatch):
    url = s3_server.bucket() + "/run.zarr"
    ResultStore.create(url, _layout(), attrs=ATTRS, markers=stage_markers())
    store = ResultStore.open(url, write_behind=True)
    import s3fs

    real = s3fs.S3FileSystem._pipe_file

    async def flaky(self, path, data, *args, **kwargs):  # every PUT of a chunk, zarr's or the store's own
        if "/gradient/" in path:
            raise ConnectionError("the endpoint went away")
        return await real(self, path, data, *args, **kwargs)

    monkeypatch.setattr(s3fs.S3FileSystem, "_pipe_file", flaky)
    fs = location.filesystem(url)[0]  # its sync methods were bound when it was made
    monkeypatch.setattr(fs, "pipe_file", fsspec.asyn.sync_wrapper(functools.partial(flaky, fs), obj=fs))
    store.write("hull", (1,), np.ones(GRID.shape, bool))
    store.mark_done("hull", (1,))
    store.write("gradient", (1,), np.ones((*GRID.shape, 3), np.float32))
    store.mark_done("tomography", (1,))
    with pytest.raises(OSError, match=r"writing gradient at \(1,\) to the object store failed: "
                                      r"ConnectionError: the endpoint went away"):
        store.flush()
    fresh = ResultStore.open(url, mode="r")
    assert fresh.is_done("hull", (1,)) and not fresh.is_done("tomography", (1,))


def test_an_unreachable_bucket_is_one_line_naming_the_url(s3_server):
    url = "s3://no-such-bucket-here/run.zarr"
    with pytest.raises(StoreError) as info:
        ResultStore.create(url, _layout(), attrs=ATTRS, markers=stage_markers())
    assert info.value.file == url and "\n" not in str(info.value)
    with pytest.raises(StoreError, match="no result store at this path"):
        ResultStore.open(url)


def test_folder_glob_and_multipage_tiff_frames_on_s3(s3_server, tmp_path, cache):
    from PIL import Image

    rng = np.random.default_rng(3)
    stack = rng.integers(0, 65535, size=(4, 12, 16)).astype(np.uint16)
    d = tmp_path / "cap" / "frames"
    d.mkdir(parents=True)
    for k, img in enumerate(stack):
        assert __import__("cv2").imwrite(str(d / f"img{k + 1}.png"), img)  # natural order img1..img4
    Image.fromarray(stack[0]).save(tmp_path / "cap" / "pages.tif", save_all=True,
                                   append_images=[Image.fromarray(p) for p in stack[1:]])
    url = s3_server.upload(tmp_path / "cap", s3_server.bucket() + "/cap")
    for spec in (url + "/frames", url + "/frames/", url + "/frames/img*.png", url + "/pages.tif"):
        src = open_frames(spec, camera_name="c")
        assert len(src) == 4, spec
        for k in (0, 3):
            np.testing.assert_array_equal(src.read(k), stack[k].astype(np.float32))
