"""The report's file layer (``storage.report``) on a small synthetic result store with known answers.

``make_store`` builds a store in the layout of SPEC section 2 / docs/design.md: a hot
Gaussian blob rising over 3 frames on a 24 x 20 x 16 grid, its exact gradient, a hull,
derived quantities, and 2 cameras whose flow is the blob's re-projected deflection plus
Gaussian noise of known RMS (so the report's re-projection residual must equal the noise).
It is also used by tests/workers/test_report_build.py (the report's figures and
residuals), tests/storage/test_export.py and tests/e2e/test_report_browser.py.

Here: the read model returns the store's plain data exactly, the writer writes what it is
handed, and this module computes nothing (it imports no pipeline kernel).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from schlieren.pipeline.geometry import Camera, FlowGrid, Grid, Medium
from schlieren.pipeline.residuals import predict_flows
from schlieren.pipeline.tomography import build_geometry
from schlieren.storage.errors import StoreError
from schlieren.storage.report import ReportPage, ReportReader, ReportWriter, frame_range, html_img, html_table

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
    _write_frames(session_dir, rng)
    refr, grads = zip(*(blob(f) for f in range(N_FRAMES)))
    fg = FlowGrid(IMAGE, FACTOR)
    geom = build_geometry(CAMERAS, GRID, fg)
    flows = [predict_flows(geom, CAMERAS, g, n_ambient=MEDIUM.n_ambient) for g in grads]
    flows = [f + rng.normal(0.0, NOISE_PX, f.shape) for f in flows]
    layout = result_layout(camera_names=[c.name for c in CAMERAS], n_frames=N_FRAMES, flow_shape=fg.shape,
                           grid=GRID, first_frame=1)
    st = ResultStore.create(str(store_path), layout, attrs=_store_attrs(session_dir, fg, partial),
                            markers=stage_markers())
    _fill_store(st, flows, refr, grads, partial)
    if partial == "missing":
        g = zarr.open_group(str(store_path), mode="r+")
        del g["gradient"]
        del g["temperature"]
    return store_path


def _write_frames(session_dir: Path, rng) -> None:
    """Noise PNG frames for every camera (the report shows them beside the deflections)."""
    for cam in CAMERAS:
        d = session_dir / cam.name / "frames"
        d.mkdir(parents=True, exist_ok=True)
        for k in range(N_FRAMES + 2):
            iio.imwrite(d / f"{k:05d}.png", rng.integers(0, 256, (IMAGE[1], IMAGE[0]), dtype=np.uint8))


def _store_attrs(session_dir: Path, fg: FlowGrid, partial: str | None) -> dict:
    """The store's attributes as a run writes them: session, params, run, stage_times."""
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
    return attrs


def _fill_store(st, flows, refr, grads, partial: str | None) -> None:
    """Every array chunk by chunk with its completion marker, as a run leaves them."""
    st.write("time", slice(None), (1 + np.arange(N_FRAMES)) / FRAME_RATE)
    st.write("time_offset", slice(None), np.zeros(len(CAMERAS)))
    finished = N_FRAMES - 1 if partial == "unfinished" else N_FRAMES
    for stage in ("clock", "geometry"):
        st.mark_done(stage, ())
    for c in range(len(CAMERAS)):
        st.mark_done("sync", c)
        for f in range(N_FRAMES):
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



STORAGE_REPORT = Path(__file__).resolve().parents[2] / "storage" / "report"  # the package: reader, writer
COMPUTING_MODULES = ("schlieren.workers.report.figures", "schlieren.workers.report.volume_figures",
                     "schlieren.workers.report.volume_render", "schlieren.pipeline.residuals",
                     "schlieren.pipeline.tomography")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_store(tmp_path_factory.mktemp("report_store"))


def _stored(store_path, name, index):
    """What the store holds, cast as the reader casts it (float64)."""
    return np.asarray(zarr.open_group(str(store_path), mode="r")[name][index]).astype(np.float64)


