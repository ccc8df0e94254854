"""numba kernels of the background registration: the reference's cubic B-spline and its
gradient at the moved sample positions, the residuals of the photometric model, and the
weighted normal equations (each sample touches only its motion terms and the two knots
of its row).

Driven by :mod:`.registration`. The spline coefficients are those of the prepared
reference (:mod:`schlieren.pipeline.flow.splines`, padded by 2).
"""

import numba as nb
import numpy as np

_PAD = 2


@nb.njit(inline="always")
def _weights(t):
    # cubic B-spline weights for offsets -1, 0, 1, 2 at fractional t, and their derivatives
    s = 1.0 - t
    t2 = t * t
    w0 = s * s * s / 6.0
    w3 = t2 * t / 6.0
    w1 = 2.0 / 3.0 - t2 + 0.5 * t2 * t
    w2 = 1.0 - w0 - w1 - w3
    d0 = -0.5 * s * s
    d3 = 0.5 * t2
    d1 = -2.0 * t + 1.5 * t2
    d2 = -(d0 + d1 + d3)
    return w0, w1, w2, w3, d0, d1, d2, d3


@nb.njit(inline="always")
def _spline_value_grad(cp, x, y, Wm, Hm):
    # value and (d/dx, d/dy) at (x, y) from padded coefficients; positions clamped (the
    # gradient is then that of the clamped position)
    x = min(max(x, 0.0), Wm)
    y = min(max(y, 0.0), Hm)
    x0 = int(x)
    y0 = int(y)
    ax0, ax1, ax2, ax3, bx0, bx1, bx2, bx3 = _weights(x - x0)
    ay0, ay1, ay2, ay3, by0, by1, by2, by3 = _weights(y - y0)
    k = x0 + 1
    val = 0.0
    gx = 0.0
    gy = 0.0
    for j in range(4):
        row = cp[y0 + 1 + j]
        sx = ax0 * row[k] + ax1 * row[k + 1] + ax2 * row[k + 2] + ax3 * row[k + 3]
        dx = bx0 * row[k] + bx1 * row[k + 1] + bx2 * row[k + 2] + bx3 * row[k + 3]
        wy = ay0 if j == 0 else (ay1 if j == 1 else (ay2 if j == 2 else ay3))
        dy = by0 if j == 0 else (by1 if j == 1 else (by2 if j == 2 else by3))
        val += wy * sx
        gx += wy * dx
        gy += dy * sx
    return val, gx, gy


@nb.njit(inline="always")
def _warp(X, Y, cx, cy, th):
    # T(q) of motion.py at full-resolution position (X, Y): returns qx, qy, D, Tx, Ty
    qx = X - cx
    qy = Y - cy
    D = 1.0 + th[6] * qx + th[7] * qy
    Tx = ((1.0 + th[2]) * qx + th[3] * qy + th[0]) / D
    Ty = (th[4] * qx + (1.0 + th[5]) * qy + th[1]) / D
    return qx, qy, D, Tx, Ty


@nb.njit(inline="always")
def _knot(Y, k0, step, nk):
    if nk == 1:
        return 0, 0.0
    t = (Y - k0) / step
    t = min(max(t, 0.0), nk - 1.0)
    k = min(int(t), nk - 2)
    return k, t - k


@nb.njit(cache=True, nogil=True, fastmath=True)
def _residuals(cp, frame, xs, ys, scale, cx, cy, th, nm, k0, step, gam, bet, e, J, kk):
    """Residual ``frame - ((1 + gamma) ref(T) + beta)`` at the samples, and each sample's
    Jacobian row: the ``nm`` motion terms, then the gains and offsets of its row's two knots
    (``kk``: the left knot)."""
    Hm = cp.shape[0] - 2 * _PAD - 1.0
    Wm = cp.shape[1] - 2 * _PAD - 1.0
    nk = gam.shape[0]
    for i in range(xs.shape[0]):
        X = scale * xs[i]
        Y = scale * ys[i]
        qx, qy, D, Tx, Ty = _warp(X, Y, cx, cy, th)
        v, dvx, dvy = _spline_value_grad(cp, xs[i] + (Tx - qx) / scale, ys[i] + (Ty - qy) / scale, Wm, Hm)
        k, w = _knot(Y, k0, step, nk)
        k1 = min(k + 1, nk - 1)
        g = 1.0 + (1.0 - w) * gam[k] + w * gam[k1]
        b = (1.0 - w) * bet[k] + w * bet[k1]
        e[i] = frame[ys[i], xs[i]] - (g * v + b)
        gx = g * dvx / scale / D
        gy = g * dvy / scale / D
        J[i, 0] = gx
        J[i, 1] = gy
        if nm > 2:
            J[i, 2] = gx * qx
            J[i, 3] = gx * qy
            J[i, 4] = gy * qx
            J[i, 5] = gy * qy
        if nm > 6:
            gt = -(gx * Tx + gy * Ty)
            J[i, 6] = gt * qx
            J[i, 7] = gt * qy
        J[i, nm] = v * (1.0 - w)
        J[i, nm + 1] = v * w
        J[i, nm + 2] = 1.0 - w
        J[i, nm + 3] = w
        kk[i] = k
