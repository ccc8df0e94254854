"""The user documentation stays true: no pointer outside the clone, examples that load."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
USER_DOCS = [REPO / "README.md", REPO / "LICENSE", *sorted((REPO / "docs").glob("*.md")), REPO / "deploy" / "GUIDE.md"]


def blocks(md: Path, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", md.read_text(), flags=re.S)


@pytest.mark.parametrize("path", USER_DOCS, ids=lambda p: p.name)
def test_nothing_user_facing_points_outside_the_clone(path):
    text = path.read_text()
    assert "../shared" not in text and "shared/SPEC" not in text and "SPEC.md" not in text


def test_every_relative_link_in_the_docs_exists():
    for md in USER_DOCS:
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", md.read_text()):
            assert (md.parent / target).exists(), f"{md.name}: broken link {target}"


def test_licence_is_the_declared_bsd_3_clause():
    import tomllib

    meta = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert meta["license"] == "BSD-3-Clause" and "LICENSE" in meta["license-files"]
    assert (REPO / "LICENSE").read_text().startswith("BSD 3-Clause License")


def test_the_session_example_is_a_valid_manifest(tmp_path):
    from schlieren.storage.session import load_session

    (example,) = [b for b in blocks(REPO / "docs" / "session.md", "yaml") if "format: schlieren-session/1" in b]
    (tmp_path / "session.yaml").write_text(example)
    s = load_session(tmp_path, check_files=False)
    cam = s.cameras[0]
    assert s.frames == (40, 160) and s.strobe_search == (30, 40) and s.grid.shape == (120, 60, 60)
    assert cam.center.tolist() == pytest.approx([2.5, 0.0, 0.15])  # C = -R^T t, looking along -x at the box
    assert cam.background_distance() == pytest.approx(5.0)


def test_the_calibration_examples_import(tmp_path):
    from schlieren.storage.calibration_io import import_calibration

    md = REPO / "docs" / "calibration.md"
    yml = [b for b in blocks(md, "yaml") if b.startswith("format:")][0]
    (tmp_path / "rig.yaml").write_text(yml)
    (tmp_path / "rig.json").write_text(blocks(md, "json")[0])
    (tmp_path / "cam00.yml").write_text([b for b in blocks(md, "yaml") if b.startswith("%YAML")][0])
    cams = [import_calibration(str(tmp_path / n)).camera("cam00") for n in ("rig.yaml", "rig.json", "cam00.yml")]
    for c in cams:
        assert c["K"] == cams[0]["K"] and c["R"] == cams[0]["R"] and c["t"] == cams[0]["t"]
        assert c["image_size"] == [1440, 1080] and c["dist"][:2] == [-0.08, 0.11]
    assert yaml.safe_load(yml)["cameras"][0]["rms"] == 0.12


def test_the_store_page_lists_every_array_of_the_layout():
    from schlieren.pipeline.geometry import Grid
    from schlieren.storage.layout import result_layout

    text = (REPO / "docs" / "store.md").read_text()
    grid = Grid((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), 0.01)
    for spec in result_layout(camera_names=["a"], n_frames=2, flow_shape=(4, 5), grid=grid, flow_factor=3,
                              n_raw=4, raw_first=0, image_shape=(12, 15), row_knots=[0.0, 11.0]):
        assert f"`{spec.name}`" in text, spec.name
        units = spec.attrs.get("units")
        if units and units != "1":
            assert units in text, (spec.name, units)
