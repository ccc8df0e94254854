"""Numba kernels of :mod:`~schlieren.pipeline.poisson.multigrid`: red-black Gauss-Seidel
smoothing and residuals (finest level over cell lists, coarse levels with per-face weights),
restriction and prolongation, and the levels' set-up."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _gs_cells(u, f, inv_dg, h2, cells, sy, sz, first):
    """Gauss-Seidel update of the listed cells of one colour (finest level, unit weights).

    ``u``, ``f`` and ``inv_dg`` are flattened boxes whose outer layer is inactive, so
    every neighbour index is in bounds; inactive cells hold zero. With ``first`` the
    neighbours are known to be zero (the red half-sweep from a zero start).
    """
    if first:
        for c in range(cells.shape[0]):
            p = cells[c]
            u[p] = f[p] * h2 * inv_dg[p]
        return
    for c in range(cells.shape[0]):
        p = cells[c]
        u[p] = (f[p] * h2 + u[p - 1] + u[p + 1] + u[p - sy] + u[p + sy] + u[p - sz] + u[p + sz]) * inv_dg[p]


@nb.njit(cache=True)
def _scatter_first(r, flat, is_red, h2, inv_dg, f, u):
    """``f[flat] = r`` and the first red half-sweep from zero (finest level)."""
    for c in range(flat.shape[0]):
        p = flat[c]
        f[p] = r[c]
        if is_red[c]:
            u[p] = r[c] * h2 * inv_dg[p]


@nb.njit(cache=True)
def _gs_red_gather(u, f, inv_dg, h2, flat, is_red, sy, sz, out):
    """The last red half-sweep of the finest level, gathering ``out = u[flat]`` on the way."""
    for c in range(flat.shape[0]):
        p = flat[c]
        if is_red[c]:
            u[p] = (f[p] * h2 + u[p - 1] + u[p + 1] + u[p - sy] + u[p + sy] + u[p - sz] + u[p + sz]) * inv_dg[p]
        out[c] = u[p]


@nb.njit(cache=True)
def _residual_cells(u, f, dg, inv_h2, cells, sy, sz, out):
    """``out = f - A u`` on the listed cells (finest level); other entries untouched.

    After a black half-sweep the residual vanishes on black cells, so the V-cycle
    computes it on the red cells only.
    """
    for c in range(cells.shape[0]):
        p = cells[c]
        s = dg[p] * u[p] - (u[p - 1] + u[p + 1] + u[p - sy] + u[p + sy] + u[p - sz] + u[p + sz])
        out[p] = f[p] - s * inv_h2


@nb.njit(cache=True)
def _gs_weighted(u, f, mask, wx, wy, wz, inv_dg, h2, colour, first):
    """Gauss-Seidel half-sweep on one colour of a coarse level (per-face weights).

    ``wx[k, j, i]`` weights the face between ``(k, j, i)`` and ``(k, j, i + 1)`` (zero at
    the array edge and next to inactive cells), likewise ``wy`` and ``wz``.
    """
    nz, ny, nx = u.shape
    for k in range(nz):
        for j in range(ny):
            for i in range((colour + k + j) % 2, nx, 2):
                if not mask[k, j, i]:
                    continue
                s = f[k, j, i] * h2
                if not first:
                    if i > 0:
                        s += wx[k, j, i - 1] * u[k, j, i - 1]
                    if i < nx - 1:
                        s += wx[k, j, i] * u[k, j, i + 1]
                    if j > 0:
                        s += wy[k, j - 1, i] * u[k, j - 1, i]
                    if j < ny - 1:
                        s += wy[k, j, i] * u[k, j + 1, i]
                    if k > 0:
                        s += wz[k - 1, j, i] * u[k - 1, j, i]
                    if k < nz - 1:
                        s += wz[k, j, i] * u[k + 1, j, i]
                u[k, j, i] = s * inv_dg[k, j, i]


@nb.njit(cache=True)
def _residual_weighted(u, f, mask, wx, wy, wz, dg, inv_h2, colour, out):
    """``out = f - A u`` on the active cells of one colour of a coarse level."""
    nz, ny, nx = u.shape
    for k in range(nz):
        for j in range(ny):
            for i in range((colour + k + j) % 2, nx, 2):
                if not mask[k, j, i]:
                    continue
                s = dg[k, j, i] * u[k, j, i]
                if i > 0:
                    s -= wx[k, j, i - 1] * u[k, j, i - 1]
                if i < nx - 1:
                    s -= wx[k, j, i] * u[k, j, i + 1]
                if j > 0:
                    s -= wy[k, j - 1, i] * u[k, j - 1, i]
                if j < ny - 1:
                    s -= wy[k, j, i] * u[k, j + 1, i]
                if k > 0:
                    s -= wz[k - 1, j, i] * u[k - 1, j, i]
                if k < nz - 1:
                    s -= wz[k, j, i] * u[k + 1, j, i]
                out[k, j, i] = f[k, j, i] - s * inv_h2


@nb.njit(cache=True)
def _restrict(r, mask_c, tx, ty, out):
    """Full weighting: transpose of :func:`_prolong_add` divided by 8.

    Separable: the 1-D weights (1/4, 3/4, 3/4, 1/4) on fine cells ``2K-1 .. 2K+2`` are
    applied along x (into ``tx``), then y (``ty``), then z (fine cells outside the array
    count as zero).
    """
    cz, cy, cx = out.shape
    fz, fy, fx = r.shape
    for k in range(fz):
        for j in range(fy):
            for I in range(cx):
                s = 0.0
                for c in range(4):
                    i = 2 * I - 1 + c
                    if 0 <= i < fx:
                        s += (0.25 if c == 0 or c == 3 else 0.75) * r[k, j, i]
                tx[k, j, I] = s
    for k in range(fz):
        for J in range(cy):
            for I in range(cx):
                s = 0.0
                for b in range(4):
                    j = 2 * J - 1 + b
                    if 0 <= j < fy:
                        s += (0.25 if b == 0 or b == 3 else 0.75) * tx[k, j, I]
                ty[k, J, I] = s
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                if not mask_c[K, J, I]:
                    out[K, J, I] = 0.0
                    continue
                s = 0.0
                for a in range(4):
                    k = 2 * K - 1 + a
                    if 0 <= k < fz:
                        s += (0.25 if a == 0 or a == 3 else 0.75) * ty[k, J, I]
                out[K, J, I] = 0.125 * s


@nb.njit(cache=True)
def _prolong_add(uc, mask_f, ex, ey, uf):
    """Add the trilinear (cell-centred) interpolation of ``uc`` to the active fine cells.

    Fine cell ``k`` takes 3/4 of coarse cell ``k // 2`` and 1/4 of its other neighbour
    (``k // 2 - 1`` for even ``k``, ``k // 2 + 1`` for odd; zero outside the array),
    separably along x (into ``ex``), y (``ey``) and z.
    """
    fz, fy, fx = uf.shape
    cz, cy, cx = uc.shape
    for K in range(cz):
        for J in range(cy):
            for i in range(fx):
                I = i // 2
                In = I - 1 if i % 2 == 0 else I + 1
                s = 0.75 * uc[K, J, I] if I < cx else 0.0
                if 0 <= In < cx:
                    s += 0.25 * uc[K, J, In]
                ex[K, J, i] = s
    for K in range(cz):
        for j in range(fy):
            J = j // 2
            Jn = J - 1 if j % 2 == 0 else J + 1
            for i in range(fx):
                s = 0.75 * ex[K, J, i] if J < cy else 0.0
                if 0 <= Jn < cy:
                    s += 0.25 * ex[K, Jn, i]
                ey[K, j, i] = s
    for k in range(fz):
        K = k // 2
        Kn = K - 1 if k % 2 == 0 else K + 1
        for j in range(fy):
            for i in range(fx):
                if not mask_f[k, j, i]:
                    continue
                s = 0.75 * ey[K, j, i] if K < cz else 0.0
                if 0 <= Kn < cz:
                    s += 0.25 * ey[Kn, j, i]
                uf[k, j, i] += s


@nb.njit(cache=True)
def _fine_level(mask, real, wx, wy, wz, ddir, dg, inv_dg):
    """Finest level: unit face weights between active cells, the Dirichlet part of each
    active diagonal, the diagonal itself, and the active cells as flat indices (all with
    their colour, red, black).

    A neighbour that is inactive but ``real`` is a Dirichlet face; one that is not
    ``real`` is a natural face and counts for nothing. ``mask``'s outer layer is inactive.
    """
    nz, ny, nx = mask.shape
    n = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                n += mask[k, j, i]
    flat = np.empty(n, np.int64)
    is_red = np.zeros(n, np.bool_)
    red = np.empty(n, np.int64)
    black = np.empty(n, np.int64)
    a = nr = nb_ = 0
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                if not mask[k, j, i]:
                    continue
                p = (k * ny + j) * nx + i
                flat[a] = p
                if (k + j + i) % 2 == 0:
                    is_red[a] = True
                    red[nr] = p
                    nr += 1
                else:
                    black[nb_] = p
                    nb_ += 1
                a += 1
                wx[k, j, i] = 1.0 if mask[k, j, i + 1] else 0.0
                wy[k, j, i] = 1.0 if mask[k, j + 1, i] else 0.0
                wz[k, j, i] = 1.0 if mask[k + 1, j, i] else 0.0
                d = 0.0
                faces = 0.0
                for dk, dj, di in ((0, 0, -1), (0, 0, 1), (0, -1, 0), (0, 1, 0), (-1, 0, 0), (1, 0, 0)):
                    kk, jj, ii = k + dk, j + dj, i + di
                    if real[kk, jj, ii]:
                        faces += 1.0
                        if not mask[kk, jj, ii]:
                            d += 1.0
                ddir[k, j, i] = d
                dg[k, j, i] = faces
                inv_dg[k, j, i] = 1.0 / faces
    return flat, is_red, red[:nr], black[:nb_]


@nb.njit(cache=True)
def _coarsen(mask, wx, wy, wz, ddir, min_children, dirichlet_scale, mc, Wx, Wy, Wz, Dc):
    """Aggregation-Galerkin coarse level (see the section comment); outputs zero-filled.

    Returns the number of active coarse cells.
    """
    nz, ny, nx = mask.shape
    cz, cy, cx = mc.shape
    cnt = np.zeros(mc.shape, np.int64)
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                K, J, I = k // 2, j // 2, i // 2
                if mask[k, j, i]:
                    cnt[K, J, I] += 1
                    Dc[K, J, I] += dirichlet_scale * ddir[k, j, i]
                # fine faces crossing a block boundary (odd index -> next block)
                if i % 2 == 1 and I + 1 < cx:
                    Wx[K, J, I] += 0.25 * wx[k, j, i]
                if j % 2 == 1 and J + 1 < cy:
                    Wy[K, J, I] += 0.25 * wy[k, j, i]
                if k % 2 == 1 and K + 1 < cz:
                    Wz[K, J, I] += 0.25 * wz[k, j, i]
    active = 0
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                mc[K, J, I] = cnt[K, J, I] >= min_children
                active += mc[K, J, I]
    # faces touching a coarse cell dropped by min_children become Dirichlet faces
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                for d in range(3):
                    K2, J2, I2 = K + (d == 2), J + (d == 1), I + (d == 0)
                    if K2 >= cz or J2 >= cy or I2 >= cx:
                        continue
                    w = Wx[K, J, I] if d == 0 else (Wy[K, J, I] if d == 1 else Wz[K, J, I])
                    if w == 0.0:
                        continue
                    a, b = mc[K, J, I], mc[K2, J2, I2]
                    if not (a and b):
                        if a:
                            Dc[K, J, I] += w
                        if b:
                            Dc[K2, J2, I2] += w
                        if d == 0:
                            Wx[K, J, I] = 0.0
                        elif d == 1:
                            Wy[K, J, I] = 0.0
                        else:
                            Wz[K, J, I] = 0.0
    for K in range(cz):
        for J in range(cy):
            for I in range(cx):
                if not mc[K, J, I]:
                    Dc[K, J, I] = 0.0
    return active
