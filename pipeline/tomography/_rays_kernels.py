"""Numba kernel of :mod:`~schlieren.pipeline.tomography.rays`: the approximate exit direction of each ray."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True)
def _d_out_kernel(flows, rays, hw, xy, jac, rot, centers, bg_point, bg_normal, x_c, out):
    for q in nb.prange(rays.shape[0]):
        ray = rays[q]
        c = ray // hw
        d0 = flows[ray, 0]
        d1 = flows[ray, 1]
        u = xy[ray, 0] + jac[ray, 0, 0] * d0 + jac[ray, 0, 1] * d1
        v = xy[ray, 1] + jac[ray, 1, 0] * d0 + jac[ray, 1, 1] * d1
        dx = u * rot[c, 0, 0] + v * rot[c, 1, 0] + rot[c, 2, 0]  # R^T (u, v, 1)
        dy = u * rot[c, 0, 1] + v * rot[c, 1, 1] + rot[c, 2, 1]
        dz = u * rot[c, 0, 2] + v * rot[c, 1, 2] + rot[c, 2, 2]
        num = 0.0
        den = 0.0
        for k in range(3):
            num += (bg_point[c, k] - centers[c, k]) * bg_normal[c, k]
        den = dx * bg_normal[c, 0] + dy * bg_normal[c, 1] + dz * bg_normal[c, 2]
        s = num / den
        vx = centers[c, 0] + s * dx - x_c[ray, 0]
        vy = centers[c, 1] + s * dy - x_c[ray, 1]
        vz = centers[c, 2] + s * dz - x_c[ray, 2]
        nrm = np.sqrt(vx * vx + vy * vy + vz * vz)
        out[q, 0] = vx / nrm
        out[q, 1] = vy / nrm
        out[q, 2] = vz / nrm
