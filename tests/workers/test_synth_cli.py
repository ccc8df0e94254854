"""`schlieren synth` and `schlieren evaluate`: a tiny session and its truth, end to end."""

import json

import cv2
import numpy as np
import pytest
import zarr
from flow_grids import on_grid
from scipy import ndimage

from schlieren.pipeline import metrics
from schlieren.pipeline.geometry import FlowGrid, Grid
from schlieren.pipeline.synthetic.render import flash_rows
from schlieren.storage import synthetic_io as sio
from schlieren.storage.session import load_session
from schlieren.workers.cli import main
from schlieren.workers.evaluate import evaluate
from schlieren.workers.synth import FIRST_FRAME, FLASH_FRAME, TAIL_FRAMES

W, H, N = 144, 108, 2


def read_image(path):
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)

LINE_TIME = 1.0 / (60.0 * 120)   # a frame period's worth of rows, as a real rolling shutter


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "session"
    rc = main(["synth", str(out), "--cameras", "3", "--phantom", "blob", "--frames", str(N),
               "--size", f"{W}x{H}", "--supersample", "2", "--recon-voxel", "0.005", "--seed", "4",
               "--line-time", str(LINE_TIME)])
    assert rc == 0
    return out


def _store(path, vol, grid: Grid, times):
    g = zarr.open_group(str(path), mode="w")
    a = g.create_array("refractivity", shape=vol.shape, chunks=(1,) + vol.shape[1:], dtype="float32",
                       dimension_names=["frame", "z", "y", "x"], attributes=grid.to_attrs())
    a[:] = vol
    t = g.create_array("time", shape=(len(times),), dtype="float64", dimension_names=["frame"])
    t[:] = times
    return path


def test_session_loads_and_truth_is_consistent(synth_dir):
    s = load_session(synth_dir / "session.yaml")
    assert s.frames == (FIRST_FRAME, FIRST_FRAME + N)
    assert s.n_frames_available == FIRST_FRAME + N + TAIL_FRAMES
    assert all(c.time_offset is None for c in s.cameras)      # strobe sync: offsets hidden
    t = sio.read_truth(synth_dir / "truth.zarr")
    fg = FlowGrid((W, H), 3)
    g = t.group
    assert g["deflection"].shape == (3, N, *fg.shape, 2)
    # the output instants follow docs/design.md
    expected = (FIRST_FRAME + np.arange(N)) / 60.0 + t.time_offset.mean() + 0.5 * H * LINE_TIME
    np.testing.assert_allclose(t.time, expected, atol=1e-12)
    # the blob is static, so rolling shutter changes nothing: both deflections agree
    d, drs = g["deflection"][:], g["deflection_rs"][:]
    assert np.abs(d).max() > 0.01
    np.testing.assert_allclose(drs, d, atol=1e-6)
    # d_in are the unit rays through the flow-cell centres
    cam = s.cameras[1]
    _, rays = cam.rays(fg.pixel_centres())
    np.testing.assert_allclose(g["d_in"][1, 0], rays, atol=1e-6)
    dout = g["d_out"][1, 0]
    np.testing.assert_allclose(np.linalg.norm(dout, axis=-1), 1.0, atol=1e-6)


def test_flash_band_is_where_the_hidden_offsets_put_it(synth_dir):
    s = load_session(synth_dir / "session.yaml")
    t = sio.read_truth(synth_dir / "truth.zarr")
    for c, cam in enumerate(s.cameras):
        cam = cam.with_time_offset(float(t.time_offset[c]))
        ref = read_image(synth_dir / f"{cam.name}/reference.png").astype(float)
        for f in (FLASH_FRAME - 1, FLASH_FRAME, FLASH_FRAME + 1):
            img = read_image(synth_dir / (sio.frame_pattern(cam.name) % f)).astype(float)
            lit = flash_rows(cam, f, frame_rate=60.0, exposure=1 / 120)
            bright = (img - ref).mean(axis=1) > 40
            np.testing.assert_array_equal(bright, lit)
        assert flash_rows(cam, FLASH_FRAME, frame_rate=60.0, exposure=1 / 120).any()
        for f in range(FLASH_FRAME + 1, FIRST_FRAME + N + TAIL_FRAMES):
            assert not flash_rows(cam, f, frame_rate=60.0, exposure=1 / 120).any()


