"""numba kernels of the flow: cubic B-spline warps, the LK residual and solve, the ICI
window rule, per-cell block moments, the texture-bias solve and the pyramid prolongation.

Driven by :mod:`.splines`, :mod:`.lk` and :mod:`.hs`. All work on float32 arrays in place
(outputs passed in); ``cache=True`` keeps the compiled code between processes.
"""

import numba as nb
import numpy as np


_F32 = np.float32
_PAD = 2  # border of the padded spline-coefficient arrays


@nb.njit(inline="always", fastmath=True)
def _bspline_weights(t):
    # cubic B-spline weights for offsets -1, 0, 1, 2 at fractional t (float32)
    s = _F32(1.0) - t
    t2 = t * t
    t3 = t2 * t
    w0 = s * s * s * _F32(1.0 / 6.0)
    w3 = t3 * _F32(1.0 / 6.0)
    w1 = _F32(2.0 / 3.0) - t2 + _F32(0.5) * t3
    w2 = _F32(1.0) - w0 - w1 - w3
    return w0, w1, w2, w3


@nb.njit(inline="always", fastmath=True)
def _bspline_at(cp, x, y, Wm, Hm):
    # Cubic B-spline interpolation at image coordinate (x, y) from coefficients ``cp``
    # padded by _PAD on every side (see _spline_coefficients); the position is clamped
    # to [0, Wm] x [0, Hm] (Wm = W - 1, Hm = H - 1).
    x = min(max(x, _F32(0.0)), Wm)
    y = min(max(y, _F32(0.0)), Hm)
    x0 = int(x)
    y0 = int(y)
    ax0, ax1, ax2, ax3 = _bspline_weights(x - _F32(x0))
    ay0, ay1, ay2, ay3 = _bspline_weights(y - _F32(y0))
    k = x0 + 1  # padded column of image column x0 - 1
    r0 = cp[y0 + 1]
    r1 = cp[y0 + 2]
    r2 = cp[y0 + 3]
    r3 = cp[y0 + 4]
    return (ay0 * (ax0 * r0[k] + ax1 * r0[k + 1] + ax2 * r0[k + 2] + ax3 * r0[k + 3])
            + ay1 * (ax0 * r1[k] + ax1 * r1[k + 1] + ax2 * r1[k + 2] + ax3 * r1[k + 3])
            + ay2 * (ax0 * r2[k] + ax1 * r2[k + 1] + ax2 * r2[k + 2] + ax3 * r2[k + 3])
            + ay3 * (ax0 * r3[k] + ax1 * r3[k + 1] + ax2 * r3[k + 2] + ax3 * r3[k + 3]))


@nb.njit(fastmath=True, cache=True, nogil=True)
def _warp_kernel(cp, u, v, out):
    H, W = out.shape
    Wm = _F32(W - 1)
    Hm = _F32(H - 1)
    for r in range(H):
        fr = _F32(r)
        for c in range(W):
            out[r, c] = _bspline_at(cp, _F32(c) + u[r, c], fr + v[r, c], Wm, Hm)


@nb.njit(fastmath=True, cache=True, nogil=True)
def _warp_rows_kernel(cp, rows, u, v, out):
    """:func:`_warp_kernel` for the image rows ``rows`` only (``u``, ``v``, ``out``: one row each)."""
    W = out.shape[1]
    Wm = _F32(W - 1)
    Hm = _F32(cp.shape[0] - 2 * _PAD - 1)
    for q in range(rows.shape[0]):
        fr = _F32(rows[q])
        for c in range(W):
            out[q, c] = _bspline_at(cp, _F32(c) + u[q, c], fr + v[q, c], Wm, Hm)


