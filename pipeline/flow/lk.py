"""Dense Lucas-Kanade on one pyramid level (paper sec. 4: the method of choice on BOS
data), with its variants: the per-pixel window by the intersection of confidence
intervals (ICI), the finest level solved once per flow cell, and the first-order bias of
the window mean (:func:`_texture_bias`) that :func:`~.stage.deflection_stage` subtracts.
"""

from __future__ import annotations

import cv2
import numpy as np

from ._kernels import (_block_moments_kernel, _ici_kernel, _lk_residual_grad_kernel, _lk_residual_kernel,
                       _lk_solve_kernel, _texture_bias_kernel, _warp_kernel)
from .images import _gradients
from .windows import _block_window_linear_taps, _block_window_taps, _cell_window_sums, _window_filter, _window_taps

__all__ = ["ici_windows"]


def _lk_level(coef, frame, u, v, *, window, window_type, iterations, regularisation,
              gradient, keep=None, weight=None, ici=None, cells=0, **_):
    """Dense Lucas-Kanade on one level, warping the reference at every iteration.

    Each pixel ``q`` of the window of ``p`` is linearised around its own current warp:
    ``ref(q + d_p) ~= ref(q + d_q) + g_q . (d_p - d_q)``, so the window normal equations
    give ``d_p = T_p^-1 sum_q w g_q (frame_q - ref(q + d_q) + g_q . d_q)``. In the linear
    regime one step returns the window-weighted true displacement (no oscillation between
    neighbouring pixels, unlike the naive incremental dense update); the iterations
    remove the linearisation error. ``g`` is the frame gradient (fixed, so the structure
    tensor is filtered once per level); the fixed point does not depend on it.
    The fixed point is the structure-tensor weighted window mean
    ``T_p^-1 sum_q w g_q g_q^T d_q`` of the true displacement (corrected to first order by
    :func:`_texture_bias`). ``keep`` (a dict) receives the level's gradients. ``weight``
    (0/1 per pixel) removes invalid pixels from every window sum (their gradient is
    zeroed, so they add neither to the structure tensor nor to the mismatch).
    ``cells`` = f > 1 (frame gradient, no ICI): solve on the f x f flow cells instead of
    every pixel and return the flow on the cell grid (:func:`_lk_cells`).
    """
    taps = _window_taps(window, window_type)
    gx, gy = _gradients(frame)
    if weight is not None:
        gx *= weight
        gy *= weight
    if cells > 1 and gradient == "frame" and ici is None:
        return _lk_cells(coef, frame, gx, gy, u, v, window=window, window_type=window_type,
                         iterations=iterations, regularisation=regularisation, f=int(cells), keep=keep)
    if gradient != "frame":
        mix = np.float32(0.5 if gradient == "symmetric" else 1.0)
        g = (np.empty_like(frame), np.empty_like(frame))
        ex = np.empty_like(frame)
        ey = np.empty_like(frame)
        for _ in range(iterations):
            _lk_residual_grad_kernel(coef, frame, gx, gy, u, v, mix, g[0], g[1], ex, ey)
            if weight is not None:
                for a in (g[0], g[1], ex, ey):
                    a *= weight
            sxx = _window_filter(g[0] * g[0], taps)
            sxy = _window_filter(g[0] * g[1], taps)
            syy = _window_filter(g[1] * g[1], taps)
            lam = np.float32(regularisation * 0.5 * (float(sxx[::4, ::4].mean())
                                                     + float(syy[::4, ::4].mean())))
            _lk_solve_kernel(sxx, sxy, syy, lam, _window_filter(ex, taps),
                             _window_filter(ey, taps), u, v)
        if keep is not None:
            keep["gx"], keep["gy"] = g
        return u, v
    if keep is not None:
        keep["gx"], keep["gy"] = gx, gy
    sxx = _window_filter(gx * gx, taps)
    sxy = _window_filter(gx * gy, taps)
    syy = _window_filter(gy * gy, taps)
    lam = np.float32(regularisation * 0.5 * (float(sxx[::4, ::4].mean()) + float(syy[::4, ::4].mean())))
    ex = np.empty_like(frame)
    ey = np.empty_like(frame)
    for _ in range(iterations):
        _lk_residual_kernel(coef, frame, gx, gy, u, v, ex, ey)
        bx = _window_filter(ex, taps)
        by = _window_filter(ey, taps)
        _lk_solve_kernel(sxx, sxy, syy, lam, bx, by, u, v)
    if ici is not None:
        u, v = _lk_ici(coef, frame, gx, gy, u, v, window_type=window_type, regularisation=regularisation, **ici)
    return u, v


