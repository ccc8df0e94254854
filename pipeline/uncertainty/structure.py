"""The structure term: the fine structure the estimate loses, from its own curvature.

The smoothness prior, the few views and the integration's discretisation (paper eq. 8)
all remove structure at the voxel scale, and a smoothing of width ``s`` voxels changes a
field by about ``(s^2 / 2) h^2 lap(r)``: the local RMS of the estimate's own ``h^2 lap(r)``
(refractivity units) marks where that loss is large. Its weight
(:attr:`~schlieren.pipeline.uncertainty.UncertaintyParams.structure_scale`) is 0 by default:
beside the bias term (:mod:`.bias`) it barely changes the fit on the realistic family's tune cases.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.uncertainty.local import masked_mean

__all__ = ["curvature_rms"]


def curvature_rms(refractivity: np.ndarray, hull: np.ndarray, *, smoothing: float) -> np.ndarray:
    """Local RMS of ``h^2 lap(r)`` (the 7-point Laplacian in grid units: refractivity units)
    over the hull (Gaussian of ``smoothing`` voxels), zero outside it.

    Parameters
    ----------
    refractivity : ndarray, shape (nz, ny, nx)
    hull : ndarray, shape (nz, ny, nx) bool

    Returns
    -------
    ndarray, shape (nz, ny, nx) float64
    """
    lap = ndi.laplace(np.asarray(refractivity, dtype=np.float64), mode="nearest")
    return np.sqrt(masked_mean(lap * lap, hull, smoothing))
