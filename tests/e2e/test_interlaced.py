"""Interlaced cameras end to end: the tiny progressive capture read as 1080i-style fields.

Each synthetic frame is split into its two fields (half the rows each, bobbed back to full
height) at twice the frame rate, and each field is compared with the reference
deinterlaced the same way. Against the ground truth this loses some accuracy (half the
vertical resolution per field, and the odd fields are stamped half a frame later than the
progressive frames they come from) but must stay close to the progressive run (within
3.5 dB on this capture).
"""

from __future__ import annotations

import shutil

import numpy as np
import yaml


def test_interlaced_session_reconstructs_close_to_the_progressive_one(tiny_session, serial_store, tmp_path):
    from schlieren.storage.frames import bob_field, read_reference
    from schlieren.storage.session import load_session
    from schlieren.workers.evaluate import evaluate
    from schlieren.workers.run import run_session

    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess, ignore=shutil.ignore_patterns("truth.zarr"))
    m = yaml.safe_load((sess / "session.yaml").read_text())
    a, b = m["frames"]
    s0, s1 = m["sync"]["strobe"]["search_frames"]
    for c in m["cameras"]:
        c["interlaced"] = "top_first"
        c["rolling_shutter"]["line_time"] *= 2  # the same row timing, counted in field rows
    m["frames"] = [2 * a, 2 * b]
    m["sync"]["strobe"]["search_frames"] = [2 * s0, 2 * s1]
    (sess / "session.yaml").write_text(yaml.safe_dump(m))

    s = load_session(sess)
    ref = read_reference(s.sources[0].reference)
    for parity in (0, 1):
        np.testing.assert_array_equal(read_reference(s.sources[0], parity=parity), bob_field(ref, parity))

    summary = run_session(sess, tmp_path / "run.zarr", serial=True)
    assert summary.ok and summary.warnings == []
    got = evaluate(tmp_path / "run.zarr", tiny_session.truth)
    base = evaluate(serial_store, tiny_session.truth)
    assert [r["frame"] for r in got["frames"]] == list(range(2 * a, 2 * b))
    # Measured (2026-11-24, default parameters): progressive 36.9 dB, fields 33.8 dB; with
    # the curl-coupled tomography (same day) progressive 38.0 dB, fields 34.2 dB. The
    # footprint-chosen LK window and the curl term gain the progressive run more than the
    # fields (which carry half the rows); on the fields the defaults still beat the old fixed
    # window (31.9 dB), a larger window (33.65 dB) and more smoothing (33.8 dB). Both bounds
    # can fail: a field-timing or parity mix-up costs far more than 4 dB.
    assert got["overall"]["psnr"] > base["overall"]["psnr"] - 4.0, (got["overall"], base["overall"])
    assert got["overall"]["psnr"] > 33.5, got["overall"]
