"""The realistic benchmark family (``schlieren bench realistic``): rig, scaling, scoring."""

from __future__ import annotations

import json

import numpy as np
import pytest

from schlieren.storage import synthetic_io as sio
from schlieren.workers import realistic as rb
from schlieren.workers.bench import realistic_render
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
    assert {c.bits_per_pixel for c in rb.select_cases("plume2-8cam-960-dist-h264-", variant="clean")} == {0.5, 1.0}
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


def test_a_probe_without_keep_store_deletes_what_it_scored(tmp_path, monkeypatch):
    """run_case(keep_store=False): the scored store, its cache folder and the truth rows'
    estimate are gone afterwards, the scores returned; kept by default; a failed run's store
    stays whatever was asked (the pipeline and scoring are stand-ins writing real folders)."""
    import types

    from schlieren.workers import evaluate as ev_mod
    from schlieren.workers import run as run_mod

    case = rb.CASES[0]
    ok = [True]

    def fake_run(session, store, **kw):
        for p in (store, type(store)(f"{store}.cache")):
            (p / "x").mkdir(parents=True)
            (p / "x" / "chunk").write_bytes(b"\0" * 64)
        return types.SimpleNamespace(ok=ok[0], root_failures=lambda: {"deflection": "boom"})

    ev = {"overall": {"psnr": 40.0, "rms": 0.01}, "plume": {"psnr": 30.0, "rms": 0.03},
          "frames": [{"frame": 0, "psnr": 40.0, "psnr_plume": 30.0, "peak_ratio": 1.0}]}
    monkeypatch.setattr(rb, "ensure_session", lambda c, w, progress=None: {"session": "s", "truth": "t", "peak_px": 0.25})
    monkeypatch.setattr(run_mod, "run_session", fake_run)
    monkeypatch.setattr(ev_mod, "evaluate", lambda store, truth: ev)
    monkeypatch.setattr(rb, "_chosen", lambda store: {})
    monkeypatch.setattr(rb, "capture_diagnostics", lambda store, truth: {"mask_fill": 0.1})
    d = tmp_path / case.name
    kept = rb.run_case(case, tmp_path, label="a", truth_rows=False)
    assert (d / "store-a.zarr").is_dir() and (d / "store-a.zarr.cache").is_dir() and kept["store"]
    gone = rb.run_case(case, tmp_path, label="b", truth_rows=False, keep_store=False)
    assert gone["rows"]["optical_flow"]["psnr"] == 40.0 and gone["store"] is None
    assert not (d / "store-b.zarr").exists() and not (d / "store-b.zarr.cache").exists()
    ok[0] = False
    failed = rb.run_case(case, tmp_path, label="c", truth_rows=False, keep_store=False)
    assert failed["failures"] and (d / "store-c.zarr").is_dir()


def test_scale_solve_follows_a_saturating_response():
    """The excess-temperature scale converges where the deflection saturates (r ~ 1/T), and
    a linear response takes the proportional steps (as the CFD flows' scales did)."""
    def saturating(s):  # like the quick flow: 0.023 px at scale 1, 0.25 px needs a scale near 70
        return 0.0767 * np.log1p(0.35 * s)

    probes = []
    scale, peak, ok = realistic_render._solve_scale(saturating, 0.25, probes)
    assert ok and abs(peak / 0.25 - 1.0) < rb.PEAK_TOL and saturating(scale) == peak
    assert scale > 50 and len(probes) <= rb.MAX_PROBES
    # proportional steps alone are still 20 % short after the old budget of three probes
    s = 1.0
    for _ in range(3):
        s *= 0.25 / saturating(s)
    assert saturating(s) < 0.8 * 0.25

    probes = []
    scale, peak, ok = realistic_render._solve_scale(lambda s: 0.2 * s, 0.25, probes)
    assert ok and scale == 0.25 / 0.2 and len(probes) == 2
    # an unreachable request: the closest probe, flagged
    scale, peak, ok = realistic_render._solve_scale(lambda s: 0.1 * s / (1.0 + s), 0.25, [])
    assert not ok and peak <= 0.1


