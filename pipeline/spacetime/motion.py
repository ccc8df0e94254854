"""The motion between two volumes of a sequence: dense pyramidal 3D Lucas-Kanade.

Beyond the paper, which solves every frame alone. A gas flow at 60 frames per second moves
a few voxels between frames, so successive reconstructions show the same structures
displaced: :func:`volume_motion` estimates that displacement field from two volumes (the
per-frame gradient reconstructions, their three components as channels), and
:func:`warp_volume` moves a volume along it. The estimator is the 2D pyramidal
Lucas-Kanade of :mod:`schlieren.pipeline.sync.motion` in three dimensions: at each level of
a Gaussian pyramid the moving volume is warped by the current estimate, and the update
solves the 3x3 normal equations of the linearised brightness constancy summed over the
channels and a Gaussian window, with a Tikhonov term relative to the mean structure tensor
trace so that featureless regions keep the coarser estimate.

Displacements are in voxels, ordered (z, y, x) like the array axes. The warps and the
interpolation of a coarse motion are numba kernels (:mod:`._kernels`).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from schlieren.pipeline.spacetime import _kernels

__all__ = ["volume_motion", "warp_volume", "downsample2", "upsample_motion"]


def _channels(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float32)
    return v[..., None] if v.ndim == 3 else v


def downsample2(v: np.ndarray) -> np.ndarray:
    """A volume (nz, ny, nx[, c]) at half resolution: Gaussian (sigma 1 voxel) then every
    second voxel along each spatial axis."""
    v = _channels(v)
    out = np.stack([ndi.gaussian_filter(v[..., c], 1.0, mode="nearest")[::2, ::2, ::2] for c in range(v.shape[-1])],
                   axis=-1)
    return out


def upsample_motion(u: np.ndarray, shape: tuple[int, int, int], scale: int = 2) -> np.ndarray:
    """A motion field of a grid ``scale`` times coarser (voxels of that grid; its voxel ``j``
    is the fine voxel ``scale * j``, as :func:`downsample2` takes it) on the fine ``shape``:
    interpolated trilinearly and multiplied by ``scale``."""
    return _kernels.upsample(np.ascontiguousarray(u, dtype=np.float32), tuple(int(s) for s in shape), int(scale))


def warp_volume(v: np.ndarray, u: np.ndarray, *, order: int = 1, scale: int = 1) -> np.ndarray:
    """``v(p + u(p))`` for every voxel ``p`` (``v`` (nz, ny, nx[, c]), ``u`` in voxels of ``v``,
    (z, y, x)); outside the volume the nearest edge value. ``order``: 1 trilinear, 3 Keys
    cubic. ``scale``: ``u`` is given on a grid this many times coarser
    (:func:`upsample_motion`'s convention), sampled trilinearly."""
    if order not in (1, 3):
        raise ValueError(f"warp_volume: order must be 1 or 3, not {order}")
    v = np.asarray(v)
    squeeze = v.ndim == 3
    vc = np.ascontiguousarray(_channels(v))
    out = _kernels.warp(vc, np.ascontiguousarray(u, dtype=np.float32), int(scale), order == 3)
    return out[..., 0] if squeeze else out


def _gradients(v: np.ndarray) -> list[np.ndarray]:
    """Central differences of each channel along z, y, x: three arrays (nz, ny, nx, c)."""
    k = np.array([0.5, 0.0, -0.5], np.float32)
    return [ndi.correlate1d(v, k[::-1], axis=a, mode="nearest") for a in range(3)]


def _lk_step(ref: np.ndarray, warped: np.ndarray, sigma: float, reg: float) -> np.ndarray:
    """One Lucas-Kanade update ``du`` (nz, ny, nx, 3) with ``warped(p + du) ~ ref(p)``."""
    mean = 0.5 * (ref + warped)
    g = _gradients(mean)
    it = warped - ref
    J = {}
    for a in range(3):
        for b in range(a, 3):
            J[a, b] = ndi.gaussian_filter(np.sum(g[a] * g[b], axis=-1), sigma, mode="constant")
    r = [ndi.gaussian_filter(-np.sum(g[a] * it, axis=-1), sigma, mode="constant") for a in range(3)]
    eps = reg * float(np.mean(J[0, 0] + J[1, 1] + J[2, 2])) + 1e-30
    a11, a22, a33 = J[0, 0] + eps, J[1, 1] + eps, J[2, 2] + eps
    a12, a13, a23 = J[0, 1], J[0, 2], J[1, 2]
    # the 3x3 symmetric solve by cofactors, voxel by voxel
    c11 = a22 * a33 - a23 * a23
    c12 = a13 * a23 - a12 * a33
    c13 = a12 * a23 - a13 * a22
    c22 = a11 * a33 - a13 * a13
    c23 = a12 * a13 - a11 * a23
    c33 = a11 * a22 - a12 * a12
    det = a11 * c11 + a12 * c12 + a13 * c13
    det = np.where(np.abs(det) > 0, det, 1.0)
    du = np.empty(ref.shape[:3] + (3,), np.float32)
    du[..., 0] = (c11 * r[0] + c12 * r[1] + c13 * r[2]) / det
    du[..., 1] = (c12 * r[0] + c22 * r[1] + c23 * r[2]) / det
    du[..., 2] = (c13 * r[0] + c23 * r[1] + c33 * r[2]) / det
    return du


def volume_motion(ref: np.ndarray, mov: np.ndarray, *, levels: int = 3, sigma: float = 3.0,
                  iterations: int = 3, reg: float = 0.05, skip: int = 0,
                  max_step: float = 1.0) -> np.ndarray:
    """The displacement ``u`` with ``mov(p + u(p)) ~ ref(p)``: pyramidal 3D Lucas-Kanade.

    Parameters
    ----------
    ref, mov : ndarray, shape (nz, ny, nx) or (nz, ny, nx, c)
        The two volumes (channels, e.g. the three gradient components, are summed in
        the normal equations).
    levels : int
        Pyramid levels (each halves the resolution): displacements up to about
        ``2 ** (levels - 1)`` voxels are found.
    sigma : float
        Gaussian window of the structure tensor, voxels of each level.
    iterations : int
        Warp-and-update steps per level.
    reg : float
        Tikhonov weight of the 3x3 solve, relative to the mean structure tensor trace:
        where the volumes carry no structure the update is damped to zero.
    skip : int
        Finest levels not refined (their motion is the coarser level's, interpolated):
        the motion of a smooth flow needs no full-resolution estimate.
    max_step : float
        Largest update per step and axis, voxels of the level (a safeguard where the
        linearisation fails).

    Returns
    -------
    u : ndarray, shape (nz, ny, nx, 3) float32
        Voxels, (z, y, x).
    """
    ref = _channels(ref)
    mov = _channels(mov)
    if ref.shape != mov.shape:
        raise ValueError(f"volume_motion: shapes differ, {ref.shape} and {mov.shape}")
    pyr = [(ref, mov)]
    for _ in range(max(levels, 1) - 1):
        a, b = pyr[-1]
        if min(a.shape[:3]) < 8:
            break
        pyr.append((downsample2(a), downsample2(b)))
    u = None
    for lvl in range(len(pyr) - 1, -1, -1):
        a, b = pyr[lvl]
        u = np.zeros(a.shape[:3] + (3,), np.float32) if u is None else upsample_motion(u, a.shape[:3])
        if lvl < skip:
            continue
        for _ in range(iterations):
            du = _lk_step(a, warp_volume(b, u), sigma, reg)
            u += np.clip(du, -max_step, max_step)
    return u
