"""The realistic benchmark family (``schlieren bench realistic``): rig, scaling, scoring."""

from __future__ import annotations

import json

import numpy as np
import pytest

from schlieren.storage import synthetic_io as sio
from schlieren.workers import realistic as rb
from schlieren.workers.cli import main


def test_case_selection_and_roles():
    assert {c.role for c in rb.CASES} == {"tune", "report"}
    tune = rb.select_cases(None, role="tune")
    report = rb.select_cases(None, role="report")
    assert tune and report
    # no flow is shared between the tune and the report set
    assert not {c.flow for c in tune} & {c.flow for c in report}
    assert {c.cameras for c in rb.CASES} == {8, 16}
    assert any(c.video == "h264" for c in rb.CASES) and any(c.distortion for c in rb.CASES)
    assert rb.select_cases("plume1-16") == tuple(c for c in rb.CASES if c.name.startswith("plume1-16"))
    with pytest.raises(ValueError, match="unknown case"):
        rb.select_cases("nope")
    # the bitrate cases run only by name; an exact name does not pull in the names it prefixes
    assert not set(rb.BITRATE_CASES) & set(rb.select_cases(None))
    assert [c.name for c in rb.select_cases("plume2-8cam-960-dist-h264")] == ["plume2-8cam-960-dist-h264"]
    assert {c.bits_per_pixel for c in rb.select_cases("plume2-8cam-960-dist-h264-")} == {0.5, 1.0}
    # the content key changes with anything that changes the rendered session, not with the role
    c = rb.CASES[0]
    import dataclasses

    assert dataclasses.replace(c, role="report").key() == c.key()
    assert dataclasses.replace(c, noise=2.0).key() != c.key()


@pytest.mark.slow
def test_quick_case_end_to_end(tmp_path):
    """The quick case renders at the requested deflection, runs, and scores both metrics."""
    results = tmp_path / "results"
    assert main(["bench", "realistic", "--quick", "--out", str(tmp_path / "work"), "--results", str(results)]) == 0
    res = json.loads((results / "realistic.json").read_text())
    (case,) = res["cases"]
    case_def = rb.QUICK_CASES[0]
    assert case["peak_px"] == pytest.approx(case_def.peak_px, rel=0.1)
    of = case["rows"]["optical_flow"]
    ap = case["rows"]["approximate"]
    # 4 cameras at 160x120: far from the targets, but a real reconstruction, and the in-plume
    # figure is the harder one
    assert 15.0 < of["psnr"] < 60.0 and of["psnr_plume"] < of["psnr"]
    assert 0.2 < of["peak_ratio"] < 1.5
    assert ap["psnr"] >= of["psnr"] - 1.0
    assert "| quick-4cam-160 |" in (results / "realistic.md").read_text()