def test_reader_returns_the_stores_plain_data(store):
    rd = ReportReader(store)
    assert rd.name == "synthetic-blob" and rd.n_frames == N_FRAMES and rd.missing_arrays == []
    grid = rd.grid()
    assert grid.shape == GRID.shape == (16, 20, 24)
    np.testing.assert_allclose(grid.vmin, GRID.vmin, atol=1e-12)
    np.testing.assert_allclose(grid.vmax, GRID.vmax, atol=1e-12)
    assert grid.voxel_size == pytest.approx(GRID.voxel_size, rel=1e-12)
    cams, note = rd.cameras()
    assert note == "" and [c.name for c in cams] == [c.name for c in CAMERAS]
    for got, want in zip(cams, CAMERAS):
        np.testing.assert_allclose(got.K, want.K)
        np.testing.assert_allclose(got.R, want.R)
        np.testing.assert_allclose(got.t, want.t)
        assert got.image_size == IMAGE and got.time_offset == 0.0
    med = rd.medium()
    assert med.n_ambient == MEDIUM.n_ambient and med.T_ambient == MEDIUM.T_ambient
    np.testing.assert_array_equal(rd.times(), (1 + np.arange(N_FRAMES)) / FRAME_RATE)
    assert rd.params["tomography"]["step"] == 0.25
    assert rd.mask_threshold() == 0.05
    # volumes come back as float64 with the stored values; the blob of frame 1 is where it was put
    r1 = rd.volume("refractivity", 1)
    assert r1.dtype == np.float64 and r1.shape == GRID.shape
    np.testing.assert_array_equal(r1, _stored(store, "refractivity", 1))
    np.testing.assert_allclose(r1, blob(1)[0], rtol=0, atol=1e-10)
    g2 = rd.volume("gradient", 2)
    np.testing.assert_allclose(g2, blob(2)[1], rtol=1e-6, atol=1e-6 * np.abs(blob(2)[1]).max())
    assert rd.volume("hull", 0).dtype == bool
    flow = rd.camera_frame("flow", 1, 2)
    assert flow.shape == FlowGrid(IMAGE, FACTOR).shape + (2,)
    np.testing.assert_array_equal(flow, _stored(store, "flow", (1, 2)))
    assert rd.shape("flow") == (2, N_FRAMES) + FlowGrid(IMAGE, FACTOR).shape + (2,)
    # store frame f is capture frame 1 + f; the camera image is the PNG make_store wrote there
    assert [rd.capture_index(f) for f in range(N_FRAMES)] == [1, 2, 3]
    image, source = rd.camera_image(1, rd.capture_index(1))
    want = iio.imread(store.parent / "session" / "cam01" / "frames" / "00002.png")
    np.testing.assert_array_equal(image, want.astype(np.float32))
    assert "capture frame 2" in source
    completion = dict((s, (n, t)) for s, n, t in rd.completion())
    assert completion["integrate"] == (3, 3) and completion["deflection"] == (6, 6)


def test_reader_of_a_partial_run_reads_missing_as_none(tmp_path):
    rd = ReportReader(make_store(tmp_path / "u", partial="unfinished"))
    np.testing.assert_array_equal(rd.frame_done("refractivity", N_FRAMES), [True, True, False])
    np.testing.assert_array_equal(rd.frame_done("hull", N_FRAMES), [True, True, True])
    assert rd.volume("refractivity", 2) is None and rd.volume("gradient", 2) is None
    assert rd.volume("refractivity", 1) is not None
    assert rd.mask_threshold() is None
    assert dict((s, (n, t)) for s, n, t in rd.completion())["integrate"] == (2, 3)
    assert "stage_times" in rd.attrs and "integrate" not in rd.attrs["stage_times"]

    rd = ReportReader(make_store(tmp_path / "m", partial="missing"))
    assert rd.missing_arrays == ["gradient", "temperature"]
    assert not rd.has("gradient") and rd.has("refractivity")
    assert rd.volume("gradient", 0) is None and rd.volume("temperature", 0) is None
    np.testing.assert_array_equal(rd.frame_done("gradient", N_FRAMES), [False] * N_FRAMES)
    assert "stage_times" not in rd.attrs
    assert rd.grid().shape == GRID.shape  # from the first volume array present (hull)


def test_reader_without_a_session_frame_source_says_why(store, tmp_path):
    import shutil

    copy = tmp_path / "run.zarr"
    shutil.copytree(store, copy)
    g = zarr.open_group(str(copy), mode="r+")
    g.attrs["session_path"] = str(tmp_path / "gone" / "session.yaml")
    image, why = ReportReader(copy).camera_image(0, 1)
    assert image is None and why.startswith("camera frame not readable")
    del g.attrs["session_path"]
    image, why = ReportReader(copy).camera_image(0, 1)
    assert image is None and why == "the store does not name the session's frames"