def ici_windows(smallest: int, largest: int, ratio: float = 1.4) -> tuple[int, ...]:
    """Odd window edges from ``smallest`` to ``largest``, growing by about ``ratio``."""
    out = [int(smallest) | 1]
    while out[-1] < largest:
        nxt = max(int(round(out[-1] * ratio)) | 1, out[-1] + 2)
        out.append(min(nxt, int(largest) | 1))
    return tuple(out)


def _lk_ici(coef, frame, gx, gy, u, v, *, windows, window_type, regularisation, gamma, info=None):
    """Per-pixel LK window by the intersection of confidence intervals (ICI).

    Around the converged pilot estimate ``(u, v)``, one more LK step is taken with every
    window of ``windows`` (small to large, sharing the linearisation), each with its
    variance ``sigma^2 (T + lam)^-1 M (T + lam)^-1`` (``M`` the structure tensor filtered
    with the squared window weights, ``sigma`` the image noise: a robust scale of the
    warped residual ``frame - ref(q + d)``). A pixel takes the largest window whose
    confidence interval (``gamma`` standard deviations) still meets those of all smaller
    windows: large windows where the deflection is smooth (less noise), small ones where
    it has fine structure (less bias). Katkovnik, Egiazarian & Astola, *Local Approximation
    Techniques in Signal and Image Processing* (2006), applied to LK's window.

    ``info`` (a dict) receives ``noise`` (image noise, standardised units), the median
    chosen window and the median predicted flow noise (pixels of this level).
    """
    H, W = frame.shape
    ex = np.empty_like(frame)
    ey = np.empty_like(frame)
    _lk_residual_kernel(coef, frame, gx, gy, u, v, ex, ey)
    warped = np.empty_like(frame)
    _warp_kernel(coef, u, v, warped)
    res = (frame - warped)[::2, ::2]
    keep_px = (gx[::2, ::2] != 0) | (gy[::2, ::2] != 0)   # invalid pixels have zeroed gradients
    res = res[keep_px] if keep_px.any() else res.ravel()
    noise = float(1.4826 * np.median(np.abs(res - np.median(res))))
    s2 = np.float32(max(noise, 1e-6) ** 2)
    gxx, gxy, gyy = gx * gx, gx * gy, gy * gy
    lo = np.full((H, W, 2), -np.inf, np.float32)
    hi = np.full((H, W, 2), np.inf, np.float32)
    alive = np.ones((H, W), np.bool_)
    chosen = np.zeros((H, W), np.int16)
    sd = np.zeros((H, W), np.float32)
    uu = u.copy()
    vv = v.copy()
    for code, w in enumerate(windows):
        taps = _window_taps(w, window_type)
        t2 = (taps * taps).astype(np.float32)
        sxx = _window_filter(gxx, taps)
        sxy = _window_filter(gxy, taps)
        syy = _window_filter(gyy, taps)
        lam = np.float32(regularisation * 0.5 * (float(sxx[::4, ::4].mean()) + float(syy[::4, ::4].mean())))
        _ici_kernel(sxx, sxy, syy, lam, _window_filter(ex, taps), _window_filter(ey, taps),
                    _window_filter(gxx, t2), _window_filter(gxy, t2), _window_filter(gyy, t2), s2,
                    np.float32(gamma), code, lo, hi, alive, uu, vv, chosen, sd)
    if info is not None:
        info["noise"] = noise
        info["window_median"] = int(np.asarray(windows)[int(np.median(chosen[::2, ::2]))])
        info["window_fraction"] = {int(w): float(np.mean(chosen[::2, ::2] == i)) for i, w in enumerate(windows)}
        info["flow_noise_px"] = float(np.median(sd[::2, ::2]))
    return uu, vv


