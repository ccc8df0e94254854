"""Random dot backgrounds, as many BOS labs print them (Raffel 2015, Exp. Fluids 56: 60).

One dot per cell of a square lattice of pitch ``p`` on the background plane, at a uniformly
random position inside its cell (a jittered grid: dots may touch or overlap, never
cluster), all of one diameter. A printed dot's edge is not a step: ink spread and the
camera's optics soften it; the dot's coverage of a point at distance ``d`` from its
centre is ``erfc((d - radius) / (sqrt(2) edge)) / 2`` (a disk blurred by a Gaussian of
sigma ``edge`` across its rim), which the renderer's pixel-area sampling resolves, so the
pattern stays cleaner than the flow that is judged on it. Overlapping dots take the
larger coverage (ink on ink stays black).

Evaluated procedurally at any point, like the Wavelet Noise (:mod:`.background`): the
renderer never resamples an image. The pattern is returned with zero mean and unit
standard deviation, dark dots on white paper (negative values on the dots).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["dot_table", "dot_params", "dots_values"]

#: Cells of the periodic jitter table (a power of two: the wrap-around is a bit mask).
TABLE = 256


def dot_table(n: int = TABLE, *, seed: int = 0) -> np.ndarray:
    """Dot positions inside their cells, shape (n, n, 2), uniform in [0, 1) (x, y in cell units).

    The table is periodic: cell ``(i, j)`` uses entry ``(i mod n, j mod n)``.
    """
    if n < 2 or n & (n - 1):
        raise ValueError("the dot table's size must be a power of two")
    return np.random.default_rng(seed).uniform(0.0, 1.0, (n, n, 2))


@njit(cache=True)
def _coverage(table, x, y, radius, edge):
    """Ink coverage in [0, 1] at lattice coordinates (x, y) (cell units)."""
    mask = table.shape[0] - 1
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    cov = 0.0
    for dj in range(-1, 2):
        cy = iy + dj
        for di in range(-1, 2):
            cx = ix + di
            px = cx + table[cy & mask, cx & mask, 0]
            py = cy + table[cy & mask, cx & mask, 1]
            d = math.sqrt((x - px) ** 2 + (y - py) ** 2)
            c = 0.5 * math.erfc((d - radius) / (1.4142135623730951 * edge))
            if c > cov:
                cov = c
    return cov


@njit(cache=True)
def _dots_at(table, x, y, par):
    """Unit-variance dot pattern at lattice coordinates (x, y); ``par`` from :func:`dot_params`."""
    return (par[2] - _coverage(table, x, y, par[0], par[1])) / par[3]


@njit(cache=True)
def _dots_many(table, x, y, par, out):
    for i in range(x.shape[0]):
        out[i] = _dots_at(table, x[i], y[i], par)


def dot_params(table: np.ndarray, *, diameter: float, edge: float) -> np.ndarray:
    """Kernel parameters ``(radius, edge, mean coverage, coverage std)`` (cell units).

    Parameters
    ----------
    table : ndarray
        :func:`dot_table`.
    diameter : float
        Dot diameter in units of the pitch (below 1; 0.5-0.7 gives 20-40 % ink).
    edge : float
        Sigma of the dot's soft rim in units of the pitch (> 0).
    """
    if not 0.0 < diameter < 1.0:
        raise ValueError("the dot diameter must be between 0 and 1 pitch")
    if not 0.0 < edge < 0.25:
        raise ValueError("the dot edge must be between 0 and 0.25 pitch")
    radius = 0.5 * float(diameter)
    # coverage statistics over a large sample of the periodic pattern (exact up to sampling)
    pts = np.random.default_rng(12345).uniform(0.0, table.shape[0], (2, 200000))
    raw = np.empty(pts.shape[1])
    _dots_many(table, pts[0], pts[1], np.array([radius, float(edge), 0.0, -1.0]), raw)  # raw = coverage
    return np.array([radius, float(edge), float(raw.mean()), float(raw.std())])


def dots_values(table: np.ndarray, par: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The unit-variance pattern at lattice coordinates ``x, y`` (any equal shapes)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty(x.size)
    _dots_many(table, np.ascontiguousarray(x.ravel()), np.ascontiguousarray(np.asarray(y, dtype=np.float64).ravel()),
               par, out)
    return out.reshape(x.shape)