@nb.njit(fastmath=True, cache=True, nogil=True)
def _lk_residual_kernel(cp, frame, gx, gy, u, v, ex, ey):
    # e = frame - ref(q + d(q)) + g . d(q); returns gx * e, gy * e.
    # Per row: first the B-spline indices and weights (a loop LLVM vectorises), then the
    # 4x4 gathers: faster than evaluating _bspline_at pixel by pixel (docs/tuning.md, "Speed").
    H, W = frame.shape
    Wm = _F32(W - 1)
    Hm = _F32(H - 1)
    ix = np.empty(W, np.int64)
    iy = np.empty(W, np.int64)
    wx = np.empty((4, W), np.float32)
    wy = np.empty((4, W), np.float32)
    sixth = _F32(1.0 / 6.0)
    for r in range(H):
        fr = _F32(r)
        for c in range(W):
            x = min(max(_F32(c) + u[r, c], _F32(0.0)), Wm)
            y = min(max(fr + v[r, c], _F32(0.0)), Hm)
            x0 = np.floor(x)
            y0 = np.floor(y)
            tx = x - x0
            ty = y - y0
            ix[c] = int(x0) + 1  # padded column of image column x0 - 1
            iy[c] = int(y0) + 1
            s = _F32(1.0) - tx
            t2 = tx * tx
            t3 = t2 * tx
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + _F32(0.5) * t3
            wx[0, c] = a0
            wx[1, c] = a1
            wx[2, c] = _F32(1.0) - a0 - a1 - a3
            wx[3, c] = a3
            s = _F32(1.0) - ty
            t2 = ty * ty
            t3 = t2 * ty
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + _F32(0.5) * t3
            wy[0, c] = a0
            wy[1, c] = a1
            wy[2, c] = _F32(1.0) - a0 - a1 - a3
            wy[3, c] = a3
        for c in range(W):
            k = ix[c]
            rr = iy[c]
            acc = _F32(0.0)
            for j in range(4):
                row = cp[rr + j]
                acc += wy[j, c] * (wx[0, c] * row[k] + wx[1, c] * row[k + 1]
                                   + wx[2, c] * row[k + 2] + wx[3, c] * row[k + 3])
            uu = u[r, c]
            vv = v[r, c]
            g1 = gx[r, c]
            g2 = gy[r, c]
            e = frame[r, c] - acc + g1 * uu + g2 * vv
            ex[r, c] = g1 * e
            ey[r, c] = g2 * e


