"""Numba kernels of :mod:`schlieren.pipeline.spacetime.motion`: warping a multi-channel
volume along a displacement field given on the same grid or on a grid ``s`` times coarser
(the coarse field sampled trilinearly at ``p / s``, the coarse grid's voxel ``j`` being the
fine voxel ``s j``, as :func:`~schlieren.pipeline.spacetime.motion.downsample2` takes it),
with trilinear or Keys-cubic (``a = -1/2``, no prefilter) interpolation, clamped at the
volume's edges. Serial loops: the pipeline runs one thread per task."""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["warp", "upsample"]


@nb.njit(cache=True, inline="always")
def _clamp(i, n):
    return 0 if i < 0 else (n - 1 if i > n - 1 else i)


@nb.njit(cache=True, inline="always")
def _keys(t, w):
    """Keys cubic weights (a = -1/2) of the four taps around fractional offset ``t`` in [0, 1)."""
    t2 = t * t
    t3 = t2 * t
    w[0] = -0.5 * t3 + t2 - 0.5 * t
    w[1] = 1.5 * t3 - 2.5 * t2 + 1.0
    w[2] = -1.5 * t3 + 2.0 * t2 + 0.5 * t
    w[3] = 0.5 * t3 - 0.5 * t2


@nb.njit(cache=True, inline="always")
def _coarse(u, z, y, x, s, out):
    """``s`` times the trilinear interpolation of the coarse field ``u`` at ``(z, y, x) / s``."""
    mz, my, mx = u.shape[0], u.shape[1], u.shape[2]
    cz, cy, cx = z / s, y / s, x / s
    z0, y0, x0 = int(np.floor(cz)), int(np.floor(cy)), int(np.floor(cx))
    fz, fy, fx = cz - z0, cy - y0, cx - x0
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    for dz in range(2):
        wz = fz if dz else 1.0 - fz
        iz = _clamp(z0 + dz, mz)
        for dy in range(2):
            wy = fy if dy else 1.0 - fy
            iy = _clamp(y0 + dy, my)
            for dx in range(2):
                w = wz * wy * (fx if dx else 1.0 - fx)
                ix = _clamp(x0 + dx, mx)
                for a in range(3):
                    out[a] += w * u[iz, iy, ix, a]
    for a in range(3):
        out[a] *= s


@nb.njit(cache=True)
def upsample(u, shape, s):
    """The coarse displacement field ``u`` (voxels of its grid) on the fine grid ``shape``."""
    out = np.empty((shape[0], shape[1], shape[2], 3), np.float32)
    d = np.empty(3)
    for z in range(shape[0]):
        for y in range(shape[1]):
            for x in range(shape[2]):
                _coarse(u, z, y, x, s, d)
                for a in range(3):
                    out[z, y, x, a] = d[a]
    return out


@nb.njit(cache=True)
def warp(v, u, s, cubic):  # one loop nest over voxels, taps and channels (a numba kernel)
    """``v(p + u(p))`` for every voxel ``p``: ``v`` (nz, ny, nx, c), ``u`` (mz, my, mx, 3)
    displacements in voxels of ``v`` given on a grid ``s`` times coarser (1: the same grid);
    trilinear or (``cubic``) Keys-cubic interpolation, indices clamped to the volume."""
    nz, ny, nx, nc = v.shape
    out = np.zeros(v.shape, np.float32)
    d = np.empty(3)
    wz = np.empty(4)
    wy = np.empty(4)
    wx = np.empty(4)
    for z in range(nz):
        for y in range(ny):
            for x in range(nx):
                if s == 1:
                    d[0], d[1], d[2] = u[z, y, x, 0], u[z, y, x, 1], u[z, y, x, 2]
                else:
                    _coarse(u, z, y, x, s, d)
                pz, py, px = z + d[0], y + d[1], x + d[2]
                z0, y0, x0 = int(np.floor(pz)), int(np.floor(py)), int(np.floor(px))
                fz, fy, fx = pz - z0, py - y0, px - x0
                if cubic:
                    _keys(fz, wz)
                    _keys(fy, wy)
                    _keys(fx, wx)
                    for a in range(4):
                        iz = _clamp(z0 - 1 + a, nz)
                        for b in range(4):
                            iy = _clamp(y0 - 1 + b, ny)
                            wab = wz[a] * wy[b]
                            for c in range(4):
                                ix = _clamp(x0 - 1 + c, nx)
                                w = wab * wx[c]
                                for k in range(nc):
                                    out[z, y, x, k] += w * v[iz, iy, ix, k]
                else:
                    for a in range(2):
                        iz = _clamp(z0 + a, nz)
                        w_a = fz if a else 1.0 - fz
                        for b in range(2):
                            iy = _clamp(y0 + b, ny)
                            wab = w_a * (fy if b else 1.0 - fy)
                            for c in range(2):
                                ix = _clamp(x0 + c, nx)
                                w = wab * (fx if c else 1.0 - fx)
                                for k in range(nc):
                                    out[z, y, x, k] += w * v[iz, iy, ix, k]
    return out
