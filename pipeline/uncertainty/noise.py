"""The measured noise of the flows, and samples of it (the uncertainty's input).

Where no camera sees flow (outside every mask) a measured deflection is pure noise:
sensor noise, compression and the optical flow's own error. :func:`flow_noise_level`
measures its RMS per camera and flow component there (robustly, 1.4826 x MAD, as
:func:`~schlieren.pipeline.tomography.rhs_noise` does for the right-hand side).

Neighbouring flow cells share most of their pixels (the LK window, the smoothing and the
block mean: :func:`~schlieren.pipeline.flow.measurement_sigma`), so their noise is
correlated. :func:`correlated_flow_noise` draws fields with that correlation: white noise
filtered by a Gaussian of the window's width ``s`` (flow cells), whose correlation at a
lag of ``d`` cells is ``exp(-d^2 / (4 s^2))``, scaled to the measured RMS. On the realistic
family the flows outside the masks correlate at 0.80 / 0.40 / 0.09 at lags of 1 / 2 / 3
cells (16 cameras; the window's ``s`` = 1.05 cells predicts 0.80 / 0.40 / 0.13) and
0.83 / 0.49 / 0.17 (8 cameras at 960x720; ``s`` = 1.18: 0.84 / 0.49 / 0.20).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["flow_noise_level", "correlated_flow_noise", "noise_correlation"]

#: Fewest finite cells outside the masks a camera needs for its own noise level (else
#: the median of the other cameras' is used).
MIN_QUIET_CELLS = 50


def flow_noise_level(flows: np.ndarray, quiet: np.ndarray) -> np.ndarray:
    """Robust RMS noise of each camera's flow components over the cells that see no flow.

    Parameters
    ----------
    flows : ndarray, shape (C, h, w, 2)
        Deflections (pixels).
    quiet : ndarray, shape (C, h, w) bool
        Cells outside every flow mask (their deflection is noise).

    Returns
    -------
    sigma : ndarray, shape (C, 2)
        ``1.4826 * MAD`` per camera and component (pixels). A camera with fewer than
        :data:`MIN_QUIET_CELLS` finite quiet cells takes the median of the others'; NaN
        if no camera has enough.
    """
    flows = np.asarray(flows)
    quiet = np.asarray(quiet, dtype=bool)
    if flows.shape[:-1] != quiet.shape or flows.shape[-1] != 2:
        raise ValueError(f"flows {flows.shape} and quiet {quiet.shape} do not match")
    out = np.full((flows.shape[0], 2), np.nan)
    for c in range(flows.shape[0]):
        f = np.asarray(flows[c][quiet[c]], dtype=np.float64)
        f = f[np.isfinite(f).all(axis=1)]
        if len(f) >= MIN_QUIET_CELLS:
            out[c] = 1.4826 * np.median(np.abs(f - np.median(f, axis=0)), axis=0)
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any() and not bad.all():
        out[bad] = np.median(out[~bad], axis=0)
    return out


def _taps(sigma: float) -> np.ndarray:
    """1-D Gaussian taps of ``sigma`` cells out to ``4 sigma`` (normalised to sum 1)."""
    K = max(1, int(np.ceil(4.0 * sigma)))
    k = np.exp(-0.5 * (np.arange(-K, K + 1) / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def correlated_flow_noise(rng: np.random.Generator, shape, sigma_cells, level: np.ndarray) -> np.ndarray:
    """Noise fields like the flows' own: per camera, white noise filtered by a Gaussian of
    ``sigma_cells`` (reflected at the image border) and scaled to unit variance, times
    ``level``.

    Parameters
    ----------
    rng : numpy.random.Generator
    shape : (C, h, w)
        The flow grid of every camera.
    sigma_cells : sequence of float, length C
        Width of the flow's averaging per camera (flow cells; 0: white noise).
    level : ndarray, shape (C, 2)
        RMS of each camera's components (pixels, :func:`flow_noise_level`).

    Returns
    -------
    noise : ndarray, shape (C, h, w, 2) float32
    """
    C, h, w = (int(v) for v in shape)
    sig = np.asarray(sigma_cells, dtype=np.float64).reshape(-1)
    level = np.asarray(level, dtype=np.float64).reshape(C, 2)
    if len(sig) != C:
        raise ValueError(f"one width per camera expected ({C}), got {len(sig)}")
    out = np.empty((C, h, w, 2), np.float32)
    for c in range(C):
        for j in range(2):
            n = rng.standard_normal((h, w), dtype=np.float32)
            if sig[c] > 0:
                k = _taps(sig[c])
                n = cv2.sepFilter2D(n, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT)
                n /= np.float32(np.sum(k.astype(np.float64) ** 2))  # unit variance: (sum k^2)^2 per 2-D tap set
            out[c, ..., j] = n * np.float32(level[c, j])
    return out


def noise_correlation(flows: np.ndarray, quiet: np.ndarray, lags=(1, 2, 3)) -> np.ndarray:
    """Correlation of the flow's noise between cells ``lag`` apart (mean over cameras, both
    components and both image axes), over pairs of finite quiet cells: the check of the
    window model's correlation (:func:`correlated_flow_noise`).

    Returns
    -------
    corr : ndarray, shape (len(lags),)
    """
    flows = np.asarray(flows, dtype=np.float64)
    quiet = np.asarray(quiet, dtype=bool) & np.isfinite(flows).all(axis=-1)
    out = []
    for lag in lags:
        vals = []
        for c in range(flows.shape[0]):
            for j in range(2):
                f = flows[c, ..., j]
                q = quiet[c]
                if q.sum() < MIN_QUIET_CELLS:
                    continue
                z = np.where(q, f - np.median(f[q]), 0.0)
                for ax in (0, 1):
                    a = [slice(None)] * 2
                    b = [slice(None)] * 2
                    a[ax] = slice(lag, None)
                    b[ax] = slice(None, -lag)
                    both = q[tuple(a)] & q[tuple(b)]
                    x, y = z[tuple(a)][both], z[tuple(b)][both]
                    den = np.sqrt(np.sum(x * x) * np.sum(y * y))
                    if den > 0:
                        vals.append(float(np.sum(x * y) / den))
        out.append(float(np.mean(vals)) if vals else np.nan)
    return np.asarray(out)
