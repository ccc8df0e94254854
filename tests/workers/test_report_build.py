"""The HTML report as built by ``workers.report``: read via storage, computed via pipeline.

Uses the synthetic store of tests/storage/test_report.py (a hot Gaussian blob rising over
3 frames, 2 cameras whose flow is the blob's exact re-projection plus Gaussian noise of
known RMS), so the page's re-projection residual must equal that noise.
"""

from __future__ import annotations

import importlib.util
import json
import re
from html.parser import HTMLParser
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from schlieren.storage.errors import StoreError
from schlieren.workers.report import build_report


def _fixture_module():
    path = Path(__file__).parents[1] / "storage" / "test_report.py"
    spec = importlib.util.spec_from_file_location("_schlieren_report_store_fixture_workers", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


FX = _fixture_module()
make_store, N_FRAMES, FRAME_RATE, NOISE_PX = FX.make_store, FX.N_FRAMES, FX.FRAME_RATE, FX.NOISE_PX


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links = []

    def handle_starttag(self, tag, attrs):
        for k, v in attrs:
            if k in ("src", "href") and v and not v.startswith("#"):
                self.links.append(v)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    store = make_store(root)
    evaluation = {"truth": "truth.zarr", "overall": {"rms": 0.0125, "psnr": 38.06, "mean_psnr": 38.1, "frames": 3},
                  "frames": [{"frame": k, "time": (1 + k) / FRAME_RATE, "rms": 0.0125, "psnr": 38.06,
                              "truth_from": "frame"} for k in range(N_FRAMES)]}
    index = build_report(store, root / "out", evaluation=evaluation)
    return store, index


def test_report_writes_page_with_existing_relative_links(report):
    store, index = report
    assert index.name == "index.html" and index.exists()
    parser = _Links()
    parser.feed(index.read_text())
    assert len(parser.links) >= 10
    for link in parser.links:
        assert not link.startswith(("/", "http:", "https:", "file:")), link
        assert (index.parent / link).exists(), link
    html = index.read_text()
    for name in ("deflection_cam00.png", "deflection_cam01.png", "hull.png", "slices_refractivity.png",
                 "slices_temperature.png", "render.png", "render.gif", "residual_cam00.png", "timings.png"):
        assert f"figures/{name}" in html, name
    assert "synthetic-blob" in html
    assert "Missing from the store" not in html
    assert "capture frame 2" in html  # store frame 1 of a run over capture frames 1..3
    # every navigation link has its section
    anchors = re.findall(r'<nav>(.*?)</nav>', html)[0]
    for target in re.findall(r'href="#([^"]+)"', anchors):
        assert f'<section id="{target}">' in html, target
    # the accuracy table (SPEC section 4) from the evaluation passed in
    assert re.search(r"<td>overall</td><td></td><td>1.25</td><td>38.06</td>", html)


def test_figures_are_real_images(report):
    _, index = report
    fig = index.parent / "figures"
    for name in ("deflection_cam00.png", "hull.png", "slices_temperature.png", "residual_cam01.png"):
        img = iio.imread(fig / name)
        assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
        assert img[..., :3].std() > 10  # not a blank canvas


def test_residual_rms_equals_the_known_noise(report):
    """flow = re-projection of the stored gradient + N(0, NOISE_PX) per component, so the
    residual vector RMS must be sqrt(2) * NOISE_PX for every camera."""
    _, index = report
    summary = json.loads((index.parent / "summary.json").read_text())
    res = summary["residual_rms_px"]
    assert set(res) == {"cam00", "cam01"}
    for cam, r in res.items():
        assert r["rms"] == pytest.approx(np.sqrt(2) * NOISE_PX, rel=0.08), cam
        assert r["rms_measured"] > 3 * r["rms"]  # the blob's deflections dominate the noise
        assert r["frames"] == [1, 2, 3]  # capture frames (the fixture's store starts at frame 1)
    html = index.read_text()
    assert re.search(r"<td>cam00</td><td>0\.01\d*</td>", html)


def test_timings_table_lists_stages_and_total(report):
    _, index = report
    html = index.read_text()
    # wall-clock = completed - started; task time as stored
    for stage, wall, task in (("deflection", "5", "9.5"), ("tomography", "7.25", "7"), ("integrate", "1.5", "1.25")):
        assert re.search(rf"<td>{stage}</td><td>[^<]*</td><td>[^<]*</td><td>{re.escape(wall)}</td>"
                         rf"<td>{re.escape(task)}</td>", html), stage
    assert re.search(r"<td>run \(first start to last completion\)</td><td></td><td></td><td>13.75</td>"
                     r"<td>17.75</td>", html)


def test_animation_shows_the_blob_rising(report):
    """Each GIF frame is one rendering; the glow's centroid moves up the image as z grows."""
    _, index = report
    gif = iio.imread(index.parent / "figures" / "render.gif", index=None)
    assert gif.shape[0] == N_FRAMES
    rows = []
    for k in range(N_FRAMES):
        png = iio.imread(index.parent / "figures" / f"render_{k + 1:05d}.png").astype(float)
        w = png.sum(axis=-1)
        w = np.where(w > 0.25 * w.max(), w, 0.0)  # the glow, not the box lines
        rows.append((w.sum(axis=1) * np.arange(w.shape[0])).sum() / w.sum())
    assert rows[0] > rows[1] > rows[2]  # image rows grow downwards


def test_store_with_missing_arrays_reports_what_is_missing(tmp_path):
    store = make_store(tmp_path, partial="missing")
    index = build_report(store, tmp_path / "out", frames=(1, 3), max_cameras=1)
    html = index.read_text()
    assert "Missing from the store" in html
    for missing in ("gradient", "temperature", "attribute stage_times"):
        assert missing in html
    figs = tmp_path / "out" / "figures"
    assert not (figs / "slices_temperature.png").exists()
    assert (figs / "slices_refractivity.png").exists()
    # residuals fall back to central differences of the refractivity
    assert "central differences of the refractivity" in html
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["frames"] == [1, 3] and summary["shown_frame"] == 2
    for r in summary["residual_rms_px"].values():
        assert r["rms"] < 0.5 * r["rms_measured"]  # still explains most of the deflection


def test_unfinished_run_shows_completed_frames_only(tmp_path):
    """The last frame's tomography is not done (NaN chunks, marker unset): the report
    picks its single-frame figures among finished frames, renders only those, and lists
    the completion markers."""
    store = make_store(tmp_path, partial="unfinished")
    index = build_report(store, tmp_path / "out", max_cameras=1)
    html = index.read_text()
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["shown_frame"] in (1, 2)  # capture frames
    assert summary["completion"]["integrate"] == "2 of 3" and summary["completion"]["hull"] == "3 of 3"
    assert summary["completion"]["threshold"] == "0 of 1" and summary["completion"]["sync"] == "2 of 2"
    assert "Not reconstructed yet: frames 3" in html
    figs = tmp_path / "out" / "figures"
    assert (figs / "render_00002.png").exists() and not (figs / "render_00003.png").exists()
    assert len(iio.imread(figs / "render.gif", index=None)) == 2
    for r in summary["residual_rms_px"].values():
        assert r["frames"] == [1, 2]
    assert "integrate" not in summary["stage_seconds"]


def test_bad_store_is_a_one_line_error(tmp_path):
    with pytest.raises(StoreError, match="not found"):
        build_report(tmp_path / "nope.zarr", tmp_path / "out")
    g = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    g.attrs["format"] = "something-else/2"
    with pytest.raises(StoreError, match="unknown store format"):
        build_report(tmp_path / "other.zarr", tmp_path / "out")
    store = make_store(tmp_path / "s", partial="missing")
    with pytest.raises(StoreError, match="frame range"):
        build_report(store, tmp_path / "out", frames=(5, 9))


def test_report_command_prints_index_path(report, tmp_path, capsys, monkeypatch):
    """The CLI glue: arguments reach build_report, the default folder sits beside the store,
    the path of index.html is printed; a missing store is a one-line error (exit 2)."""
    import schlieren.workers.report.make as glue
    from schlieren.workers.cli import main

    store, index = report
    calls = []

    def fake_build_report(store_path, out_dir, *, frames=None, max_cameras=None, evaluation=None):
        calls.append((Path(store_path), Path(out_dir), frames, max_cameras))
        return Path(out_dir) / "index.html"

    monkeypatch.setattr(glue, "build_report", fake_build_report)
    assert main(["report", str(store), "--frames", "0:2", "--cameras", "1"]) == 0
    assert calls == [(store, store.parent / "run_report", (0, 2), 1)]
    assert capsys.readouterr().out.strip() == str(store.parent / "run_report" / "index.html")
    monkeypatch.undo()
    assert main(["report", str(tmp_path / "missing.zarr")]) == 2
    err = capsys.readouterr().err
    assert "not found" in err and len(err.strip().splitlines()) == 1


def test_figures_are_the_pipelines_images_written_unchanged(report):
    """The orchestration hands the figure modules' pixels to storage as they are: the hull figure
    and the shown frame's four-view rendering, redrawn from the stored data, match the files."""
    from schlieren.storage.report import ReportReader
    from schlieren.workers.report import figures, volume_figures, volume_render

    store, index = report
    summary = json.loads((index.parent / "summary.json").read_text())
    assert summary["shown_frame"] == 2  # the middle of 3 complete frames, as a capture index
    shown = 1  # its store index
    rd = ReportReader(store)
    grid = rd.grid()
    hull = rd.volume("hull", shown).astype(bool)
    want = figures.figure_to_rgb(volume_figures.hull_figure(hull, grid, title="visual hull, frame 2"))
    np.testing.assert_array_equal(iio.imread(index.parent / "figures" / "hull.png"), want)
    r_amb = rd.medium().refractivity_ambient
    deficit = max(float(np.nanmax(r_amb - rd.volume("refractivity", f))) for f in range(N_FRAMES))
    tf = volume_render.TransferFunction(r_ambient=r_amb, scale=deficit)
    size = volume_render.fit_image_size(grid, azimuth_deg=30.0, elevation_deg=15.0, long_side=360)
    first = volume_render.render_volume(rd.volume("refractivity", shown), grid, azimuth_deg=30.0,
                                       elevation_deg=15.0, transfer=tf, image_size=size)
    views = iio.imread(index.parent / "figures" / "render_views.png")
    np.testing.assert_array_equal(views[:, :first.shape[1]], first)