# 83 lines: one fused per-row pass (B-spline weights, derivatives, 4x4 gathers) stays one kernel for speed
@nb.njit(fastmath=True, cache=True, nogil=True)
def _lk_residual_grad_kernel(cp, frame, fgx, fgy, u, v, mix, gx, gy, ex, ey):
    # As _lk_residual_kernel, with the gradient g = mix * grad ref(q + d_q) + (1 - mix) *
    # frame gradient (fgx, fgy), the reference gradient being the exact derivative of the
    # cubic B-spline at the warped position; writes g to (gx, gy) and g * e to (ex, ey).
    H, W = frame.shape
    Wm = _F32(W - 1)
    Hm = _F32(H - 1)
    ix = np.empty(W, np.int64)
    iy = np.empty(W, np.int64)
    wx = np.empty((4, W), np.float32)
    wy = np.empty((4, W), np.float32)
    dx = np.empty((4, W), np.float32)
    dy = np.empty((4, W), np.float32)
    sixth = _F32(1.0 / 6.0)
    half = _F32(0.5)
    m1 = _F32(1.0) - mix
    for r in range(H):
        fr = _F32(r)
        for c in range(W):
            x = min(max(_F32(c) + u[r, c], _F32(0.0)), Wm)
            y = min(max(fr + v[r, c], _F32(0.0)), Hm)
            x0 = np.floor(x)
            y0 = np.floor(y)
            tx = x - x0
            ty = y - y0
            ix[c] = int(x0) + 1
            iy[c] = int(y0) + 1
            s = _F32(1.0) - tx
            t2 = tx * tx
            t3 = t2 * tx
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + half * t3
            wx[0, c] = a0
            wx[1, c] = a1
            wx[2, c] = _F32(1.0) - a0 - a1 - a3
            wx[3, c] = a3
            d0 = -half * s * s
            d3 = half * t2
            d1 = _F32(1.5) * t2 - _F32(2.0) * tx
            dx[0, c] = d0
            dx[1, c] = d1
            dx[2, c] = -d0 - d1 - d3
            dx[3, c] = d3
            s = _F32(1.0) - ty
            t2 = ty * ty
            t3 = t2 * ty
            a0 = s * s * s * sixth
            a3 = t3 * sixth
            a1 = _F32(2.0 / 3.0) - t2 + half * t3
            wy[0, c] = a0
            wy[1, c] = a1
            wy[2, c] = _F32(1.0) - a0 - a1 - a3
            wy[3, c] = a3
            d0 = -half * s * s
            d3 = half * t2
            d1 = _F32(1.5) * t2 - _F32(2.0) * ty
            dy[0, c] = d0
            dy[1, c] = d1
            dy[2, c] = -d0 - d1 - d3
            dy[3, c] = d3
        for c in range(W):
            k = ix[c]
            rr = iy[c]
            acc = _F32(0.0)
            accx = _F32(0.0)
            accy = _F32(0.0)
            for j in range(4):
                row = cp[rr + j]
                h = (wx[0, c] * row[k] + wx[1, c] * row[k + 1]
                     + wx[2, c] * row[k + 2] + wx[3, c] * row[k + 3])
                hd = (dx[0, c] * row[k] + dx[1, c] * row[k + 1]
                      + dx[2, c] * row[k + 2] + dx[3, c] * row[k + 3])
                acc += wy[j, c] * h
                accx += wy[j, c] * hd
                accy += dy[j, c] * h
            g1 = mix * accx + m1 * fgx[r, c]
            g2 = mix * accy + m1 * fgy[r, c]
            e = frame[r, c] - acc + g1 * u[r, c] + g2 * v[r, c]
            gx[r, c] = g1
            gy[r, c] = g2
            ex[r, c] = g1 * e
            ey[r, c] = g2 * e


@nb.njit(fastmath=True, cache=True, nogil=True)
def _lk_solve_kernel(sxx, sxy, syy, lam, bx, by, u, v):
    # d = (T + lam I)^-1 b per pixel (2x2 closed form); singular windows give d = 0
    H, W = u.shape
    for r in range(H):
        for c in range(W):
            p = sxx[r, c] + lam
            q = sxy[r, c]
            s = syy[r, c] + lam
            det = p * s - q * q
            inv = _F32(1.0) / det if det > _F32(0.0) else _F32(0.0)
            b1 = bx[r, c]
            b2 = by[r, c]
            u[r, c] = (s * b1 - q * b2) * inv
            v[r, c] = (p * b2 - q * b1) * inv


