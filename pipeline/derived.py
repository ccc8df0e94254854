"""Derived quantities from refractivity (paper sec. 3: "refractive indices directly correspond
to volume densities"; docs/design.md physics conventions).

* Density by Gladstone-Dale: ``n - 1 = G rho``, so ``rho = r / G`` (kg/m^3).
* Temperature by the ideal gas law at the ambient pressure ``p_ambient``:
  ``rho = p M / (R T)`` with the Gladstone-Dale density gives ``r = r_amb T_amb / T``, so
  ``T = T_amb r_amb / r`` (K), where ``r_amb = n_ambient - 1``.

Non-positive refractivity is unphysical (noise far below ambient density); both
functions return NaN there.
"""

from __future__ import annotations

import logging

import numpy as np

from schlieren.pipeline.geometry import Medium

__all__ = ["density", "temperature"]

log = logging.getLogger(__name__)


def _positive(r: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    r = np.asarray(r, dtype=np.float64)
    bad = ~(r > 0)
    if bad.any():
        log.warning("%s: %d voxel(s) with refractivity <= 0 set to NaN", what, int(bad.sum()))
    return r, bad


def density(r: np.ndarray, medium: Medium = Medium()) -> np.ndarray:
    """Gas density from refractivity by Gladstone-Dale.

    Parameters
    ----------
    r : ndarray
        Refractivity ``n - 1`` (any shape).
    medium : Medium
        Uses ``gladstone_dale`` (m^3/kg).

    Returns
    -------
    rho : ndarray, same shape, float64
        kg/m^3; NaN where ``r <= 0``.
    """
    r, bad = _positive(r, "density")
    rho = r / medium.gladstone_dale
    rho[bad] = np.nan
    return rho


def temperature(r: np.ndarray, medium: Medium = Medium()) -> np.ndarray:
    """Gas temperature from refractivity, ideal gas at ``medium.p_ambient``.

    Parameters
    ----------
    r : ndarray
        Refractivity ``n - 1``.
    medium : Medium
        Uses ``n_ambient`` and ``T_ambient`` (K); the pressure is the ambient one, so it
        cancels: ``T = T_amb (n_amb - 1) / r``.

    Returns
    -------
    T : ndarray, same shape, float64
        Kelvin; NaN where ``r <= 0``.
    """
    r, bad = _positive(r, "temperature")
    with np.errstate(divide="ignore", invalid="ignore"):
        T = medium.T_ambient * medium.refractivity_ambient / r
    T[bad] = np.nan
    return T