def test_writer_writes_what_it_is_handed(tmp_path):
    rng = np.random.default_rng(1)
    out = tmp_path / "out"
    (out / "figures").mkdir(parents=True)
    (out / "figures" / "stale.png").write_bytes(b"old")
    (out / "figures" / "stale.gif").write_bytes(b"old")
    w = ReportWriter(out)
    assert not any((out / "figures").iterdir())  # an earlier report's figures are gone
    rgb = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    assert w.image("a.png", rgb) == "figures/a.png"
    np.testing.assert_array_equal(iio.imread(out / "figures" / "a.png"), rgb)
    frames = np.stack([np.full((8, 10, 3), v, np.uint8) for v in (0, 128, 255)])
    assert w.animation("anim.gif", frames, fps=10.0) == "figures/anim.gif"
    back = iio.imread(out / "figures" / "anim.gif", index=None)
    assert back.shape[0] == 3
    np.testing.assert_array_equal(back[..., :3].reshape(3, -1).mean(axis=1), [0, 128, 255])
    with pytest.raises(ValueError):
        w.image("../escape.png", rgb)
    with pytest.raises(ValueError):
        w.image("b.png", rgb.astype(np.float64))

    page = ReportPage(title="schlieren report: <x>")
    page.missing = ["gradient"]
    page.add("Numbers (one)", html_table(["a", "b"], [[1, "<2>"]], "num") + html_img("figures/a.png", "A", "cap"),
             "numbers")
    page.summary.update({"count": np.int64(3), "value": np.float32(0.5), "bad": np.float32("nan")})
    index = w.finish(page)
    assert index == out / "index.html"
    text = index.read_text()
    assert "<title>schlieren report: &lt;x&gt;</title>" in text
    assert '<nav><a href="#numbers">Numbers</a></nav>' in text
    assert '<section id="numbers"><h2>Numbers (one)</h2>' in text
    assert "<td>1</td><td>&lt;2&gt;</td>" in text and '<img src="figures/a.png" alt="A">' in text
    assert "Missing from the store (partial run?): gradient." in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary == {"count": 3, "value": 0.5, "bad": None, "figures": ["figures/a.png", "figures/anim.gif"]}


def test_bad_store_or_frame_range_is_a_store_error(tmp_path):
    with pytest.raises(StoreError, match="not found"):
        ReportReader(tmp_path / "nope.zarr")
    g = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    g.attrs["format"] = "something-else/2"
    with pytest.raises(StoreError, match="unknown store format"):
        ReportReader(tmp_path / "other.zarr")
    with pytest.raises(StoreError, match="frame range"):
        frame_range((5, 9), N_FRAMES)
    assert frame_range((1, None), N_FRAMES) == range(1, 3) and frame_range(None, N_FRAMES) == range(3)


def _imported_modules(path: Path) -> set[str]:
    """Every module an ``import`` statement in ``path`` names (``from a import b`` gives a and a.b)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"relative import in {path.name}: line {node.lineno}"
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def test_ast_import_check_sees_computing_imports(tmp_path):
    """The checker below is not vacuous: it finds each way of importing a kernel module."""
    src = tmp_path / "m.py"
    for line in ("from schlieren.workers.report import figures", "import schlieren.pipeline.residuals as r",
                 "from schlieren.pipeline.tomography import build_geometry",
                 "def f():\n    from schlieren.pipeline import tomography\n"):
        src.write_text(line + "\n")
        assert _imported_modules(src) & set(COMPUTING_MODULES), line


def test_storage_report_does_not_import_computing_modules():
    """storage/report/ only reads and writes (STYLE.md): the figures and residuals are
    made in workers/report/, so no drawing or pipeline kernel module is imported here, not
    even inside a function, and importing it loads none of them (nor matplotlib)."""
    modules = sorted(STORAGE_REPORT.glob("*.py"))
    assert {p.name for p in modules} >= {"__init__.py", "reader.py", "writer.py"}
    found = set().union(*(_imported_modules(p) for p in modules))
    assert "schlieren.pipeline.geometry" in found  # the plain types are allowed (and parsed)
    assert not found & set(COMPUTING_MODULES), found & set(COMPUTING_MODULES)
    assert not {m for m in found if m.startswith("schlieren.workers")}
    code = ("import sys\nimport schlieren.storage.report\n"
            f"print(','.join(sorted(m for m in sys.modules if m in {COMPUTING_MODULES!r} "
            "or m.split('.')[0] == 'matplotlib')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
