"""The background's motion against the reference as a small parametric map, and its fit
to a flow field.

A camera that moves (or a background that moves) between the reference and a frame adds
the same smooth displacement to every deflection of the frame (paper sec. 4: the flow
measures ``frame(p) ~= reference(p + delta)``). For sub-pixel motions of a camera in
front of a plane it is a homography of the image; a shift, a rotation about the optical
axis and a zoom make it affine. The parameter vector (:data:`MOTION_PARAMS`) is the
same for every model (the terms a model lacks stay 0), in image pixels about the image
centre ``c = ((W - 1) / 2, (H - 1) / 2)``, with ``q = p - c``::

    T(q) = (A q + t) / (1 + g q_x + h q_y),   A = I + [[a, b], [c, d]],   t = (u, v)
    motion(p) = T(q) - q

so ``(u, v)`` is the displacement at the image centre, ``(c - b) / 2`` the rotation
(radians, image x towards image y) and ``(a + d) / 2`` the relative change of scale.
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline.flow.images import nonfinite_cells
from schlieren.pipeline.geometry import FlowGrid

__all__ = ["MOTION_PARAMS", "motion_size", "no_motion", "motion_displacement", "motion_field",
           "motion_extent", "motion_summary", "fit_flow_motion"]

#: Entries of a motion vector (``background_motion``'s last axis).
MOTION_PARAMS = ("u", "v", "a", "b", "c", "d", "g", "h")

_SIZES = {"none": 0, "translation": 2, "affine": 6, "homography": 8}


def motion_size(model: str) -> int:
    """Free entries of :data:`MOTION_PARAMS` of a model (the first ``n``)."""
    try:
        return _SIZES[model]
    except KeyError:
        raise ValueError(f"unknown motion model {model!r}; use one of {tuple(_SIZES)}") from None


def no_motion() -> np.ndarray:
    """The motion vector of a background that did not move."""
    return np.zeros(len(MOTION_PARAMS), np.float64)


def _centre(image_size) -> tuple[float, float]:
    W, H = image_size
    return 0.5 * (W - 1), 0.5 * (H - 1)


def motion_displacement(motion, x, y, image_size) -> tuple[np.ndarray, np.ndarray]:
    """The motion's displacement (pixels) at image positions ``(x, y)`` (column, row).

    Parameters
    ----------
    motion : array_like, shape (..., 8)
        :data:`MOTION_PARAMS` (several motions broadcast against ``x`` and ``y``).
    x, y : array_like
        Image coordinates (pixel centres at integers), broadcastable.
    image_size : (int, int)
        ``(width, height)``.
    """
    u, v, a, b, c, d, g, h = np.moveaxis(np.asarray(motion, np.float64), -1, 0)[:8]
    cx, cy = _centre(image_size)
    qx = np.asarray(x, np.float64) - cx
    qy = np.asarray(y, np.float64) - cy
    den = 1.0 + g * qx + h * qy
    tx = ((1.0 + a) * qx + b * qy + u) / den
    ty = (c * qx + (1.0 + d) * qy + v) / den
    return tx - qx, ty - qy


def motion_field(motion, image_size, factor: int = 1) -> np.ndarray:
    """The motion's displacement at the centres of the flow grid's cells.

    Returns
    -------
    field : ndarray, shape (H // factor, W // factor, 2), float32
        Component 0 = u (columns), 1 = v (rows), like a flow; for an affine motion the
        cell centre's value is also the cell's mean.
    """
    centres = FlowGrid(tuple(image_size), int(factor)).pixel_centres()
    dx, dy = motion_displacement(motion, centres[..., 0], centres[..., 1], image_size)
    return np.stack([dx, dy], axis=-1).astype(np.float32)


def motion_extent(motion, image_size) -> float:
    """The largest displacement (pixels) the motion gives a pixel of the image (the
    largest of the image's corners and centre)."""
    W, H = image_size
    x = np.array([0.0, W - 1.0, 0.0, W - 1.0, 0.5 * (W - 1)])
    y = np.array([0.0, 0.0, H - 1.0, H - 1.0, 0.5 * (H - 1)])
    dx, dy = motion_displacement(motion, x, y, image_size)
    return float(np.max(np.hypot(dx, dy)))


def motion_summary(motion, image_size) -> dict:
    """Readable terms of a motion vector: ``u``, ``v`` (pixels at the image centre),
    ``rotation`` (radians), ``scale`` (relative change) and ``extent`` (:func:`motion_extent`)."""
    m = np.asarray(motion, np.float64).ravel()
    return {"u": float(m[0]), "v": float(m[1]), "rotation": float(0.5 * (m[4] - m[3])),
            "scale": float(0.5 * (m[2] + m[5])), "extent": motion_extent(m, image_size)}


def _design(qx: np.ndarray, qy: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the linearised displacement (x and y components) in the first ``n`` entries
    of :data:`MOTION_PARAMS`, at centred positions ``q`` (exact for n <= 6)."""
    one, zero = np.ones_like(qx), np.zeros_like(qx)
    # the projective terms to first order: q_x (1 - g q_x - h q_y), q_y (1 - g q_x - h q_y)
    jx = np.stack([one, zero, qx, qy, zero, zero, -qx * qx, -qx * qy], axis=-1)[:, :n]
    jy = np.stack([zero, one, zero, zero, qx, qy, -qx * qy, -qy * qy], axis=-1)[:, :n]
    return jx, jy


def fit_flow_motion(flow: np.ndarray, cells: np.ndarray, image_size, factor: int, *, model: str = "affine",
                    iterations: int = 10, tukey: float = 4.685) -> tuple[np.ndarray, dict]:
    """Robust fit of a motion to a flow field on the cells where it should be zero.

    Iteratively reweighted least squares with Tukey's biweight on the vector residual's
    length (scale: 1.4826 x its median), started from ordinary least squares: the cells of
    a plume that leaks into ``cells`` (deflections several times the flow's noise) get
    weight 0, while every cell of the background counts; no random sampling (the result
    is deterministic), and the linear model has one minimum near the least-squares start.

    Parameters
    ----------
    flow : ndarray, shape (h, w, 2)
        Deflections on the flow grid (NaN cells are ignored).
    cells : ndarray, shape (h, w), bool
        Cells to fit on.
    image_size : (int, int)
        ``(width, height)`` of the image.
    factor : int
        Image pixels per flow cell.
    model : str
        ``translation``, ``affine`` or ``homography`` (its projective terms linearised).

    Returns
    -------
    motion : ndarray, shape (8,)
        :data:`MOTION_PARAMS` (zeros where the fit was impossible).
    info : dict
        ``cells`` (cells with weight), ``rms`` (weighted residual RMS, pixels).
    """
    n = motion_size(model)
    out = no_motion()
    rows, cols = np.nonzero(cells)
    vals = flow[rows, cols]  # (m, 2), the cells' deflections only
    fin = ~nonfinite_cells(vals)
    if not fin.all():
        rows, cols, vals = rows[fin], cols[fin], vals[fin]
    if n == 0 or len(rows) < 2 * n:
        return out, {"cells": 0, "rms": float("nan")}
    cx, cy = _centre(image_size)
    f = int(factor)  # the cells' centres (FlowGrid.pixel_centres)
    qx = f * cols.astype(np.float64) + (f - 1) / 2.0 - cx
    qy = f * rows.astype(np.float64) + (f - 1) / 2.0 - cy
    s = max(float(np.max(np.abs(qx))), float(np.max(np.abs(qy))), 1.0)
    jx, jy = _design(qx / s, qy / s, n)
    J = np.concatenate([jx, jy])
    y = np.concatenate([vals[:, 0], vals[:, 1]]).astype(np.float64)
    w = np.ones(len(qx))
    theta = np.zeros(n)
    for _ in range(iterations):
        ww = np.concatenate([w, w])
        A = J.T @ (J * ww[:, None])
        rhs = J.T @ (ww * y)
        try:
            new = np.linalg.solve(A + 1e-12 * np.trace(A) / n * np.eye(n), rhs)
        except np.linalg.LinAlgError:
            break
        done = np.allclose(new, theta, rtol=0, atol=1e-7)
        theta = new
        r = y - J @ theta
        rr = np.hypot(r[:len(qx)], r[len(qx):])
        scale = 1.4826 * float(np.median(rr))
        if scale <= 0:
            break
        z = rr / (tukey * scale)
        w = np.where(z < 1, (1 - z * z) ** 2, 0.0)
        if done:
            break
    # back to per-pixel units: linear terms / s, projective terms / s^2
    units = np.array([1.0, 1.0, s, s, s, s, s * s, s * s])[:n]
    out[:n] = theta / units
    r = y - J @ theta
    rr = np.hypot(r[:len(qx)], r[len(qx):])
    rms = float(np.sqrt(np.sum(w * rr * rr) / max(np.sum(w), 1e-12)))
    return out, {"cells": int(np.count_nonzero(w > 0)), "rms": rms}