def test_cfd_cases_trace_and_score_the_upsampled_spline(tmp_path, monkeypatch):
    """A CFD case renders the knots' spline upsampled ``upsample`` times: the truth the
    family scores is that field on the finer grid (the tracer differentiates the same one)."""
    import dataclasses

    from schlieren.pipeline.geometry import Medium
    from schlieren.pipeline.synthetic.cfd import upsample_cfd
    from schlieren.pipeline.synthetic.phantoms import refractivity_from_temperature

    coarse = realistic_render._quick_flow(realistic_render._grid(0.005))   # stands in for the PhiFlow knots
    monkeypatch.setattr(realistic_render, "cfd_flow", lambda flow, cache_dir, *, voxel, progress=None: coarse)
    case = dataclasses.replace(rb.QUICK_CASES[0], name="cfd-4cam-160", upsample=2)
    info = rb.ensure_session(case, tmp_path)
    t = sio.read_truth(info["truth"])
    np.testing.assert_allclose(t.voxel_size, 0.0025)
    fine = upsample_cfd(coarse, 2)
    assert t.refractivity.shape[1:] == fine.grid.shape == tuple(2 * n for n in coarse.grid.shape)
    # every stored knot is the spline's refractivity at that knot time (the excess as scaled to the peak)
    scale = info["scale"]
    for j, kt in enumerate(t.knot_time):
        k = int(np.argmin(np.abs(coarse.knot_times - kt)))
        assert abs(coarse.knot_times[k] - kt) < 1e-9
        excess = (fine.excess[k] * np.float32(scale)).astype(np.float64)   # as _scaled, then the phantom
        want = refractivity_from_temperature(Medium().T_ambient + excess, Medium())
        np.testing.assert_allclose(np.asarray(t.knot_refractivity[j]), want, rtol=0, atol=1e-9)
    # and the case key tells the two renders apart
    assert case.key() != dataclasses.replace(case, upsample=1).key()


def test_every_case_has_a_lab_twin_and_the_first_renders_stay_valid():
    """Each clean case has a `-lab` variant (issue 33's lab preset) of the same capture; the
    new variety cases report only; the keys of the cases rendered before the lab variants
    existed are unchanged (their cached sessions stay valid)."""
    import dataclasses

    from schlieren.pipeline.synthetic.lab import LAB_PRESETS

    clean = [c for c in rb.CASES if c.lab is None]
    labs = [c for c in rb.CASES if c.lab is not None]
    assert {c.name + "-lab" for c in clean} <= {c.name for c in labs}
    for c in labs:
        twin = rb.clean_twin(c)
        assert twin is not None and twin.lab is None and c.role == twin.role
        assert c.name.startswith(twin.name + "-lab") and c.key() != twin.key()
        assert dataclasses.replace(c, name=twin.name, lab=None, reference_frames=twin.reference_frames) == twin
        assert c.lab in LAB_PRESETS
    assert rb.select_cases(None, variant="clean") == tuple(clean)
    assert rb.select_cases(None, variant="lab") == tuple(labs)
    assert [c.name for c in rb.select_cases("plume1-16cam-640-lab")] == ["plume1-16cam-640-lab"]
    # the variety (new flows, textures, a long readout) is reported on, never tuned on
    new = [c for c in clean if c.flow in ("candle-s4", "turb-s5") or c.texture or c.line_time]
    assert len(new) == 6 and {c.role for c in new} == {"report"}
    assert {c.texture for c in new} == {None, "fine", "coarse", "dots"}
    # renders made before these fields existed (docs/realistic.md's family) keep their keys
    keys = {c.name: c.key() for c in rb.CASES}
    assert keys["plume1-16cam-640"] == "986efe1d9bac" and keys["plume1-8cam-960-dist"] == "0c1a57a0fae6"
    assert keys["plume1-8cam-960-dist-h264"] == "60c2ffcf4a4c" and keys["plume1-16cam-640-h264"] == "379bfc828fe2"
    # anything that changes the lab capture changes its key
    lab = next(c for c in labs if c.name == "plume1-16cam-640-lab")
    assert dataclasses.replace(lab, lab="lab-all").key() != lab.key()
    assert dataclasses.replace(lab, texture="dots").key() != lab.key()


