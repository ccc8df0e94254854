"""Exit directions and right-hand sides from the deflections (paper sec. 5, eq. 3).

The approximate exit direction ``d_out_hat`` is the unit vector from ``X_c``, the point of
the undeflected ray closest to the volume centre, to ``B'``, the background point seen by
the deflected ray: the undeflected camera ray through ``p + delta`` meets the background
plane in ``B'`` (flow sign of SPEC: ``frame(p) ~= reference(p + delta)``). The
undistortion of ``p + delta`` is linearised around ``p`` with the Jacobian stored in the
geometry (deflections are a few pixels at most; the quadratic remainder is below 1e-6 px
for the distortions of real lenses).
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.tomography._rays_kernels import _d_out_kernel
from schlieren.pipeline.tomography.geometry import TomoGeometry

__all__ = ["approximate_d_out", "rhs_from_d_out", "rhs_from_flows"]


def _d_out_rays(geom: TomoGeometry, flows_flat: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """``d_out_hat`` for a subset of rays; ``flows_flat`` has shape (n_rays, 2).

    One numba pass per ray (the vectorised numpy form made about a dozen (n, 3)
    temporaries; docs/tuning.md, "Speed"). Paper sec. 5's approximate exit direction.
    """
    C, h, w = geom.flow_shape
    rays = np.ascontiguousarray(rays, dtype=np.int64)
    out = np.empty((len(rays), 3))
    f = np.ascontiguousarray(flows_flat, dtype=np.float64)
    _d_out_kernel(f, rays, h * w, geom.xy.reshape(-1, 2), geom.jac.reshape(-1, 2, 2),
                  np.ascontiguousarray(geom.rot, dtype=np.float64),
                  np.ascontiguousarray(geom.centers, dtype=np.float64),
                  np.ascontiguousarray(geom.bg_point, dtype=np.float64),
                  np.ascontiguousarray(geom.bg_normal, dtype=np.float64), geom.x_c.reshape(-1, 3), out)
    return out


def approximate_d_out(geom: TomoGeometry, flows: np.ndarray) -> np.ndarray:
    """Approximate exit directions ``d_out_hat`` of every flow-grid ray (paper sec. 5).

    Parameters
    ----------
    geom : TomoGeometry
    flows : ndarray, shape (C, h, w, 2)
        Deflections ``delta`` in pixels of the original image (component 0 = u/x).

    Returns
    -------
    d_out : ndarray, shape (C, h, w, 3)
        Unit world directions from ``X_c`` to the background point seen by the deflected
        ray. Zero flow gives ``d_out == d_in``.
    """
    flows = np.asarray(flows)
    if flows.shape != tuple(geom.flow_shape) + (2,):
        raise ValueError(f"flows must have shape {tuple(geom.flow_shape) + (2,)}, got {flows.shape}")
    rays = np.arange(geom.n_rays)
    return _d_out_rays(geom, flows.reshape(-1, 2), rays).reshape(*geom.flow_shape, 3)


def rhs_from_d_out(geom: TomoGeometry, d_out: np.ndarray, *, n_ambient: float) -> np.ndarray:
    """Right-hand side ``n_ambient * (d_out - d_in)`` of eq. 5 (dimensionless).

    Parameters
    ----------
    d_out : ndarray, shape (C, h, w, 3)
        Exit directions (unit; exact from a ray tracer, or :func:`approximate_d_out`).
    n_ambient : float

    Returns
    -------
    rhs : ndarray, shape (C, h, w, 3)
    """
    d_out = np.asarray(d_out, dtype=np.float64)
    return n_ambient * (d_out - geom.d_in)


def rhs_from_flows(geom: TomoGeometry, flows: np.ndarray, *, n_ambient: float,
                   rays: np.ndarray | None = None) -> np.ndarray:
    """Right-hand side from deflections for all rays, or only ``rays`` (flat indices).

    Returns shape (C, h, w, 3) for all rays, else (len(rays), 3).
    """
    flat = np.asarray(flows).reshape(-1, 2)
    if rays is None:
        rays_ = np.arange(geom.n_rays)
        out = n_ambient * (_d_out_rays(geom, flat, rays_) - geom.d_in.reshape(-1, 3))
        return out.reshape(*geom.flow_shape, 3)
    rays = np.asarray(rays)
    return n_ambient * (_d_out_rays(geom, flat, rays) - geom.d_in.reshape(-1, 3)[rays])
