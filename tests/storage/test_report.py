"""The HTML report of a small synthetic result store with known answers.

``make_store`` builds a store in the layout of SPEC section 2 / docs/design.md: a hot
Gaussian blob rising over 3 frames on a 24 x 20 x 16 grid, its exact gradient, a hull,
derived quantities, and 2 cameras whose flow is the blob's re-projected deflection plus
Gaussian noise of known RMS (so the report's re-projection residual must equal the noise).
It is also used by tests/storage/test_export.py and tests/e2e/test_report_browser.py.
"""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid, Medium
from schlieren.pipeline.residuals import predict_flows
from schlieren.pipeline.tomography import build_geometry
from schlieren.storage.errors import StoreError
from schlieren.storage.report import write_report

MEDIUM = Medium()
R_AMB = MEDIUM.refractivity_ambient
GRID = Grid((-0.03, -0.025, 0.0), (0.03, 0.025, 0.04), 0.0025)  # nx, ny, nz = 24, 20, 16
N_FRAMES = 3
FRAME_RATE = 60.0
AMP = 1.5e-4     # refractivity deficit at the blob centre (about 600 K at the peak)
SIGMA = 0.006    # metres
NOISE_PX = 0.01  # per flow component
IMAGE = (96, 72)
FACTOR = 2


def blob_centre(f: int) -> np.ndarray:
    return np.array([0.002, -0.001, 0.012 + 0.008 * f])  # rises 8 mm per frame


def blob(f: int):
    X = GRID.centres()
    d = X - blob_centre(f)
    g = AMP * np.exp(-np.sum(d ** 2, axis=-1) / (2 * SIGMA ** 2))
    return R_AMB - g, d / SIGMA ** 2 * g[..., None]


def look_at(name, eye, target=(0.0, 0.0, 0.02), f=900.0, bg_distance=2.0):
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    W, H = IMAGE
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    return Camera(name, K, np.zeros(5), R, -R @ eye, IMAGE, target + bg_distance * z, -z)


CAMERAS = [look_at("cam00", [0.55, -0.25, 0.05]), look_at("cam01", [-0.3, -0.52, 0.03])]


def make_store(root: Path, *, partial: str | None = None, seed: int = 0) -> Path:
    """Write a synthetic session folder (camera PNG frames) and its result store under root.

    The store is made by the project's own writer (``ResultStore.create`` with
    ``result_layout`` and the stage markers), chunk by chunk with completion markers, as a
    run leaves it. ``partial="unfinished"``: the last frame's tomography and integration
    and the mask threshold are not done (NaN chunks, markers unset) and ``stage_times``
    lacks them. ``partial="missing"``: ``gradient`` and ``temperature`` are deleted and
    there are no ``stage_times``.
    """
    from schlieren.storage.layout import result_layout, stage_markers
    from schlieren.storage.store import ResultStore

    rng = np.random.default_rng(seed)
    session_dir = root / "session"
    store_path = root / "run.zarr"
    for cam in CAMERAS:
        d = session_dir / cam.name / "frames"
        d.mkdir(parents=True, exist_ok=True)
        for k in range(N_FRAMES + 2):
            iio.imwrite(d / f"{k:05d}.png", rng.integers(0, 256, (IMAGE[1], IMAGE[0]), dtype=np.uint8))
    refr, grads = zip(*(blob(f) for f in range(N_FRAMES)))
    fg = FlowGrid(IMAGE, FACTOR)
    geom = build_geometry(CAMERAS, GRID, fg)
    flows = [predict_flows(geom, CAMERAS, g, n_ambient=MEDIUM.n_ambient) for g in grads]
    flows = [f + rng.normal(0.0, NOISE_PX, f.shape) for f in flows]

    session = {
        "format": "schlieren-session/1", "name": "synthetic-blob", "frame_rate": FRAME_RATE, "frames": [1, 4],
        "volume": {"min": list(GRID.vmin), "max": list(GRID.vmax), "voxel_size": GRID.voxel_size},
        "medium": {"n_ambient": MEDIUM.n_ambient, "T_ambient": MEDIUM.T_ambient},
        "cameras": [{
            "name": cam.name, "frames": f"{cam.name}/frames/%05d.png", "reference": f"{cam.name}/frames/00000.png",
            "image_size": list(cam.image_size), "K": cam.K.tolist(), "dist": cam.dist.tolist(),
            "R": cam.R.tolist(), "t": cam.t.tolist(),
            "background": {"point": cam.bg_point.tolist(), "normal": cam.bg_normal.tolist()},
            "rolling_shutter": {"line_time": 0.0}, "time_offset": 0.0} for cam in CAMERAS],
    }
    stage_times = {
        "deflection": {"started": "2026-11-21T08:00:00+00:00", "completed": "2026-11-21T08:00:05+00:00",
                       "task_seconds": 9.5, "executor": "serial"},
        "tomography": {"started": "2026-11-21T08:00:05+00:00", "completed": "2026-11-21T08:00:12.250000+00:00",
                       "task_seconds": 7.0, "executor": "serial"},
        "integrate": {"started": "2026-11-21T08:00:12.250000+00:00", "completed": "2026-11-21T08:00:13.750000+00:00",
                      "task_seconds": 1.25, "executor": "serial"},
    }
    if partial == "unfinished":
        del stage_times["integrate"]
    attrs = {"session": session, "session_path": str(session_dir / "session.yaml"), "session_name": "synthetic-blob",
             "params": {"flow": {"factor": FACTOR}, "tomography": {"step": 0.25, "n_ambient": MEDIUM.n_ambient}},
             "version": "0.1.0", "fingerprint": "fixture",
             "run": {"frames": [1, 1 + N_FRAMES], "n_frames": N_FRAMES, "flow_factor": FACTOR,
                     "flow_shape": list(fg.shape)}}
    if partial != "missing":
        attrs["stage_times"] = stage_times
    layout = result_layout(camera_names=[c.name for c in CAMERAS], n_frames=N_FRAMES, flow_shape=fg.shape,
                           grid=GRID, first_frame=1)
    st = ResultStore.create(str(store_path), layout, attrs=attrs, markers=stage_markers())
    st.write("time", slice(None), (1 + np.arange(N_FRAMES)) / FRAME_RATE)
    st.write("time_offset", slice(None), np.zeros(len(CAMERAS)))
    finished = N_FRAMES - 1 if partial == "unfinished" else N_FRAMES
    for stage in ("clock", "geometry"):
        st.mark_done(stage, ())
    for c in range(len(CAMERAS)):
        st.mark_done("sync", c)
        for f in range(N_FRAMES):
            st.mark_done("frames", (c, f))
            st.mark_done("deflection", (c, f))
    if partial != "unfinished":
        st.write("mask_threshold", slice(None), [0.05])
        st.mark_done("threshold", ())
    for f in range(N_FRAMES):
        for c in range(len(CAMERAS)):
            flow = flows[f][c]
            st.write("flow", (c, f), flow)
            st.write("potential", (c, f), np.cumsum(flow[..., 0], axis=-1))
            st.write("mask", (c, f), np.hypot(flow[..., 0], flow[..., 1]) > 0.05)
            for stage in ("resample", "potential", "mask"):
                st.mark_done(stage, (c, f))
        r = refr[f]
        st.write("hull", f, (R_AMB - r) > 0.02 * AMP)
        st.mark_done("hull", f)
        if f < finished:
            st.write("gradient", f, grads[f])
            st.mark_done("tomography", f)
            st.write("refractivity", f, r)
            st.write("temperature", f, MEDIUM.T_ambient * R_AMB / r)
            st.write("density", f, r / MEDIUM.gladstone_dale)
            st.mark_done("integrate", f)
    if partial == "missing":
        g = zarr.open_group(str(store_path), mode="r+")
        del g["gradient"]
        del g["temperature"]
    return store_path


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
    index = write_report(store, root / "out", evaluation=evaluation)
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
        assert r["frames"] == [0, 1, 2]
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
        png = iio.imread(index.parent / "figures" / f"render_{k:05d}.png").astype(float)
        w = png.sum(axis=-1)
        w = np.where(w > 0.25 * w.max(), w, 0.0)  # the glow, not the box lines
        rows.append((w.sum(axis=1) * np.arange(w.shape[0])).sum() / w.sum())
    assert rows[0] > rows[1] > rows[2]  # image rows grow downwards


