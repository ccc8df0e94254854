"""``schlieren check`` on a small session written with known defects (issue 33 item 6):
the table, the notes and the HTML page report them; ``--watch`` prints only what changes
and ends cleanly on Ctrl-C; a millimetre calibration is refused before any reading."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pipeline"))
from rigcheck_images import Texture, noisy  # noqa: E402

from schlieren.pipeline.geometry import Grid  # noqa: E402
from schlieren.pipeline.synthetic.rig import make_rig  # noqa: E402
from schlieren.storage.errors import SessionError  # noqa: E402
from schlieren.workers.check import check_session, table_text, watch, write_page  # noqa: E402

SIZE = (240, 180)  # width, height
GRID = Grid((-0.075, -0.075, 0.0), (0.075, 0.075, 0.3), 0.005)
SHIFT = (0.2, -0.1)  # camera cam01's frames against its reference
HOT = [(40, 50), (100, 200), (150, 30)]  # cam01's hot pixels (row, column)


def write_session(root: Path, *, noise=1.5, n_frames=8) -> Path:
    """Two cameras, PNG frames: 6 reference frames, a flash in frame 1 of the strobe window
    [0, 4), frames 4.. to process; camera cam01 moved by SHIFT and has the HOT pixels."""
    cams = make_rig(2, grid=GRID, image_size=SIZE, line_time=5e-5)
    rng = np.random.default_rng(0)
    docs = []
    for k, cam in enumerate(cams):
        tex = Texture(SIZE[::-1], seed=10 + k, contrast=30.0)
        d = SHIFT if k == 1 else (0.0, 0.0)
        for sub in ("reference", "frames"):
            (root / cam.name / sub).mkdir(parents=True, exist_ok=True)

        def save(path, img, hot=(k == 1)):
            img = noisy(img, noise, rng, quantise=True)
            if hot:
                for r, c in HOT:
                    img[r, c] = 255
            cv2.imwrite(str(path), img.astype(np.uint8))

        for i in range(6):
            save(root / cam.name / "reference" / f"{i:03d}.png", tex.render())
        for i in range(n_frames):
            img = tex.render(*d)
            if i == 1:
                img[60:120] += 40.0  # the flash's band of rows
            save(root / cam.name / "frames" / f"{i:05d}.png", img)
        docs.append({"name": cam.name, "frames": f"{cam.name}/frames/%05d.png",
                     "reference": f"{cam.name}/reference/%03d.png", "image_size": list(SIZE),
                     "K": cam.K.tolist(), "dist": cam.dist.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(),
                     "background": {"point": cam.bg_point.tolist(), "normal": cam.bg_normal.tolist()},
                     "rolling_shutter": {"line_time": cam.line_time}})
    manifest = {"format": "schlieren-session/1", "name": "checked", "frame_rate": 60.0,
                "volume": {"min": list(GRID.vmin), "max": list(GRID.vmax), "voxel_size": GRID.voxel_size},
                "sync": {"strobe": {"search_frames": [0, 4]}}, "cameras": docs}
    (root / "session.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return root


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return write_session(tmp_path_factory.mktemp("check") / "session")


def test_check_reports_the_injected_defects(session, tmp_path):
    rig = check_session(session, results=tmp_path)  # no family results there
    a, b = rig.checked
    assert a.name == "cam00" and b.name == "cam01"
    for c in (a, b):
        assert c.noise == pytest.approx(np.sqrt(1.5 ** 2 + 1 / 12), rel=0.05)
        assert c.flash.startswith("frame 1 rows 60-119") and c.offset is not None
    assert a.shift.magnitude < 0.01
    assert abs(b.shift.du - SHIFT[0]) < 0.01 and abs(b.shift.dv - SHIFT[1]) < 0.01
    assert sorted(map(tuple, b.hot.tolist())) == sorted(HOT) and len(a.hot) == 0
    text = table_text(rig)
    assert "cam01: moved against its reference by up to 0.22" in text
    assert "cam01: 3 hot and 0 dead pixels" in text and "cam00:" not in text
    assert "no benchmark family results found" in text
    index = write_page(rig, tmp_path / "page")
    html = index.read_text()
    assert "cam01" in html and "moved against its reference" in html
    assert (tmp_path / "page" / "summary.json").is_file()


def test_check_names_the_family_case_and_its_files(session):
    rig = check_session(session)  # the checkout's benchmarks/results
    if rig.family is None:
        pytest.skip("no benchmarks/results/realistic.json in this checkout")
    text = table_text(rig)
    assert f"nearest case {rig.family.name}" in text and "realistic.json" in text


def test_check_command_prints_the_table_and_writes_the_page(session, tmp_path, capsys):
    from schlieren.workers.cli import main

    assert main(["check", str(session), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[1].split()[:3] == ["camera", "noise", "flow"]
    assert (tmp_path / "out" / "index.html").is_file() and "page:" in out


def test_a_single_reference_image_is_read_and_the_noise_comes_from_the_frames(session, tmp_path):
    """A session whose reference is one image file (what ``schlieren synth`` writes): the
    noise is measured on the checked frames where the rays miss the volume."""
    root = tmp_path / "single"
    shutil.copytree(session, root)
    m = yaml.safe_load((root / "session.yaml").read_text())
    for c in m["cameras"]:
        img = cv2.imread(str(root / c["name"] / "reference" / "000.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(root / c["name"] / "reference.png"), img)
        shutil.rmtree(root / c["name"] / "reference")
        c["reference"] = f"{c['name']}/reference.png"
    (root / "session.yaml").write_text(yaml.safe_dump(m, sort_keys=False))
    rig = check_session(root, results=tmp_path)
    assert len(rig.checked) == 2
    for c in rig.checked:
        assert c.noise_source.startswith("3 frames")
        assert c.noise == pytest.approx(np.sqrt(1.5 ** 2 + 1 / 12), rel=0.05)
    b = rig.checked[1]
    assert abs(b.shift.du - SHIFT[0]) < 0.01 and abs(b.shift.dv - SHIFT[1]) < 0.01
    assert sorted(map(tuple, b.hot.tolist())) == sorted(HOT)


def test_a_millimetre_manifest_is_refused_before_reading(session, tmp_path):
    root = tmp_path / "mm"
    shutil.copytree(session, root)
    m = yaml.safe_load((root / "session.yaml").read_text())
    for c in m["cameras"]:
        c["t"] = [1000 * v for v in c["t"]]
    (root / "session.yaml").write_text(yaml.safe_dump(m))
    with pytest.raises(SessionError, match="calibration in millimetres") as info:
        check_session(root)
    assert info.value.camera == "cam00" and info.value.file.endswith("session.yaml")


def test_watch_prints_only_changes_and_stops_on_ctrl_c(session, tmp_path):
    folder = tmp_path / "live"
    folder.mkdir()
    lines: list[str] = []
    steps = iter([
        lambda: shutil.copytree(session, folder, dirs_exist_ok=True),  # the recording arrives
        lambda: None,  # nothing changes
        lambda: _move_camera(folder, "cam00"),  # a camera is bumped
    ])

    def sleep(_):
        step = next(steps, None)
        if step is None:
            raise KeyboardInterrupt
        step()

    assert watch(folder, interval=0.01, results=tmp_path, out=lines.append, sleep=sleep) == 0
    assert lines[0].startswith("waiting for session.yaml")
    header = [k for k, line in enumerate(lines) if line.startswith("camera")]
    assert len(header) == 1
    rows = [line for line in lines if line.startswith("cam0")]
    assert [r.split()[0] for r in rows] == ["cam00", "cam01", "cam00"]  # cam00 again once it moved
    assert any(line.startswith("note: cam00: moved") for line in lines)
    assert lines[-1] == "watch stopped"


def _move_camera(folder: Path, name: str) -> None:
    for p in sorted((folder / name / "frames").glob("*.png")):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(p), np.roll(img, 1, axis=1))  # one pixel to the right


@pytest.mark.slow
def test_predicted_flow_noise_against_a_serial_run_without_flow(tmp_path):
    """A run of a session without flow: the noise of each camera's stored raw flow is within
    a factor 1.5 of what check predicted for it."""
    import zarr

    from schlieren.pipeline.masks import flow_noise
    from schlieren.workers.api import run

    root = write_session(tmp_path / "still", noise=2.0)
    rig = check_session(root, results=tmp_path)
    run(root, tmp_path / "store.zarr", progress=False)
    raw = zarr.open_group(str(tmp_path / "store.zarr"), mode="r")["flow_raw"][:]
    for c, cam in enumerate(rig.checked):
        measured = float(np.median([flow_noise(raw[c, k]) for k in range(raw.shape[1])
                                    if np.isfinite(raw[c, k]).any()]))
        assert 1 / 1.5 < cam.flow_noise / measured < 1.5, (cam.name, cam.flow_noise, measured)