@nb.njit(fastmath=True, cache=True, nogil=True)
def _ici_kernel(sxx, sxy, syy, lam, bx, by, mxx, mxy, myy, s2, gamma, code, lo, hi, alive, u, v, chosen, sd):
    # One window of the ICI rule: d_w = (T + lam I)^-1 b, Var(d_w) = s2 (T+lam)^-1 M (T+lam)^-1.
    # A pixel keeps d_w while its interval [d_w - gamma sd, d_w + gamma sd] still meets the
    # intersection of every smaller window's interval (per component); once it does not,
    # the pixel keeps its last estimate (Katkovnik's intersection of confidence intervals).
    H, W = u.shape
    for r in range(H):
        for c in range(W):
            if not alive[r, c]:
                continue
            p = sxx[r, c] + lam
            q = sxy[r, c]
            s = syy[r, c] + lam
            det = p * s - q * q
            if det <= _F32(0.0):
                continue
            inv = _F32(1.0) / det
            a = s * inv          # (T + lam)^-1 = [[a, b], [b, d]]
            b = -q * inv
            d = p * inv
            du = a * bx[r, c] + b * by[r, c]
            dv = b * bx[r, c] + d * by[r, c]
            m1 = mxx[r, c]
            m2 = mxy[r, c]
            m3 = myy[r, c]
            vu = a * (a * m1 + b * m2) + b * (a * m2 + b * m3)
            vv = b * (b * m1 + d * m2) + d * (b * m2 + d * m3)
            su = gamma * np.sqrt(max(vu * s2, _F32(0.0)))
            sv = gamma * np.sqrt(max(vv * s2, _F32(0.0)))
            l0 = max(lo[r, c, 0], du - su)
            h0 = min(hi[r, c, 0], du + su)
            l1 = max(lo[r, c, 1], dv - sv)
            h1 = min(hi[r, c, 1], dv + sv)
            if l0 <= h0 and l1 <= h1:
                lo[r, c, 0] = l0
                hi[r, c, 0] = h0
                lo[r, c, 1] = l1
                hi[r, c, 1] = h1
                u[r, c] = du
                v[r, c] = dv
                chosen[r, c] = code
                sd[r, c] = np.sqrt(max((vu + vv) * s2, _F32(0.0)))
            else:
                alive[r, c] = False


@nb.njit(fastmath=True, cache=True, nogil=True)
def _block_moments_kernel(ga, gb, f, out):
    # Per f x f block (i, j) of the flow grid and channel q: the block sum of q, of q * xl
    # and of q * yl, where (xl, yl) is the pixel offset from the block centre. out: (3,
    # rows, cols, k): out[0] = sums, out[1] = x-moments, out[2] = y-moments. k = 3: the
    # channels are the products (a a, a b, b b) of the inputs (the structure tensor from
    # gx, gy); k = 2: the inputs themselves (a, b).
    _, rows, cols, k = out.shape
    c0 = _F32(0.5) * _F32(f - 1)
    products = k == 3
    for i in range(rows):
        for j in range(cols):
            s0 = s1 = s2 = x0 = x1 = x2 = y0 = y1 = y2 = _F32(0.0)
            for dr in range(f):
                yl = _F32(dr) - c0
                ra = ga[i * f + dr]
                rb = gb[i * f + dr]
                for dc in range(f):
                    xl = _F32(dc) - c0
                    a = ra[j * f + dc]
                    b = rb[j * f + dc]
                    if products:
                        p0 = a * a
                        p1 = a * b
                        p2 = b * b
                    else:
                        p0 = a
                        p1 = b
                        p2 = _F32(0.0)
                    s0 += p0
                    s1 += p1
                    s2 += p2
                    x0 += p0 * xl
                    x1 += p1 * xl
                    x2 += p2 * xl
                    y0 += p0 * yl
                    y1 += p1 * yl
                    y2 += p2 * yl
            out[0, i, j, 0] = s0
            out[0, i, j, 1] = s1
            out[1, i, j, 0] = x0
            out[1, i, j, 1] = x1
            out[2, i, j, 0] = y0
            out[2, i, j, 1] = y1
            if products:
                out[0, i, j, 2] = s2
                out[1, i, j, 2] = x2
                out[2, i, j, 2] = y2


