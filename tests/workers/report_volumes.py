"""The small volume the report's figure and renderer tests draw: a 16 x 24 x 20 voxel box
and a refractivity dip (hot Gaussian blob) in ambient air."""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.geometry import Grid

GRID = Grid((-0.02, -0.03, 0.0), (0.02, 0.03, 0.05), 0.0025)  # nx, ny, nz = 16, 24, 20
R_AMB = 2.9e-4


def blob(centre, amp=5e-5, sigma=0.004, grid=GRID):
    d = grid.centres() - np.asarray(centre)
    return R_AMB - amp * np.exp(-np.sum(d ** 2, axis=-1) / (2 * sigma ** 2))