def _lk_cells(coef, frame, gx, gy, u, v, *, window, window_type, iterations, regularisation, f, keep=None):
    """The finest LK level solved once per f x f flow cell (the flow grid of sec. 4).

    :func:`_lk_level` solves ``d_p = T_p^-1 b_p`` at every pixel (window sums of
    ``g g^T`` and of ``g (frame - ref(q + d_q) + g . d_q)``), and the deflection stage then
    averages the f x f pixels of each flow cell. Here the window sums are taken once per
    cell, around its centre: the per-pixel products are summed over each cell with their
    first moments (offsets from the cell's centre; exact), and the window is applied on
    the cell grid as a line in the pixel's offset inside each cell
    (:func:`_block_window_linear_taps`: ``sum_q w g e ~ sum_k A_k S_k + B_k (X_k + Y_k)``,
    separably), then ``d_cell = T_cell^-1 b_cell``: LK at the cell's centre with the
    window to first order inside each cell. The full-resolution work drops from five
    window filters and a solve to one pass of block moments: the window filtering runs on
    f^2 times fewer points with f times fewer taps. The line, not the window held
    constant over each cell (the block mean of the weights alone, a staircase), because
    the staircase's flow is measurably worse (docs/tuning.md, "LK solved per flow cell").
    ``u``, ``v`` (H, W) are the per-pixel warps of the residual
    (the coarser level's flow); the result is (rows, cols) = (H // f, W // f). ``keep``
    receives ``gx``, ``gy``, the block moments ``mom`` and the window sums ``T`` of
    ``g g^T`` (reused by :func:`_texture_bias`).

    The coarser pyramid levels, which only initialise the finest, are solved on f x f
    cells of their own pixels too (:func:`_pyramid_flow`; their cell flow is interpolated
    back to their pixels before it is prolonged): cheaper than per-pixel coarse levels and
    no less accurate where the window spans several cells; ``cell_solve: auto`` keeps
    narrow windows per pixel (measurements: docs/tuning.md, "LK solved per flow cell").
    """
    H, W = frame.shape
    rows, cols = H // f, W // f
    mom = np.empty((3, rows, cols, 3), np.float32)
    _block_moments_kernel(gx, gy, f, mom)
    if keep is not None:
        keep["gx"], keep["gy"], keep["mom"] = gx, gy, mom
    A, B = _block_window_linear_taps(window, window_type, f)
    T = _cell_window_sums(mom, A, B)
    if keep is not None:
        keep["T"] = T
    sxx = np.ascontiguousarray(T[..., 0])
    sxy = np.ascontiguousarray(T[..., 1])
    syy = np.ascontiguousarray(T[..., 2])
    lam = np.float32(regularisation * 0.5 * (float(sxx.mean()) + float(syy.mean())))
    ex = np.empty_like(frame)
    ey = np.empty_like(frame)
    uc = np.empty((rows, cols), np.float32)
    vc = np.empty((rows, cols), np.float32)
    e2 = np.empty((3, rows, cols, 2), np.float32)
    for it in range(iterations):
        if it:  # later iterations warp every pixel by its cell's flow (bilinear)
            u, v = _upsample_cells(uc, vc, f, (H, W))
        _lk_residual_kernel(coef, frame, gx, gy, u, v, ex, ey)
        _block_moments_kernel(ex, ey, f, e2)
        b = _cell_window_sums(e2, A, B)
        _lk_solve_kernel(sxx, sxy, syy, lam, np.ascontiguousarray(b[..., 0]),
                         np.ascontiguousarray(b[..., 1]), uc, vc)
    return uc, vc


def _upsample_cells(uc: np.ndarray, vc: np.ndarray, f: int, shape: tuple[int, int]):
    """Per-pixel flow from the cell grid: cell (i, j) is centred on pixel
    ``(f i + (f - 1) / 2, f j + (f - 1) / 2)``; bilinear, edges replicated."""
    H, W = shape
    c = (f - 1) / 2.0
    M = np.array([[1.0 / f, 0.0, -c / f], [0.0, 1.0 / f, -c / f]], np.float64)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return (cv2.warpAffine(uc, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE),
            cv2.warpAffine(vc, M, (W, H), flags=flags, borderMode=cv2.BORDER_REPLICATE))


