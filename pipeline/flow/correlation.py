"""Window cross-correlation, the classic BOS/PIV method (paper sec. 4 compares optical
flow with it)."""

from __future__ import annotations

import cv2
import numpy as np


def _correlation_flow(ref, frame, *, corr_window, corr_step, corr_taper):
    """Window cross-correlation with 3-point Gaussian sub-pixel peak fit (classic BOS).

    Interrogation windows of ``corr_window`` pixels every ``corr_step`` pixels (mean
    removed, optionally Hann tapered); the displacement of each window is the peak of the circular
    cross-correlation, refined by a 3-point Gaussian fit along each axis; the window
    displacements are interpolated bilinearly to every pixel.
    """
    H, W = ref.shape
    n = int(corr_window)
    s = int(corr_step)
    if H < n or W < n:
        raise ValueError(f"image {W}x{H} smaller than the correlation window {n}")
    r0 = np.arange(0, H - n + 1, s)
    c0 = np.arange(0, W - n + 1, s)
    sw_r = np.lib.stride_tricks.sliding_window_view(ref, (n, n))[::s, ::s]
    sw_f = np.lib.stride_tricks.sliding_window_view(frame, (n, n))[::s, ::s]
    hann = np.hanning(n + 2)[1:-1] if corr_taper else np.ones(n)
    taper = np.outer(hann, hann).astype(np.float32)
    nr, nc = sw_r.shape[:2]
    U = np.zeros((nr, nc), np.float32)
    V = np.zeros((nr, nc), np.float32)
    k = np.arange(nc)
    for i in range(nr):  # one batched FFT per row of windows
        a = sw_f[i] - sw_f[i].mean(axis=(1, 2), keepdims=True)
        b = sw_r[i] - sw_r[i].mean(axis=(1, 2), keepdims=True)
        A = np.fft.rfft2(a * taper)
        B = np.fft.rfft2(b * taper)
        # c(s) = sum_p f(p) r(p + s): peak at s = delta (frame(p) = ref(p + delta))
        c = np.fft.fftshift(np.fft.irfft2(np.conj(A) * B, s=(n, n)), axes=(1, 2))
        flat = c.reshape(nc, -1).argmax(axis=1)
        pr, pc = np.unravel_index(flat, (n, n))
        pr = np.clip(pr, 1, n - 2)
        pc = np.clip(pc, 1, n - 2)
        cmax = c[k, pr, pc]
        # a window without a positive peak (textureless, or all anti-correlated) gets no
        # sub-pixel fit: the log of a non-positive floor was NaN
        peak = cmax > 0
        floor = np.where(peak, cmax * 1e-3, 1.0)

        def lg(x):
            return np.log(np.maximum(x, floor))

        def fit(lm, l0, lp):
            den = 2.0 * (lm - 2.0 * l0 + lp)
            ok = peak & (den < -1e-12)
            return np.where(ok, (lm - lp) / np.where(ok, den, -1.0), 0.0)

        l0 = lg(cmax)
        dv = fit(lg(c[k, pr - 1, pc]), l0, lg(c[k, pr + 1, pc]))
        du = fit(lg(c[k, pr, pc - 1]), l0, lg(c[k, pr, pc + 1]))
        V[i] = pr - n // 2 + np.clip(dv, -1, 1)
        U[i] = pc - n // 2 + np.clip(du, -1, 1)
    # window centres at r0 + (n - 1) / 2; interpolate to every pixel
    rc = r0 + (n - 1) / 2.0
    cc = c0 + (n - 1) / 2.0
    ir = np.interp(np.arange(H), rc, np.arange(nr)).astype(np.float32)
    ic = np.interp(np.arange(W), cc, np.arange(nc)).astype(np.float32)
    mapx, mapy = np.meshgrid(ic, ir)
    u = cv2.remap(U, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    v = cv2.remap(V, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return u, v
