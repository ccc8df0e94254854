"""Hot, dead and stuck pixels found from a camera's frames, and nothing on clean noise (issue 33)."""

from __future__ import annotations

import numpy as np
import pytest
from flow_helpers import NoiseBackground, render

from schlieren.pipeline.capture import DEAD, HOT, STUCK, defect_counts, find_defective_pixels

SHAPE = (144, 192)


@pytest.fixture(scope="module")
def scene():
    bg = NoiseBackground(SHAPE, rng=np.random.default_rng(21), feature_px=0.9)
    clean = render(bg, SHAPE)
    return clean


def _frames(clean, n, rng, *, noise=1.5):
    return [np.clip(np.round(clean + rng.normal(0, noise, SHAPE)), 0, 255).astype(np.float32) for _ in range(n)]


def test_no_false_positives_on_clean_noise(scene):
    rng = np.random.default_rng(0)
    for n in (1, 4, 16):
        assert not find_defective_pixels(_frames(scene, n, rng)).any()
    # pure sensor noise on a flat grey (no texture at all)
    flat = np.full(SHAPE, 100.0, np.float32)
    assert not find_defective_pixels(_frames(flat, 12, rng, noise=2.0)).any()


def test_hot_dead_and_stuck_pixels_found(scene):
    rng = np.random.default_rng(1)
    frames = _frames(scene, 16, rng)
    rows = np.array([10, 40, 70, 100, 130, 20, 50, 80, 110, 25])
    cols = np.array([15, 45, 75, 105, 135, 165, 20, 60, 100, 140])
    kinds = np.array([HOT, HOT, HOT, HOT, DEAD, DEAD, DEAD, STUCK, STUCK, STUCK])
    for img in frames:
        img[rows[kinds == HOT], cols[kinds == HOT]] = 255.0
        img[rows[kinds == DEAD], cols[kinds == DEAD]] = 0.0
        img[rows[kinds == STUCK], cols[kinds == STUCK]] = scene[rows[kinds == STUCK], cols[kinds == STUCK]].round()
    d = find_defective_pixels(frames)
    found = d[rows, cols]
    assert np.all(found != 0)
    assert np.all(found[kinds == STUCK] & STUCK)
    flagged = np.argwhere(d != 0)
    assert len(flagged) == len(rows)  # the neighbours of hot pixels are not flagged
    c = defect_counts(d)
    assert c["stuck"] == 3 and c["hot"] + c["dead"] >= 7


def test_stuck_needs_enough_frames(scene):
    rng = np.random.default_rng(2)
    frames = _frames(scene, 4, rng)
    for img in frames:
        img[60, 60] = 123.0
    assert not find_defective_pixels(frames)[60, 60] & STUCK
    with pytest.raises(ValueError):
        find_defective_pixels([])