def test_frames_carry_sensor_noise_around_the_reference(synth_dir):
    ref = read_image(synth_dir / "cam00/reference.png").astype(float)
    img = read_image(synth_dir / (sio.frame_pattern("cam00") % FIRST_FRAME)).astype(float)
    t = sio.read_truth(synth_dir / "truth.zarr")
    still = np.ones_like(ref, dtype=bool)
    d = t.group["deflection_rs"][0, 0]
    moved = np.repeat(np.repeat(np.abs(d).max(-1) > 1e-4, 3, 0), 3, 1)
    still[: moved.shape[0], : moved.shape[1]] &= ~ndimage.binary_dilation(moved, iterations=6)
    diff = (img - ref)[still]
    assert abs(diff.std() - np.sqrt(1.5**2 + 2 / 12)) < 0.15


def test_evaluate_truth_against_itself_and_a_blurred_truth(synth_dir, tmp_path):
    truth = sio.read_truth(synth_dir / "truth.zarr")
    vol = np.asarray(truth.refractivity[:])
    shape = vol.shape[1:]
    grid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, shape)
    res = evaluate(_store(tmp_path / "same.zarr", vol, grid, truth.time), synth_dir / "truth.zarr")
    assert res["overall"]["rms"] == 0.0 and res["overall"]["psnr"] == float("inf")
    blurred = np.stack([ndimage.gaussian_filter(v.astype(np.float64), 1.5) for v in vol]).astype(np.float32)
    res_b = evaluate(_store(tmp_path / "blur.zarr", blurred, grid, truth.time), synth_dir / "truth.zarr")
    expected = [metrics.relative_rms(b, v) for b, v in zip(blurred, vol)]
    np.testing.assert_allclose([r["rms"] for r in res_b["frames"]], expected, rtol=1e-6)
    assert 0 < res_b["overall"]["rms"] < 0.1
    assert 20 < res_b["overall"]["psnr"] < np.inf
    # a coarser store: voxel centres at the midpoints of 2x2x2 fine blocks -> trilinear = block mean
    nz, ny, nx = shape
    coarse = vol.reshape(N, nz // 2, 2, ny // 2, 2, nx // 2, 2).astype(np.float64).mean(axis=(2, 4, 6))
    cgrid = Grid(grid.vmin, grid.vmax, 2 * grid.voxel_size)
    res_c = evaluate(_store(tmp_path / "coarse.zarr", coarse.astype(np.float32), cgrid, truth.time),
                     synth_dir / "truth.zarr")
    assert res_c["overall"]["rms"] < 1e-5


def test_evaluate_resamples_time_between_knots(tmp_path):
    fine = Grid((0, 0, 0), (0.02, 0.02, 0.02), 0.005)
    tw = sio.TruthWriter(tmp_path / "truth.zarr", grid=fine, n_frames=1, n_knots=2, n_cameras=1,
                         flow_shape=(2, 2), attrs={})
    tw.write_times([0.0], [0.0, 0.01], [0.0])
    base = np.random.default_rng(1).uniform(1e-4, 3e-4, fine.shape)
    tw.write_knot(0, base)
    tw.write_knot(1, 2 * base)
    tw.write_refractivity(0, base)
    est = (1.25 * base)[None].astype(np.float32)        # the truth at t = 0.0025 s
    res = evaluate(_store(tmp_path / "s.zarr", est, fine, [0.0025]), tmp_path / "truth.zarr")
    assert res["frames"][0]["truth_from"] == "knots"
    assert res["frames"][0]["rms"] < 1e-6
    res = evaluate(_store(tmp_path / "s2.zarr", est, fine, [0.0]), tmp_path / "truth.zarr")
    assert res["frames"][0]["rms"] == pytest.approx(metrics.relative_rms(1.25 * base, base), rel=1e-5)


def test_evaluate_cli_table_and_json(synth_dir, tmp_path, capsys):
    truth = sio.read_truth(synth_dir / "truth.zarr")
    vol = np.asarray(truth.refractivity[:])
    grid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, vol.shape[1:])
    store = _store(tmp_path / "s.zarr", vol, grid, truth.time)
    rc = main(["evaluate", str(store), "--truth", str(synth_dir / "truth.zarr"), "--json", str(tmp_path / "e.json")])
    assert rc == 0
    assert "PSNR" in capsys.readouterr().out
    data = json.loads((tmp_path / "e.json").read_text())
    assert len(data["frames"]) == N and data["overall"]["psnr"] == "inf"
    assert main(["evaluate", str(tmp_path / "missing.zarr"), "--truth", str(synth_dir / "truth.zarr")]) == 2


def test_synth_cli_rejects_bad_arguments(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "x"), "--cameras", "1"]) == 2
    assert "cameras" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "x"), "--video", "--bit-depth", "16"]) == 2