def _texture_bias(gx: np.ndarray, gy: np.ndarray, u: np.ndarray, v: np.ndarray, *,
                  window: int, window_type: str, factor: int, mom: np.ndarray | None = None,
                  linear: bool = False, T: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First-order bias of the LK window mean on the flow grid, to subtract from ``(u, v)``.

    The LK displacement of pixel ``p`` is ``T_p^-1 sum_q w(q - p) g_q g_q^T d(q)`` (see
    :func:`_lk_level`). With ``d(q) ~= d(p) + J (q - p)`` this is
    ``d(p) + T_p^-1 (S_x J[:, 0] + S_y J[:, 1])``, ``S_k = sum_q w(q - p) (q - p)_k g_q g_q^T``:
    the texture's weighted centroid is not the window centre, so wherever the deflection
    varies (``J != 0``) the window mean is shifted by a random, texture-dependent amount.
    ``T`` and ``S_k`` are evaluated at the flow-grid cell centres from per-block gradient
    moments (exact block sums; the window is taken constant inside a block, or with
    ``linear`` as the line :func:`_lk_cells` uses), ``J`` from the flow grid smoothed
    with ``sigma = window / 4`` full-resolution pixels.

    Parameters
    ----------
    gx, gy : ndarray, shape (H, W)
        Frame gradients of the finest LK level.
    u, v : ndarray, shape (rows, cols)
        LK flow on the flow grid (pixels).
    mom : ndarray, shape (3, rows, cols, 3), optional
        The block moments of ``g g^T`` (computed here when not given).
    linear : bool
        The flow comes from :func:`_lk_cells`: model its window, linear inside each cell,
        rather than constant per block (the matched model; docs/tuning.md, "LK solved per
        flow cell").
    T : ndarray, shape (rows, cols, 3), optional
        With ``linear``: the window sums of ``g g^T`` that :func:`_lk_cells` solved with
        (computed here when not given).

    Returns
    -------
    bu, bv : ndarray, shape (rows, cols), float32
        Bias in pixels.
    """
    f = int(factor)
    rows, cols = u.shape
    if mom is None:  # (:func:`_lk_cells` hands over the moments it computed)
        mom = np.empty((3, rows, cols, 3), np.float32)
        _block_moments_kernel(gx, gy, f, mom)
    kt = _block_window_taps(window, window_type, f)
    K = (len(kt) - 1) // 2
    km = kt * (f * np.arange(-K, K + 1)).astype(np.float32)

    def filt(a, kx, ky):  # correlation: out(p) = sum_k kx[k] ky[l] a(p + (k - K, l - K))
        return cv2.sepFilter2D(a, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REFLECT)

    if linear:
        # the window of :func:`_lk_cells`: w(f k + rho) ~ A_k + B_k rho per axis. With the
        # pixel offset f k + rho, sum w (q - p)_x g g^T ~ (f k A_k + B_k (f^2 - 1) / 12) (x) A
        # on the block sums + (A_k + f k B_k) (x) A on the x-moments + f k A_k (x) B on the
        # y-moments (the texture taken even inside a block for the second moment)
        A, B = _block_window_linear_taps(window, window_type, f)
        fk = (f * np.arange(-K, K + 1)).astype(np.float32)
        k1 = fk * A + B * np.float32((f * f - 1) / 12.0)
        k2 = A + fk * B
        if T is None:
            T = _cell_window_sums(mom, A, B)
        Sx = filt(mom[0], k1, A) + filt(mom[1], k2, A) + filt(mom[2], fk * A, B)
        Sy = filt(mom[0], A, k1) + filt(mom[2], A, k2) + filt(mom[1], B, fk * A)
    else:
        T = filt(mom[0], kt, kt)  # (rows, cols, 3): xx, xy, yy
        Sx = filt(mom[0], km, kt) + filt(mom[1], kt, kt)
        Sy = filt(mom[0], kt, km) + filt(mom[2], kt, kt)
    sig = window / 4.0 / f
    flow = cv2.GaussianBlur(np.dstack([u, v]), (0, 0), sig, borderType=cv2.BORDER_REFLECT)
    bu = np.empty((rows, cols), np.float32)
    bv = np.empty((rows, cols), np.float32)
    _texture_bias_kernel(T, Sx, Sy, flow, np.float32(1.0 / f), bu, bv)
    return bu, bv