def test_store_with_missing_arrays_reports_what_is_missing(tmp_path):
    store = make_store(tmp_path, partial="missing")
    index = write_report(store, tmp_path / "out", frames=(1, 3), max_cameras=1)
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
    index = write_report(store, tmp_path / "out", max_cameras=1)
    html = index.read_text()
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["shown_frame"] in (0, 1)
    assert summary["completion"]["integrate"] == "2 of 3" and summary["completion"]["hull"] == "3 of 3"
    assert summary["completion"]["threshold"] == "0 of 1" and summary["completion"]["sync"] == "2 of 2"
    assert "Not reconstructed yet: frames 2" in html
    figs = tmp_path / "out" / "figures"
    assert (figs / "render_00001.png").exists() and not (figs / "render_00002.png").exists()
    assert len(iio.imread(figs / "render.gif", index=None)) == 2
    for r in summary["residual_rms_px"].values():
        assert r["frames"] == [0, 1]
    assert "integrate" not in summary["stage_seconds"]


def test_bad_store_is_a_one_line_error(tmp_path):
    with pytest.raises(StoreError, match="not found"):
        write_report(tmp_path / "nope.zarr", tmp_path / "out")
    g = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    g.attrs["format"] = "something-else/2"
    with pytest.raises(StoreError, match="unknown store format"):
        write_report(tmp_path / "other.zarr", tmp_path / "out")
    store = make_store(tmp_path / "s", partial="missing")
    with pytest.raises(StoreError, match="frame range"):
        write_report(store, tmp_path / "out", frames=(5, 9))


def test_report_command_prints_index_path(report, tmp_path, capsys, monkeypatch):
    """The CLI glue: arguments reach write_report, the default folder sits beside the store,
    the path of index.html is printed; a missing store is a one-line error (exit 2)."""
    import schlieren.workers.report as glue
    from schlieren.workers.cli import main

    store, index = report
    calls = []

    def fake_write_report(store_path, out_dir, *, frames=None, max_cameras=None, evaluation=None):
        calls.append((Path(store_path), Path(out_dir), frames, max_cameras))
        return Path(out_dir) / "index.html"

    monkeypatch.setattr(glue, "write_report", fake_write_report)
    assert main(["report", str(store), "--frames", "0:2", "--cameras", "1"]) == 0
    assert calls == [(store, store.parent / "run_report", (0, 2), 1)]
    assert capsys.readouterr().out.strip() == str(store.parent / "run_report" / "index.html")
    monkeypatch.undo()
    assert main(["report", str(tmp_path / "missing.zarr")]) == 2
    err = capsys.readouterr().err
    assert "not found" in err and len(err.strip().splitlines()) == 1
