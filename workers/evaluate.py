"""Accuracy of a result store against synthetic ground truth (``schlieren evaluate``).

Glue: files are read by :mod:`schlieren.storage.synthetic_io`, the metric is
:mod:`schlieren.pipeline.metrics` (SPEC section 4). For each store frame the truth is
taken at the store's time: directly from ``refractivity`` when the time matches an output
instant, otherwise linearly interpolated between the phantom's ``knot_refractivity``
samples (exact: the phantom is piecewise linear in time); then trilinearly resampled to
the store's grid.
"""

from __future__ import annotations

import logging

import numpy as np

from schlieren.pipeline import metrics
from schlieren.storage import synthetic_io as sio

__all__ = ["evaluate"]

log = logging.getLogger(__name__)


def _truth_at(truth: sio.Truth, t: float) -> tuple[np.ndarray, str]:
    i0, i1, w = metrics.time_bracket(truth.time, t)
    if w == 0.0 and abs(truth.time[i0] - t) <= 1e-9:
        return np.asarray(truth.refractivity[i0], dtype=np.float64), "frame"
    i0, i1, w = metrics.time_bracket(truth.knot_time, t)
    v = np.asarray(truth.knot_refractivity[i0], dtype=np.float64)
    if w:
        v = (1.0 - w) * v + w * np.asarray(truth.knot_refractivity[i1], dtype=np.float64)
    return v, "knots"


def _r_ambient(truth: sio.Truth) -> float:
    """Ambient refractivity of a truth: its attribute, else the most common value (ambient air)."""
    r = truth.attrs.get("r_ambient") if hasattr(truth, "attrs") else None
    if r is not None:
        return float(r)
    v = np.asarray(truth.refractivity[0], dtype=np.float64).ravel()
    vals, counts = np.unique(v, return_counts=True)
    return float(vals[np.argmax(counts)])


def evaluate(store_path, truth_path) -> dict:
    """Per-frame and overall relative RMS / PSNR of the store's ``refractivity``, whole box and in plume.

    Returns
    -------
    dict
        ``{"frames": [{"frame", "time", "rms", "psnr", "rms_plume", "psnr_plume", "peak_ratio",
        "truth_from"}...], "overall": {"rms", "psnr", "mean_psnr", "frames"}, "plume": {the same
        for the in-plume RMS}, "r_ambient", "store": str, "truth": str}``; ``frame`` is the capture
        frame index (the store's ``frame`` coordinate, as in every command). Frames whose estimate
        is not (fully) computed (NaN) are listed with ``rms = nan`` and left out of the overall
        figures. The in-plume RMS (docs/store.md) is taken over the voxels where
        ``|truth - r_ambient| > 1 %`` of the truth's range, normalised by that whole-box range.
    """
    truth = sio.read_truth(truth_path)
    est, times, origin, vs = sio.read_store_refractivity(store_path)
    labels = sio.read_store_frames(store_path)
    shape = tuple(est.shape[1:])
    target = metrics.grid_from_attrs(origin, vs, shape)
    tgrid = metrics.grid_from_attrs(truth.grid_origin, truth.voxel_size, tuple(truth.refractivity.shape[1:]))
    span = (truth.knot_time.min(), truth.knot_time.max())
    moving = truth.knot_time.size > 1   # a static phantom (one knot) is valid at any time
    r_amb = _r_ambient(truth)
    nan = float("nan")
    rows = []
    for k, t in enumerate(times):
        e = np.asarray(est[k], dtype=np.float64)
        if not np.isfinite(t) or not np.all(np.isfinite(e)):
            rows.append({"frame": int(labels[k]), "time": float(t), "rms": nan, "psnr": nan, "rms_plume": nan,
                         "psnr_plume": nan, "peak_ratio": nan, "truth_from": "missing"})
            continue
        if moving and (t < span[0] - 1e-9 or t > span[1] + 1e-9):
            log.warning("frame %d at t=%.6f s is outside the truth's span; using the nearest truth", labels[k], t)
        tv, src = _truth_at(truth, float(t))
        tv = metrics.resample_space(tv, tgrid, target)
        rms = metrics.relative_rms(e, tv)
        rp = metrics.plume_rms(e, tv, r_amb)
        rows.append({"frame": int(labels[k]), "time": float(t), "rms": rms, "psnr": metrics.psnr(rms), "rms_plume": rp,
                     "psnr_plume": metrics.psnr(rp) if np.isfinite(rp) else nan,
                     "peak_ratio": metrics.peak_ratio(e, tv, r_amb), "truth_from": src})
    return {"store": str(store_path), "truth": str(truth_path), "frames": rows, "r_ambient": r_amb,
            "overall": metrics.summarise([r["rms"] for r in rows]),
            "plume": metrics.summarise([r["rms_plume"] for r in rows])}
