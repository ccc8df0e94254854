"""Re-projection residuals: push a reconstructed gradient back through the measurement model.

For each flow-grid pixel ``p`` of each camera (paper sec. 5, eq. 3, straight-ray
approximation), using the tomography's own per-session geometry
(:func:`schlieren.pipeline.tomography.build_geometry`: the same rays, ``X_c`` and projection
matrix ``S`` the solver inverts, so the residual measures how well the solved system
explains the data):

1. ``I = S g``: the line integral of ``grad n`` along the undeflected ray through ``p``
   (line integrals of the normalised radial basis whose coefficients are the voxel-centre
   values, eqs. 4-6);
2. the tomography's right-hand side is ``n_ambient * (d_out_hat - d_in)``, hence
   ``d_out_hat = unit(d_in + I / n_ambient)``;
3. ``d_out_hat`` leaves ``X_c``, the point of the undeflected ray closest to the volume
   centre, and meets the background plane at ``B'`` (the single-refraction approximation of
   sec. 5); the predicted deflection is ``project(B') - project(B)``, ``B`` being the
   undeflected background point (zero gradient gives exactly zero).

The residual of a camera frame is ``measured flow - predicted flow`` in image pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.geometry import Camera
from schlieren.pipeline.tomography.geometry import TomoGeometry

__all__ = ["line_integrals", "predict_flows", "ResidualStats", "residual_stats"]


def line_integrals(geom: TomoGeometry, gradient: np.ndarray) -> np.ndarray:
    """``S g``: the integral of ``grad n`` along every flow-grid ray (dimensionless).

    Parameters
    ----------
    geom : TomoGeometry
        From :func:`schlieren.pipeline.tomography.build_geometry`.
    gradient : ndarray, shape (nz, ny, nx, 3)
        Gradient of the refractive index (1/m), component 0 = x, on ``geom.grid``.

    Returns
    -------
    I : ndarray, shape (C, h, w, 3)
    """
    g = np.asarray(gradient, dtype=np.float64).reshape(-1, 3)
    if g.shape[0] != geom.S.shape[1]:
        raise ValueError(f"gradient has {g.shape[0]} voxels, the geometry expects {geom.S.shape[1]}")
    # one SpMV per component (scipy's 3-column product costs more than three single ones)
    I = np.stack([geom.S @ np.ascontiguousarray(g[:, k]) for k in range(3)], axis=-1)
    return I.reshape(*geom.flow_shape, 3)


def predict_flows(geom: TomoGeometry, cameras: list[Camera], gradient: np.ndarray, *,
                  n_ambient: float) -> np.ndarray:
    """Image-plane deflections that a reconstructed gradient field predicts (sec. 5).

    Parameters
    ----------
    geom : TomoGeometry
        Built from ``cameras`` (same order).
    cameras : list of Camera
        Used to intersect the background planes and to project (with distortion).
    gradient : ndarray, shape (nz, ny, nx, 3)
        grad n (1/m).
    n_ambient : float
        Refractive index of the surrounding air.

    Returns
    -------
    flows : ndarray, shape (C, h, w, 2), float64
        Predicted deflections in image pixels (component 0 = u), SPEC sign convention
        (``frame(p) ~= reference(p + delta)``). NaN where a ray misses the background.
    """
    C, h, w = geom.flow_shape
    if len(cameras) != C:
        raise ValueError(f"the geometry has {C} cameras, got {len(cameras)}")
    I = line_integrals(geom, gradient)
    out = np.empty((C, h, w, 2))
    for c, cam in enumerate(cameras):
        d_in = geom.d_in[c]
        d_out = d_in + I[c] / float(n_ambient)
        d_out /= np.linalg.norm(d_out, axis=-1, keepdims=True)
        uv0 = cam.project(cam.intersect_background(cam.center, d_in))
        uv1 = cam.project(cam.intersect_background(geom.x_c[c], d_out))
        delta = uv1 - uv0
        # rays that never meet the volume are not deflected (exactly, despite round-off)
        untouched = ~np.any(I[c] != 0.0, axis=-1) & np.all(np.isfinite(delta), axis=-1)
        delta[untouched] = 0.0
        out[c] = delta
    return out


@dataclass(frozen=True)
class ResidualStats:
    """Summary of ``measured - predicted`` for one camera frame (pixels).

    Attributes
    ----------
    rms : float
        RMS of the residual vector length over all finite pixels.
    rms_measured : float
        RMS of the measured deflection length over the same pixels (for scale).
    rms_in_mask : float
        RMS residual inside the mask (NaN without a mask or an empty one).
    count : int
        Number of pixels used.
    """

    rms: float
    rms_measured: float
    rms_in_mask: float
    count: int


def residual_stats(measured: np.ndarray, predicted: np.ndarray, mask: np.ndarray | None = None) -> ResidualStats:
    """RMS re-projection residual of one camera frame.

    Parameters
    ----------
    measured, predicted : ndarray, shape (rows, cols, 2)
        Deflections in pixels.
    mask : ndarray, shape (rows, cols), bool, optional

    Returns
    -------
    ResidualStats
    """
    measured = np.asarray(measured, dtype=np.float64)
    predicted = np.asarray(predicted, dtype=np.float64)
    if measured.shape != predicted.shape:
        raise ValueError(f"shapes differ: measured {measured.shape}, predicted {predicted.shape}")
    r2 = np.sum((measured - predicted) ** 2, axis=-1)
    m2 = np.sum(measured ** 2, axis=-1)
    ok = np.isfinite(r2) & np.isfinite(m2)
    n = int(ok.sum())
    if n == 0:
        return ResidualStats(float("nan"), float("nan"), float("nan"), 0)
    rms = float(np.sqrt(r2[ok].mean()))
    rms_m = float(np.sqrt(m2[ok].mean()))
    rms_in = float("nan")
    if mask is not None:
        sel = ok & np.asarray(mask, dtype=bool)
        if sel.any():
            rms_in = float(np.sqrt(r2[sel].mean()))
    return ResidualStats(rms, rms_m, rms_in, n)
