"""A reference of few noisy frames topped up in a run (issue 33, ``capture.reference_topup``):
stored for every camera, read back by a process that did not top it up (as a Dask worker's
deflection task does) bit for bit, and the result against the truth not lower than without."""

from __future__ import annotations

import numpy as np
import pytest

from schlieren.storage.store import ResultStore


@pytest.fixture(scope="module")
def noisy_reference_runs(tiny_spec, tmp_path_factory):
    """The tiny session with 3 noisy reference frames per camera, run with the top-up (default)
    and without it."""
    from schlieren.pipeline.stages import config_from_dict
    from schlieren.workers.synth import synthesize
    from schlieren.workers.run import run_session

    root = tmp_path_factory.mktemp("topup")
    sess = synthesize(root / "session", **{**tiny_spec, "reference_frames": 3})
    stores = {}
    for name, cfg in (("on", None), ("off", {"capture": {"reference_topup": 0}})):
        stores[name] = root / f"{name}.zarr"
        assert run_session(sess.session, stores[name], serial=True, config=config_from_dict(cfg)).ok
    return sess, stores


def test_a_reference_of_few_frames_is_topped_up_and_stored(noisy_reference_runs):
    _, stores = noisy_reference_runs
    st = ResultStore.open(stores["on"], mode="r")
    topped = np.asarray(st.array("reference_topup")[:])
    count = np.asarray(st.array("reference_count")[:])
    assert np.all(topped > 0)
    for c in range(len(topped)):
        low = count[c].min()  # the reference's own frames, as many as its measured noise is worth
        assert 2.0 < low < 4.5
        assert np.isclose(count[c].max(), low + topped[c])  # the static pixels
    assert "reference" not in ResultStore.open(stores["off"], mode="r")


def test_another_process_measures_the_same_flow_from_the_stored_reference(noisy_reference_runs):
    """A deflection task in a process that did not run the camera's capture task (a Dask
    worker) reads the topped-up reference from the store: the same flow bit for bit."""
    from schlieren.workers.tasks.capture import camera_capture
    from schlieren.workers.tasks.deflection import flow_params
    from schlieren.workers.tasks.run_context import context
    from schlieren.pipeline import capture

    _, stores = noisy_reference_runs
    ctx = context(str(stores["on"]), "fresh-process")
    st = ResultStore.open(stores["on"], mode="r")
    c, j = 1, 1
    np.testing.assert_array_equal(ctx.reference(c), np.asarray(st.array("reference")[c]))
    f = ctx.raw_first + j
    params = flow_params(ctx, c)
    d, _ = capture.corrected_deflection(ctx.prepared_reference(c), ctx.frame(c, f), params, ctx.config.capture,
                                        camera=camera_capture(ctx, c, None, params))
    np.testing.assert_array_equal(d, np.asarray(st.array("flow_raw")[c, j]))


def test_the_stored_reference_is_closer_to_the_noise_free_background(noisy_reference_runs, tiny_session):
    """Against the same session's noise-free reference (8-bit, quantised by 0.29 grey levels):
    the static pixels' error drops as the frames averaged there say; the others keep the
    recorded reference bit for bit."""
    import cv2

    from schlieren.storage.frames import read_reference
    from schlieren.workers.tasks.capture import static_region
    from schlieren.workers.tasks.run_context import context

    sess, stores = noisy_reference_runs
    ctx = context(str(stores["on"]), "truth-check")
    st = ResultStore.open(stores["on"], mode="r")
    q = 1.0 / 12.0  # the clean PNG's quantisation variance
    for c, src in enumerate(ctx.session.sources):
        clean = cv2.imread(str(tiny_session.session.parent / src.name / "reference.png"), cv2.IMREAD_UNCHANGED)
        clean = clean.astype(np.float64)
        recorded = read_reference(src, camera_name=src.name)
        topped = np.asarray(st.array("reference")[c])
        count = np.asarray(st.array("reference_count")[c])
        m = static_region(ctx, c) & (count > count.min())
        before = np.mean((recorded - clean)[m] ** 2) - q
        after = np.mean((topped - clean)[m] ** 2) - q
        expected = count.min() / count.max()  # the variance of n_eff frames against n_eff + added
        assert 0.8 * expected < after / before < 1.25 * expected
        np.testing.assert_array_equal(topped[count == count.min()], recorded[count == count.min()])
