"""Synthetic session files and the ground-truth group: round trips through the readers."""

import numpy as np
import pytest
import zarr
from PIL import Image

from schlieren.pipeline.geometry import Grid, Medium
from schlieren.pipeline.synthetic.rig import make_rig
from schlieren.storage import synthetic_io as sio
from schlieren.storage.errors import StoreError
from schlieren.storage.session import load_session

GRID = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.005)


def _write_session(root, *, strobe, n_frames=6, bit_depth=8):
    cams = make_rig(3, grid=GRID, image_size=(96, 64), line_time=2e-4, distortion=[-0.02, 0, 0, 0, 0])
    cams = [c.with_time_offset(-0.01 * (i + 1)) for i, c in enumerate(cams)]
    rng = np.random.default_rng(0)
    files = {}
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    for c in cams:
        img = rng.integers(0, 200, (64, 96)).astype(dtype)
        ref = sio.write_reference(root, c.name, img)
        for f in range(n_frames):
            sio.write_frame(root, c.name, f, img)
        files[c.name] = (sio.frame_pattern(c.name), ref)
    path = sio.write_manifest(root, name="t", frame_rate=60.0, frames=(1, 3), grid=GRID, medium=Medium(),
                              cameras=cams, camera_files=files, strobe_search=(3, 6) if strobe else None)  # >= 3 frames, apart from the processed ones
    return path, cams


@pytest.mark.parametrize("strobe", [True, False])
def test_manifest_loads_with_the_session_reader(tmp_path, strobe):
    path, cams = _write_session(tmp_path, strobe=strobe)
    s = load_session(path)
    assert s.frames == (1, 3)
    assert s.n_frames_available == 6
    assert s.grid.shape == GRID.shape
    for a, b in zip(s.cameras, cams):
        assert a.name == b.name
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)
        np.testing.assert_allclose(a.dist, b.dist)
        np.testing.assert_allclose(a.bg_point, b.bg_point)
        assert a.line_time == b.line_time
        if strobe:  # offsets are hidden truth: the pipeline must measure them
            assert a.time_offset is None
        else:
            assert a.time_offset == pytest.approx(b.time_offset)
    assert (s.strobe_search is not None) == strobe
    # paths are relative to the manifest
    text = path.read_text()
    assert str(tmp_path) not in text


def test_sixteen_bit_frames_round_trip(tmp_path):
    path, _ = _write_session(tmp_path, strobe=True, bit_depth=16)
    s = load_session(path)
    assert s.n_frames_available == 6


def test_truth_group_round_trip(tmp_path):
    fine = Grid((0, 0, 0), (0.02, 0.01, 0.03), 0.005)
    tw = sio.TruthWriter(tmp_path / "truth.zarr", grid=fine, n_frames=2, n_knots=3, n_cameras=2,
                         flow_shape=(4, 5), attrs={"phantom": "blob"})
    tw.write_times([0.1, 0.2], [0.05, 0.15, 0.25], [-0.01, -0.02])
    vol = np.random.default_rng(0).normal(size=fine.shape)
    for j in range(3):
        tw.write_knot(j, vol + j)
    tw.write_refractivity(0, vol)
    tw.write_refractivity(1, vol * 2)
    tw.write_camera_frame(1, 0, d_in=np.ones((4, 5, 3)), deflection=np.full((4, 5, 2), 0.25))
    t = sio.read_truth(tmp_path / "truth.zarr")
    np.testing.assert_allclose(t.time, [0.1, 0.2])
    np.testing.assert_allclose(t.knot_time, [0.05, 0.15, 0.25])
    np.testing.assert_allclose(t.time_offset, [-0.01, -0.02])
    np.testing.assert_allclose(t.refractivity[1], (vol * 2).astype(np.float32))
    np.testing.assert_allclose(t.grid_origin, fine.origin)
    assert t.attrs["phantom"] == "blob"
    g = zarr.open_group(str(tmp_path / "truth.zarr"), mode="r")
    assert tuple(g["deflection"].metadata.dimension_names) == ("camera", "frame", "v", "u", "component")
    assert tuple(g["refractivity"].metadata.dimension_names) == ("frame", "z", "y", "x")
    assert np.all(g["deflection"][1, 0] == 0.25)
    assert np.isnan(g["deflection"][0, 0]).all()      # not written: NaN fill


def test_store_reader_errors(tmp_path):
    with pytest.raises(StoreError, match="does not exist"):
        sio.read_store_refractivity(tmp_path / "nope.zarr")
    g = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    g.create_array("time", shape=(1,), dtype="float64")
    with pytest.raises(StoreError, match="refractivity"):
        sio.read_store_refractivity(tmp_path / "s.zarr")
    with pytest.raises(StoreError, match="truth"):
        sio.read_truth(tmp_path / "s.zarr")


def test_printable_background(tmp_path):
    info = sio.export_background(tmp_path / "bg.png", 300, 200, 150.0, seed=2)
    assert info["width_mm"] == pytest.approx(300 / 150 * 25.4)
    im = Image.open(tmp_path / "bg.png")
    assert im.size == (300, 200)
    assert im.info["dpi"] == pytest.approx((150, 150), abs=0.5)
    a = np.asarray(im, dtype=float)
    assert 20 < a.std() < 50
