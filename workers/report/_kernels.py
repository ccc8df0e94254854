"""Numba kernel of the volume renderer (:mod:`schlieren.workers.report.volume_render`).

:func:`march` composites front to back along many parallel rays through a scalar volume
(emission-absorption, paper Figures 1 and 8), one ray per numba thread.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["march"]


@nb.njit(cache=True, parallel=True)
def march(vol, ro, rd, step, t0, t1, r_amb, inv_scale, lut_rgb, lut_alpha, bg, t_min):
    """Front-to-back emission-absorption compositing along rays in voxel-index space.

    vol (nz, ny, nx); ro (N, 3) ray origins and rd (3,) direction as (ix, iy, iz) index
    coordinates; t0, t1 (N,) entry/exit parameters; step in index units; lut_alpha holds
    the opacity of one step for each signal level.
    """
    nz, ny, nx = vol.shape
    n = ro.shape[0]
    nl = lut_rgb.shape[0]
    out = np.empty((n, 3), np.float64)
    for p in nb.prange(n):  # rays are independent
        cr = 0.0
        cg = 0.0
        cb = 0.0
        T = 1.0
        t = t0[p] + 0.5 * step
        while t < t1[p]:
            x = min(max(ro[p, 0] + t * rd[0], 0.0), nx - 1.0)
            y = min(max(ro[p, 1] + t * rd[1], 0.0), ny - 1.0)
            z = min(max(ro[p, 2] + t * rd[2], 0.0), nz - 1.0)
            ix = min(int(x), nx - 2) if nx > 1 else 0
            iy = min(int(y), ny - 2) if ny > 1 else 0
            iz = min(int(z), nz - 2) if nz > 1 else 0
            fx = x - ix
            fy = y - iy
            fz = z - iz
            jx = ix + 1 if nx > 1 else ix
            jy = iy + 1 if ny > 1 else iy
            jz = iz + 1 if nz > 1 else iz
            c00 = vol[iz, iy, ix] * (1 - fx) + vol[iz, iy, jx] * fx
            c01 = vol[iz, jy, ix] * (1 - fx) + vol[iz, jy, jx] * fx
            c10 = vol[jz, iy, ix] * (1 - fx) + vol[jz, iy, jx] * fx
            c11 = vol[jz, jy, ix] * (1 - fx) + vol[jz, jy, jx] * fx
            c0 = c00 * (1 - fy) + c01 * fy
            c1 = c10 * (1 - fy) + c11 * fy
            val = c0 * (1 - fz) + c1 * fz
            s = (r_amb - val) * inv_scale
            if s > 0.0:
                if s > 1.0:
                    s = 1.0
                k = int(s * (nl - 1) + 0.5)
                a = lut_alpha[k]
                if a > 0.0:
                    w = T * a
                    cr += w * lut_rgb[k, 0]
                    cg += w * lut_rgb[k, 1]
                    cb += w * lut_rgb[k, 2]
                    T *= 1.0 - a
                    if T < t_min:
                        T = 0.0
                        break
            t += step
        out[p, 0] = cr + T * bg[0]
        out[p, 1] = cg + T * bg[1]
        out[p, 2] = cb + T * bg[2]
    return out
