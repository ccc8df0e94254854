"""The capture corrections in a run (issue 33): the ``capture`` stage's defective pixels, the
deflection tasks' motion, gain and offset, and a camera moved against its reference."""

from __future__ import annotations

import shutil

import cv2
import numpy as np

from schlieren.pipeline.capture import CAPTURE_STATS, MOTION_APPLIED, MOTION_PARAMS, SCREENED
from schlieren.storage.store import ResultStore


def test_a_clean_run_stores_its_measurements_and_corrects_nothing(serial_store):
    st = ResultStore.open(serial_store, mode="r")
    C = st.array("camera").shape[0]
    d = np.asarray(st.array("defective_pixels")[:])
    assert d.shape[0] == C and not d.any()
    assert np.asarray(st.array("status/capture")[:]).all()
    motion = np.asarray(st.array("background_motion")[:])
    fit = np.asarray(st.array("capture_fit")[:])
    ph = np.asarray(st.array("photometric")[:])
    assert motion.shape[1:] == (st.array("raw_frame").shape[0], len(MOTION_PARAMS))
    done = np.isfinite(fit[..., 0])
    assert done.any()
    assert np.nanmax(np.abs(motion[..., :2])) < 0.01  # pixels
    flags = fit[..., CAPTURE_STATS.index("flags")][done].astype(int)
    assert np.all(flags & ~SCREENED == 0)  # nothing applied (most registrations end on the coarse levels)
    assert np.nanmax(np.abs(ph[:, :, 0] - 1.0)) < 0.01  # gain
    assert ph.shape[-1] == st.array("row_knot").shape[0]


def test_a_camera_moved_against_its_reference_is_measured_and_corrected(tiny_session, serial_store, tmp_path):
    """cam01's reference recorded one pixel to the left of its frames: the run measures +1 px
    and its flows match those of the unmoved run."""
    from schlieren.workers.run import run_session

    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess, ignore=shutil.ignore_patterns("truth.zarr"))
    ref = sess / "cam01" / "reference.png"
    img = cv2.imread(str(ref), cv2.IMREAD_UNCHANGED)
    moved = np.concatenate([img[:, :1], img[:, :-1]], axis=1)  # ref'(q) = ref(q - 1): frame(p) = ref'(p + 1)
    cv2.imwrite(str(ref), moved)
    out = tmp_path / "out.zarr"
    summary = run_session(sess, out, serial=True)
    assert summary.ok
    st = ResultStore.open(out, mode="r")
    base = ResultStore.open(serial_store, mode="r")
    m = np.asarray(st.array("background_motion")[:])
    flags = np.asarray(st.array("capture_fit")[:])[..., CAPTURE_STATS.index("flags")]
    done = np.isfinite(flags[1])
    assert np.all(np.abs(m[1, done, 0] - 1.0) < 0.02) and np.all(np.abs(m[1, done, 1]) < 0.02)
    assert np.all(flags[1, done].astype(int) & MOTION_APPLIED)
    assert np.nanmax(np.abs(m[0, :, :2])) < 0.01  # the other cameras did not move
    f1, f0 = np.asarray(st.array("flow")[1]), np.asarray(base.array("flow")[1])
    inner = (slice(None), slice(3, -3), slice(3, -3))
    assert np.sqrt(np.nanmean((f1 - f0)[inner] ** 2)) < 0.05  # against 1 px uncorrected


def test_the_pre_smoothing_is_chosen_per_camera_stored_logged_and_reported(tiny_session, serial_store, tmp_path):
    """flow.presmooth: auto. The tiny session's backgrounds are in focus: every camera keeps
    the in-focus width (the run is the one with the fixed width). cam01's reference and frames
    blurred by a 1.5 px Gaussian (a background out of focus): cam01 alone gets less."""
    from scipy import ndimage

    from schlieren.pipeline.flow.focus import PRESMOOTH_IN_FOCUS
    from schlieren.storage.report import ReportReader
    from schlieren.workers.report.capture_section import _camera_table
    from schlieren.workers.run import run_session

    base = ResultStore.open(serial_store, mode="r")
    p = np.asarray(base.array("presmooth")[:])
    assert p.shape == (base.array("camera").shape[0],) and np.all(p == PRESMOOTH_IN_FOCUS)
    assert base.attrs["derived"]["flow.presmooth"]["requested"] == "auto"
    assert base.attrs["derived"]["flow.presmooth"]["effective"] == p.tolist()

    sess = tmp_path / "session"
    shutil.copytree(tiny_session.session.parent, sess, ignore=shutil.ignore_patterns("truth.zarr"))
    for f in [sess / "cam01" / "reference.png", *sorted((sess / "cam01" / "frames").glob("*.png"))]:
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        blurred = ndimage.gaussian_filter(img.astype(np.float64), 1.5, mode="nearest")
        cv2.imwrite(str(f), np.clip(np.round(blurred), 0, np.iinfo(img.dtype).max).astype(img.dtype))
    out = tmp_path / "out.zarr"
    assert run_session(sess, out, serial=True).ok
    st = ResultStore.open(out, mode="r")
    q = np.asarray(st.array("presmooth")[:])
    assert q[1] < 0.5 * PRESMOOTH_IN_FOCUS
    assert np.all(np.delete(q, 1) == PRESMOOTH_IN_FOCUS)
    assert st.attrs["derived"]["flow.presmooth"]["effective"] == q.tolist()
    rd = ReportReader(out)
    table = _camera_table(rd, rd.whole("background_motion"), rd.camera_names(len(q)), (192, 144))
    assert "flow pre-smoothing (px)" in table and "0.6" in table


def test_the_reference_is_averaged_from_the_frames_the_defect_test_reads(tmp_path, monkeypatch):
    """A reference of several frames: the capture task's reading of them leaves the
    process's reference (the mean ``read_reference`` makes, bit for bit) without a second read."""
    from types import SimpleNamespace

    from schlieren.storage.frames import read_reference
    from schlieren.storage.session import CameraSource
    from schlieren.workers.tasks import capture as capture_task
    from schlieren.workers.tasks.run_context import RunContext

    rng = np.random.default_rng(2)
    stack = rng.integers(0, 65536, size=(4, 24, 32)).astype(np.uint16)
    (tmp_path / "ref").mkdir()
    for i, img in enumerate(stack):
        cv2.imwrite(str(tmp_path / "ref" / f"{i:03d}.png"), img)
    src = CameraSource("cam00", str(tmp_path / "f" / "%03d.png"), str(tmp_path / "ref" / "%03d.png"), "sequence",
                       "sequence")
    small: dict = {}
    ctx = SimpleNamespace(session=SimpleNamespace(sources=[src]),
                          once=lambda key, make: small[key] if key in small else small.setdefault(key, make()))
    ctx.reference_averaged = lambda c, make: RunContext.reference_averaged(ctx, c, make)
    n: list = []
    frames = list(capture_task._reference_frames(ctx, 0, n))
    assert len(frames) == 4 and n == [4]
    np.testing.assert_array_equal(small[("reference", 0, None)], read_reference(src))
    np.testing.assert_array_equal(small[("reference", 0, None)],
                                  stack.astype(np.float64).mean(axis=0).astype(np.float32))