def test_lab_table_pairs_each_lab_case_with_its_clean_twin():
    from schlieren.workers.bench.realistic_report import family_markdown, lab_pairs

    def row(name, lab, twin, psnr, plume, fill):
        return {"case": name, "role": "report", "cameras": 16, "size": [640, 480], "video": None,
                "distortion": False, "peak_px": 0.25, "lab": lab, "twin": twin, "pipeline_seconds": 10.0,
                "rows": {"optical_flow": {"psnr": psnr, "psnr_plume": plume, "peak_ratio": 1.0}},
                "diagnostics": {"mask_fill": fill, "hull_fill": fill, "quiet_flow_median": 0.01}}

    result = {"label": "t", "seconds": 1.0, "cases": [
        row("a", None, None, 45.0, 30.0, 0.08), row("a-lab", "lab", "a", 25.0, 19.0, 1.0),
        row("b", None, None, 40.0, 28.0, 0.1), row("b-lab", "lab", "b", 39.5, 27.5, 0.1),
        row("c-lab", "lab", "c", 30.0, 20.0, 0.5)]}  # no twin in this run: not paired
    assert [(c["case"], l["case"]) for c, l in lab_pairs(result)] == [("a", "a-lab"), ("b", "b-lab")]
    md = family_markdown(result)
    assert "## Clean against lab captures" in md
    assert "| a-lab | report | 45.00 / 25.00 (-20.00) | 30.00 / 19.00 (-11.00) |" in md
    assert "8.0 / 100.0" in md
    assert "-10.25 dB whole box" in md and "within 1 dB of clean on both: 1 of 2" in md
    assert "lab" in md.split("## Clean")[0]   # the lab captures are named in the main table


@pytest.mark.slow
def test_quick_lab_case_end_to_end(tmp_path):
    """The quick case clean and as a lab records it: both score, the lab capture's masks and
    hull cover more and its flow moves where nothing flows (the camera's motion), and the
    results carry the clean-against-lab table."""
    results = tmp_path / "results"
    assert main(["bench", "realistic", "--cases", "quick-4cam-160,quick-4cam-160-lab", "--out",
                 str(tmp_path / "work"), "--results", str(results), "--workers", "0", "--no-truth-rows"]) == 0
    res = {c["case"]: c for c in json.loads((results / "realistic.json").read_text())["cases"]}
    clean, lab = res["quick-4cam-160"], res["quick-4cam-160-lab"]
    assert lab["twin"] == "quick-4cam-160" and lab["lab"] == "lab" and clean["lab"] is None
    assert lab["peak_px"] == pytest.approx(clean["peak_px"], rel=1e-6)    # the same flow at the same scale
    for r in (clean, lab):
        g = r["diagnostics"]
        assert 0.0 <= g["mask_fill"] <= g["mask_fill_max"] <= 1.0 and 0.0 <= g["hull_fill"] <= 1.0
        assert g["quiet_fraction"] > 0.2
    assert clean["diagnostics"]["hull_fill"] > 0.0
    # today's pipeline takes the camera's motion for flow: the masks cover most of the lab images
    assert lab["diagnostics"]["mask_fill"] > 2 * clean["diagnostics"]["mask_fill"]
    # the camera moved by 0.1 px and more: the flow where nothing flows shows it
    assert lab["diagnostics"]["quiet_flow_median"] > 2 * clean["diagnostics"]["quiet_flow_median"]
    assert lab["diagnostics"]["quiet_flow_median"] > 0.05
    sess = tmp_path / "work" / "quick-4cam-160-lab"
    assert sio.read_lab_truth(sess / "truth.zarr")["params"]["hot_pixels"] == 25
    assert "## Clean against lab captures" in (results / "realistic.md").read_text()
