"""Horn-Schunck (1981) optical flow on one pyramid level, with warping (paper sec. 4
compares it with Lucas-Kanade)."""

from __future__ import annotations

import cv2
import numpy as np

from ._kernels import _warp_kernel
from .images import _gradients


_HS_KERNEL = np.array([[1, 2, 1], [2, 0, 2], [1, 2, 1]], np.float32) / 12.0


def _hs_level(coef, frame, u, v, *, iterations, alpha, inner_iterations, weight=None, **_):
    """Horn-Schunck (1981) with warping: Jacobi iterations on the linearised problem
    ``min sum (e - g . (d - d0))^2 + alpha^2 |grad d|^2`` around the current warp ``d0``
    (``weight`` zeroes the data term of invalid pixels; the smoothness term fills them)."""
    gx, gy = _gradients(frame)
    if weight is not None:
        gx *= weight
        gy *= weight
    a2 = np.float32(alpha * alpha)
    denom = a2 + gx * gx + gy * gy
    warped = np.empty_like(frame)
    for _ in range(iterations):
        _warp_kernel(coef, u, v, warped)
        e = frame - warped
        u0 = u.copy()
        v0 = v.copy()
        for _ in range(inner_iterations):
            ub = cv2.filter2D(u, -1, _HS_KERNEL, borderType=cv2.BORDER_REFLECT)
            vb = cv2.filter2D(v, -1, _HS_KERNEL, borderType=cv2.BORDER_REFLECT)
            r = (e - gx * (ub - u0) - gy * (vb - v0)) / denom
            u = ub + gx * r
            v = vb + gy * r
        u = np.ascontiguousarray(u, dtype=np.float32)
        v = np.ascontiguousarray(v, dtype=np.float32)
    return u, v
