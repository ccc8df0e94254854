"""Numba kernels of :mod:`~schlieren.pipeline.poisson.tensor`: a 3x3 symmetric
eigen-decomposition and the Appendix's tensor from the smoothed structure tensor."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _eigh3(a, v):
    """Eigen-decomposition of the symmetric 3x3 ``a`` by cyclic Jacobi rotations.

    On return the diagonal of ``a`` holds the eigenvalues and the columns of ``v`` the
    eigenvectors (orthonormal to rounding); ``a`` is overwritten.
    """
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(50):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-32 * diag or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = a[p, q]
            if apq == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for kk in range(3):  # a <- a G (columns p, q)
                akp = a[kk, p]
                akq = a[kk, q]
                a[kk, p] = c * akp - s * akq
                a[kk, q] = s * akp + c * akq
            for kk in range(3):  # a <- G^T a (rows p, q)
                apk = a[p, kk]
                aqk = a[q, kk]
                a[p, kk] = c * apk - s * aqk
                a[q, kk] = s * apk + c * aqk
            a[p, q] = 0.0
            a[q, p] = 0.0
            for kk in range(3):
                vkp = v[kk, p]
                vkq = v[kk, q]
                v[kk, p] = c * vkp - s * vkq
                v[kk, q] = s * vkp + c * vkq


@nb.njit(parallel=True, cache=True)
def _tensor_from_structure(J6, M, k, alpha, D):
    """The Appendix's tensor from the smoothed structure tensor (components xx, yy, zz,
    xy, xz, yz per voxel): eigenvalues ``lambda0 >= lambda1 >= lambda2`` with vectors
    ``v0, v1, v2``; ``D = alpha v0 v0^T + sum_{j=1,2} (alpha + (1 - alpha)
    exp(-M / (k (lambda0 - lambda_j)^2))) v_j v_j^T``.

    ``J`` is positive semi-definite (a Gaussian-weighted sum of ``g g^T``), so every
    eigenvalue gap is at most ``trace(J)``; where even that bound makes both exponentials
    underflow to exactly 0 (``exp(-x) == 0`` for ``x > 745.2``) all eigenvalues are
    alpha and ``D = alpha I`` exactly, with no decomposition (almost everywhere with the
    default units).
    """
    n = J6.shape[1]
    for i in nb.prange(n):
        tr = J6[0, i] + J6[1, i] + J6[2, i]
        for r in range(3):
            for c in range(3):
                D[i, r, c] = 0.0
        inert = tr <= 0.0
        if not inert:
            bound = k * (1.01 * tr) ** 2
            inert = bound == 0.0 or M / bound > 800.0
        if inert:
            D[i, 0, 0] = alpha
            D[i, 1, 1] = alpha
            D[i, 2, 2] = alpha
            continue
        a = np.empty((3, 3))
        v = np.empty((3, 3))
        a[0, 0] = J6[0, i]
        a[1, 1] = J6[1, i]
        a[2, 2] = J6[2, i]
        a[0, 1] = a[1, 0] = J6[3, i]
        a[0, 2] = a[2, 0] = J6[4, i]
        a[1, 2] = a[2, 1] = J6[5, i]
        _eigh3(a, v)
        lam = np.array([a[0, 0], a[1, 1], a[2, 2]])
        order = np.argsort(-lam)  # lambda0 first
        l0 = lam[order[0]]
        for rank in range(3):
            j = order[rank]
            if rank == 0:
                mu = alpha
            else:
                d = (l0 - lam[j]) ** 2
                mu = alpha + (1.0 - alpha) * np.exp(-M / (k * d)) if d > 0.0 else alpha
            for r in range(3):
                for c in range(3):
                    D[i, r, c] += mu * v[r, j] * v[c, j]
