"""Local averages inside the hull: the smoothing of the uncertainty's variance fields."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

__all__ = ["masked_mean"]


def masked_mean(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-weighted mean of ``values`` over the voxels of ``mask`` (normalised
    convolution: voxels outside the mask neither contribute nor dilute), zero outside it.

    Parameters
    ----------
    values : ndarray, shape (nz, ny, nx)
    mask : ndarray, shape (nz, ny, nx) bool
    sigma : float
        Gaussian width, voxels; 0 returns ``values`` inside the mask.
    """
    mask = np.asarray(mask, dtype=bool)
    v = np.where(mask, np.asarray(values, dtype=np.float64), 0.0)
    if sigma <= 0 or not mask.any():
        return v
    num = ndi.gaussian_filter(v, sigma, mode="constant")
    den = ndi.gaussian_filter(mask.astype(np.float64), sigma, mode="constant")
    return np.where(mask, num / np.where(den > 0, den, 1.0), 0.0)