@nb.njit(fastmath=True, cache=True, nogil=True)
def _texture_bias_kernel(T, Sx, Sy, flow, inv_f, bu, bv):
    # b = T^-1 (Sx J[:, 0] + Sy J[:, 1]); J = central differences of the smoothed flow
    # (one-sided at the edges), divided by the factor f (grid cells -> image pixels).
    rows, cols = bu.shape
    for i in range(rows):
        i0 = max(i - 1, 0)
        i1 = min(i + 1, rows - 1)
        for j in range(cols):
            j0 = max(j - 1, 0)
            j1 = min(j + 1, cols - 1)
            sx = inv_f / _F32(max(j1 - j0, 1))
            sy = inv_f / _F32(max(i1 - i0, 1))
            ux = (flow[i, j1, 0] - flow[i, j0, 0]) * sx
            vx = (flow[i, j1, 1] - flow[i, j0, 1]) * sx
            uy = (flow[i1, j, 0] - flow[i0, j, 0]) * sy
            vy = (flow[i1, j, 1] - flow[i0, j, 1]) * sy
            r1 = Sx[i, j, 0] * ux + Sx[i, j, 1] * vx + Sy[i, j, 0] * uy + Sy[i, j, 1] * vy
            r2 = Sx[i, j, 1] * ux + Sx[i, j, 2] * vx + Sy[i, j, 1] * uy + Sy[i, j, 2] * vy
            p = T[i, j, 0]
            q = T[i, j, 1]
            s = T[i, j, 2]
            det = p * s - q * q
            if det > _F32(1e-6) * (p + s) * (p + s):
                inv = _F32(1.0) / det
                bu[i, j] = (s * r1 - q * r2) * inv
                bv[i, j] = (p * r2 - q * r1) * inv
            else:
                bu[i, j] = _F32(0.0)
                bv[i, j] = _F32(0.0)


@nb.njit(cache=True, nogil=True)  # no fastmath: the operations in this order, bit for bit
def _prolong_row(s0, s1, b, out):
    # One row of _prolong_kernel from the coarse rows s0 (y0) and s1 (y1): output column c
    # reads coarse columns x0 = c // 2 and x0 + 1 (clamped) at a = 0 (even c) or 1/2.
    w = s0.shape[0]
    W = out.shape[0]
    half = _F32(0.5)
    zero = _F32(0.0)
    two = _F32(2.0)
    n = min(w - 1, W // 2)
    for k in range(n):  # interior: columns 2k (a = 0) and 2k + 1 (a = 1/2), no clamping
        p0 = s0[k]
        p1 = s1[k]
        d0 = s0[k + 1] - p0
        d1 = s1[k + 1] - p1
        i0 = p0 + zero * d0
        i1 = p1 + zero * d1
        out[2 * k] = (i0 + b * (i1 - i0)) * two
        i0 = p0 + half * d0
        i1 = p1 + half * d1
        out[2 * k + 1] = (i0 + b * (i1 - i0)) * two
    for c in range(2 * n, W):  # the right edge (BORDER_REPLICATE)
        x0 = min(c // 2, w - 1)
        x1 = min(c // 2 + 1, w - 1)
        a = half if c % 2 else zero
        p0 = s0[x0]
        p1 = s1[x0]
        i0 = p0 + a * (s0[x1] - p0)
        i1 = p1 + a * (s1[x1] - p1)
        out[c] = (i0 + b * (i1 - i0)) * two


@nb.njit(cache=True, nogil=True)
def _prolong_kernel(u, v, uo, vo):
    # prolong_flow of float32 (u, v): cv2.warpAffine (INTER_LINEAR, BORDER_REPLICATE) at the
    # source position (c / 2, r / 2), times 2, in one pass instead of two warps and two
    # products (docs/tuning.md, "Speed"). OpenCV
    # interpolates as a lerp along x, then along y: i0 = p00 + a (p01 - p00),
    # i1 = p10 + a (p11 - p10), i0 + b (i1 - i0); with a, b in {0, 1/2} every product is
    # exact, so this is OpenCV's result bit for bit (tests/pipeline/test_flow.py checks it
    # against cv2 on odd and even sizes).
    h = u.shape[0]
    H = uo.shape[0]
    half = _F32(0.5)
    for r in range(H):
        y0 = min(r // 2, h - 1)
        y1 = min(r // 2 + 1, h - 1)
        b = half if r % 2 else _F32(0.0)
        _prolong_row(u[y0], u[y1], b, uo[r])
        _prolong_row(v[y0], v[y1], b, vo[r])
