"""Flows of a run on the truth's flow grid: a run's ``flow.auto_factor`` may choose a finer
grid than the one a synthetic session's deflections were rendered on."""

from __future__ import annotations

import cv2
import numpy as np


def on_grid(flow: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``flow`` (..., h, w, 2) area-averaged onto ``shape`` (rows, cols) (unchanged if equal).

    Both grids cover the same image (cell ``j`` of a grid of factor ``f`` averages pixels
    ``[f j, f j + f)``), so the area resampling averages each coarse cell's pixels up to
    the fine cells cut at its edges."""
    flow = np.asarray(flow, dtype=np.float64)
    h, w = flow.shape[-3:-1]
    if (h, w) == tuple(shape):
        return flow
    lead = flow.shape[:-3]
    flat = flow.reshape((-1, h, w, 2))
    out = np.stack([cv2.resize(f, (shape[1], shape[0]), interpolation=cv2.INTER_AREA) for f in flat])
    return out.reshape(lead + tuple(shape) + (2,))