def test_background_only(tmp_path):
    assert main(["synth", str(tmp_path), "--background-only", "--print-size", "120x80", "--dpi", "100"]) == 0
    from PIL import Image
    im = Image.open(tmp_path / "background.png")
    assert im.size == (120, 80)


def test_synthesised_session_runs_through_every_stage(tiny_session, serial_store):
    # tiny_session / serial_store (tests/conftest.py): a synthesised session loaded by
    # storage and processed by every stage of the serial executor
    truth = sio.read_truth(tiny_session.truth)
    g = zarr.open_group(str(serial_store), mode="r")
    # sync found the hidden offsets to within a couple of line times
    lt = load_session(tiny_session.session).cameras[0].line_time
    np.testing.assert_allclose(g["time_offset"][:], truth.time_offset, atol=3 * lt)
    # the measured flow follows the exact deflection
    d = truth.group["deflection"][:]
    # the run took the flow grid flow.auto_factor chose (finer than the rendered one here),
    # stored it, and the flow has that grid's shape
    from schlieren.pipeline.tomography.binning import auto_flow_factor
    from schlieren.storage.store import ResultStore

    s = load_session(tiny_session.session)
    want = auto_flow_factor(s.cameras, s.grid, 3)
    attrs = ResultStore.open(serial_store, mode="r").attrs
    assert want == 2 and attrs["run"]["flow_factor"] == want and attrs["params"]["flow"]["factor"] == want
    assert g["flow"].shape[2:4] == FlowGrid(s.cameras[0].image_size, want).shape
    f = on_grid(g["flow"][:], d.shape[-3:-1])  # the run's grid -> the truth's (rendered at 3)
    sig = np.abs(d).max(-1) > 0.2 * np.abs(d).max()
    assert np.corrcoef(f[sig].ravel(), d[sig].ravel())[0, 1] > 0.8
    res = evaluate(serial_store, tiny_session.truth)
    assert res["overall"]["frames"] == len(truth.time)
    assert 15.0 < res["overall"]["psnr"] < 80.0


def test_video_distortion_and_explicit_offsets(tmp_path):
    out = tmp_path / "v"
    assert main(["synth", str(out), "--cameras", "2", "--phantom", "tealights", "--frames", "1", "--size", "96x72",
                 "--supersample", "1", "--recon-voxel", "0.01", "--video", "--distortion", "--no-strobe"]) == 0
    s = load_session(out / "session.yaml")
    truth = sio.read_truth(out / "truth.zarr")
    assert s.n_frames_available == FIRST_FRAME + 1 + TAIL_FRAMES
    assert s.strobe_search is None
    np.testing.assert_allclose([c.time_offset for c in s.cameras], truth.time_offset)
    assert all(c.has_distortion for c in s.cameras)
    # distortion is modelled: d_in are the undistorted rays through the flow-cell centres
    fg = FlowGrid((96, 72), 3)
    _, rays = s.cameras[0].rays(fg.pixel_centres())
    np.testing.assert_allclose(truth.group["d_in"][0, 0], rays, atol=1e-6)


def test_lossy_video_with_recorded_reference_frames(tmp_path):
    """H.264 capture and a reference recorded as noisy video frames (camcorder-like sessions)."""
    from schlieren.storage.frames import read_reference

    pytest.importorskip("imageio_ffmpeg")
    common = dict(cameras=2, phantom="blob", frames=1, size=(192, 144), supersample=1, recon_voxel=0.01,
                  noise=1.5, strobe=False, seed=5)
    from schlieren.workers.synth import synthesize

    lossy = synthesize(tmp_path / "h", video=True, video_codec="h264", video_bits_per_pixel=0.16,
                       reference_frames=8, **common)
    clean = synthesize(tmp_path / "c", **common)
    s = load_session(lossy.session)
    src = s.sources[0]
    assert str(src.frames).endswith("capture.mp4") and str(src.reference).endswith("reference.mp4")
    truth = sio.read_truth(lossy.truth)
    assert truth.attrs["video"] == "h264" and truth.attrs["reference_frames"] == 8
    ref = read_reference(src)
    ref_clean = read_reference(load_session(clean.session).sources[0])
    err = np.abs(ref.astype(np.float64) - ref_clean.astype(np.float64))
    # the average of 8 noisy, lossy frames is the clean reference up to coding loss
    assert 0.05 < float(err.mean()) < 10.0
    # and it is far closer than an unrelated texture
    assert float(err.mean()) < 0.3 * float(np.abs(ref_clean - ref_clean.mean()).mean())
