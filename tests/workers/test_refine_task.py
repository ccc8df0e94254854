"""The tomography task's re-projection refinement (``refine.passes``) on the tiny session."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from store_compare import copy_store

from schlieren.pipeline.flow import RefineParams
from schlieren.pipeline.params import ParamsError
from schlieren.pipeline.stages import RunConfig, check_config


@pytest.fixture
def store_copy(serial_store, tmp_path):
    return copy_store(serial_store, tmp_path)


def _context(store, passes: int):
    from schlieren.workers.tasks import context

    ctx = context(str(store), f"refine-{passes}")
    return dataclasses.replace(ctx, config=dataclasses.replace(ctx.config, refine=RefineParams(passes=passes)))


def test_a_zero_prediction_gives_the_runs_own_flows(store_copy):
    """Around a zero gradient the refined flows are the stored ones (within 1e-3 px: the
    reference resampled at zero displacement differs only by the spline prefilter's truncation)."""
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key
    from schlieren.workers.tasks.refine import refined_flows

    ctx = _context(store_copy, 1)
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    k = 1
    grad = np.zeros(tuple(ctx.session.grid.shape) + (3,))
    got = refined_flows(ctx, k, geom, grad)
    stored = np.stack([np.asarray(ctx.store.read("flow", (c, k))) for c in range(len(ctx.cameras))])
    ok = np.isfinite(stored) & np.isfinite(got)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(got[ok], stored[ok], atol=1e-3)


def test_the_task_solves_again_from_the_refined_flows(store_copy):
    """With ``refine.passes`` 1 the task writes a finite gradient other than the plain solve's,
    of the same size (the refined flows carry the same deflections)."""
    from schlieren.workers.tasks.tomography import tomography_task

    plain = np.asarray(_context(store_copy, 0).store.read("gradient", (0,)), np.float64)
    ctx = _context(store_copy, 1)
    tomography_task(ctx, 0)
    refined = np.asarray(ctx.store.read("gradient", (0,)), np.float64)
    assert np.isfinite(refined).all()
    assert not np.array_equal(refined, plain)
    assert 0.7 < np.linalg.norm(refined) / np.linalg.norm(plain) < 1.3


def test_direct_reconstruction_refuses_refinement():
    with pytest.raises(ParamsError, match="refine.passes"):
        check_config(RunConfig(reconstruction="direct", refine=RefineParams(passes=1)))


def test_refined_solves_model_the_given_share_of_the_flow_window(store_copy):
    """``refine.window_scale`` scales the stored flow averaging the refined solves model: 0 none,
    ``s`` the plain solve's width times ``s``; the task runs with it."""
    from schlieren.workers.tasks.tomography import flow_blur, tomography_task

    ctx = _context(store_copy, 1)
    plain = flow_blur(ctx)
    assert flow_blur(ctx, 0.0) == {}
    got = flow_blur(ctx, 0.5)
    assert set(got) == set(plain)
    for key, v in plain.items():
        if key == "volume_blur":
            assert got[key] == pytest.approx(0.5 * v)
    ctx = dataclasses.replace(ctx, config=dataclasses.replace(
        ctx.config, refine=RefineParams(passes=1, window_scale=0.5)))
    tomography_task(ctx, 0)
    assert np.isfinite(np.asarray(ctx.store.read("gradient", (0,)), np.float64)).all()


def test_the_stored_registration_gives_the_flows_of_registering_again(store_copy, monkeypatch):
    """The refinement reuses each raw frame's stored registration (nothing measured again);
    on the tiny session, whose frames need no correction, registering each frame again
    against the warped reference gives the same refined flows bit for bit."""
    from schlieren.pipeline import capture
    from schlieren.workers.tasks import refine
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key

    ctx = _context(store_copy, 1)
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    grad = np.asarray(ctx.store.read("gradient", (1,)), np.float64)
    calls = []
    register = capture.correction.register_background
    monkeypatch.setattr(capture.correction, "register_background", lambda *a, **k: calls.append(1) or register(*a, **k))
    reused = refine.refined_flows(ctx, 1, geom, grad, crop=False)
    assert not calls
    monkeypatch.setattr(refine, "_stored_fit", lambda *a: None)
    again = refine.refined_flows(ctx, 1, geom, grad, crop=False)
    assert calls
    np.testing.assert_array_equal(reused, again)


def test_the_cropped_refinement_gives_the_full_images_flows(store_copy, monkeypatch):
    """``refine.crop`` (the refined flow measured only where the prediction reaches, the stored
    flow elsewhere) gives the whole image's refined flows within 5e-4 px (the resampling's
    own floor at zero displacement, which the stored flow outside the crop does not have),
    and its crops are those :func:`~schlieren.pipeline.flow.refine_region` chose."""
    from schlieren.pipeline import flow as flowmod
    from schlieren.workers.tasks import refine
    from schlieren.workers.tasks.geometry import cached_geometry, geometry_key

    ctx = _context(store_copy, 1)
    geom = cached_geometry(ctx.store_path, geometry_key(ctx))
    grad = np.asarray(ctx.store.read("gradient", (1,)), np.float64)
    full = refine.refined_flows(ctx, 1, geom, grad, crop=False)
    regions = []
    make = flowmod.refine_region
    monkeypatch.setattr(flowmod, "refine_region", lambda *a, **k: regions.append(make(*a, **k)) or regions[-1])
    cropped = refine.refined_flows(ctx, 1, geom, grad, crop=True)
    assert len(regions) == len(ctx.cameras) and not any(r.empty for r in regions)
    ok = np.isfinite(full)
    np.testing.assert_array_equal(ok, np.isfinite(cropped))
    np.testing.assert_allclose(cropped[ok], full[ok], atol=5e-4)
