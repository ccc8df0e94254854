"""Accuracy metric against ground truth (SPEC section 4; paper sec. 6, Table 1).

Relative RMS error of the refractivity over the whole box, normalised by the truth's
range in that frame, and ``PSNR = 20 log10(1 / RMS)``. Truth on its own grid and time
samples is resampled to the estimate's grid (trilinear) and times (linear).

Ambient voxels dominate the whole box (a constant-ambient guess already scores well
there; docs/tuning.md, "Metric"), so the *in-plume* figure is reported beside it: the same RMS, still normalised by the
truth's range over the whole box, over the voxels where ``|truth - r_ambient|`` exceeds
1 % of that range (:func:`plume_mask`).

For the flow: the mean end-point error against a known deflection field
(:func:`endpoint_error`, pixels).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from schlieren.pipeline.geometry import Grid

__all__ = ["relative_rms", "plume_mask", "plume_rms", "peak_ratio", "psnr", "grid_from_attrs", "resample_space", "time_bracket", "resample_truth",
           "summarise", "endpoint_error"]


def relative_rms(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Relative RMS error ``sqrt(mean((estimate - truth)^2)) / (max(truth) - min(truth))``.

    Parameters
    ----------
    estimate, truth : ndarray, same shape (one frame, e.g. (nz, ny, nx))

    Returns
    -------
    float
        0 for identical arrays; ``inf`` when the truth is constant but the estimate differs.
    """
    e = np.asarray(estimate, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if e.shape != t.shape:
        raise ValueError(f"shapes differ: {e.shape} vs {t.shape}")
    err = np.sqrt(np.mean((e - t) ** 2))
    rng = float(t.max() - t.min())
    if err == 0.0:
        return 0.0
    if rng == 0.0:
        return float("inf")
    return float(err / rng)


def plume_mask(truth: np.ndarray, r_ambient: float, *, fraction: float = 0.01) -> np.ndarray:
    """Voxels of the plume: ``|truth - r_ambient| > fraction * (max(truth) - min(truth))``."""
    t = np.asarray(truth, dtype=np.float64)
    return np.abs(t - r_ambient) > fraction * float(t.max() - t.min())


def plume_rms(estimate: np.ndarray, truth: np.ndarray, r_ambient: float, *, fraction: float = 0.01) -> float:
    """Relative RMS over the plume (:func:`plume_mask`), normalised by the truth's whole-box range.

    Returns ``nan`` when the truth has no plume voxel.
    """
    e = np.asarray(estimate, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if e.shape != t.shape:
        raise ValueError(f"shapes differ: {e.shape} vs {t.shape}")
    m = plume_mask(t, r_ambient, fraction=fraction)
    if not m.any():
        return float("nan")
    return float(np.sqrt(np.mean((e[m] - t[m]) ** 2)) / float(t.max() - t.min()))


def peak_ratio(estimate: np.ndarray, truth: np.ndarray, r_ambient: float) -> float:
    """Largest excursion from ambient of the estimate over the truth's (1 = the peak is recovered)."""
    e = np.abs(np.asarray(estimate, dtype=np.float64) - r_ambient).max()
    t = np.abs(np.asarray(truth, dtype=np.float64) - r_ambient).max()
    return float(e / t) if t > 0 else float("nan")


def psnr(rms: float) -> float:
    """Peak signal-to-noise ratio ``20 log10(1 / rms)`` in dB (``inf`` for ``rms == 0``)."""
    if rms == 0.0:
        return float("inf")
    return float(20.0 * np.log10(1.0 / rms))


def grid_from_attrs(origin, voxel_size, shape) -> Grid:
    """The :class:`Grid` whose voxel [0, 0, 0] centre is ``origin`` (x, y, z), with ``shape`` (nz, ny, nx)."""
    o = np.asarray(origin, dtype=np.float64)
    h = float(np.ravel(voxel_size)[0])
    nz, ny, nx = shape
    vmin = o - 0.5 * h
    vmax = vmin + h * np.array([nx, ny, nz], dtype=np.float64)
    return Grid(tuple(vmin), tuple(vmax), h)


def resample_space(volume: np.ndarray, src: Grid, dst: Grid, *, snap: float = 1e-6) -> np.ndarray:
    """Trilinear resampling of a volume from grid ``src`` to the voxel centres of ``dst``.

    Points outside ``src``'s voxel centres take the nearest edge value. Target centres that
    coincide with source centres (within ``snap`` voxels) reproduce the source exactly.

    Parameters
    ----------
    volume : ndarray, shape src.shape (nz, ny, nx)
    src, dst : Grid

    Returns
    -------
    ndarray, shape dst.shape, float64
    """
    vol = np.asarray(volume, dtype=np.float64)
    if vol.shape != src.shape:
        raise ValueError(f"volume shape {vol.shape} != grid shape {src.shape}")
    coords = []
    for ax_dst, ax_src in zip(dst.axes()[::-1], src.axes()[::-1]):   # z, y, x
        c = (ax_dst - ax_src[0]) / src.voxel_size
        r = np.rint(c)
        c = np.where(np.abs(c - r) < snap, r, c)
        coords.append(c)
    if all(np.array_equal(c, np.arange(n)) for c, n in zip(coords, src.shape)):
        return vol.copy()
    cz, cy, cx = np.meshgrid(*coords, indexing="ij")
    return ndimage.map_coordinates(vol, np.stack([cz, cy, cx]), order=1, mode="nearest")


def time_bracket(times: np.ndarray, t: float, *, snap: float = 1e-9) -> tuple[int, int, float]:
    """Indices ``(i0, i1)`` and weight ``w`` of ``i1`` for linear interpolation at ``t``.

    ``times`` is increasing; outside its span the nearest end is used. A time within
    ``snap`` seconds of a sample returns that sample with ``w = 0``.
    """
    ts = np.asarray(times, dtype=np.float64)
    j = int(np.argmin(np.abs(ts - t)))
    if abs(ts[j] - t) <= snap or ts.size == 1:
        return j, j, 0.0
    if t <= ts[0]:
        return 0, 0, 0.0
    if t >= ts[-1]:
        return ts.size - 1, ts.size - 1, 0.0
    i1 = int(np.searchsorted(ts, t, side="right"))
    i0 = i1 - 1
    return i0, i1, float((t - ts[i0]) / (ts[i1] - ts[i0]))


def resample_truth(truth: np.ndarray, truth_grid: Grid, truth_times: np.ndarray, target_grid: Grid,
                   target_times: np.ndarray) -> np.ndarray:
    """Truth at the target grid and times: linear in time, trilinear in space.

    Parameters
    ----------
    truth : ndarray, shape (T, nz, ny, nx)
    truth_grid : Grid
    truth_times : ndarray, shape (T,)
    target_grid : Grid
    target_times : ndarray, shape (F,)

    Returns
    -------
    ndarray, shape (F,) + target_grid.shape
    """
    out = np.empty((len(target_times),) + tuple(target_grid.shape))
    for k, t in enumerate(np.asarray(target_times, dtype=np.float64)):
        i0, i1, w = time_bracket(truth_times, float(t))
        v = np.asarray(truth[i0], dtype=np.float64)
        if w:
            v = (1.0 - w) * v + w * np.asarray(truth[i1], dtype=np.float64)
        out[k] = resample_space(v, truth_grid, target_grid)
    return out


def summarise(per_frame_rms: list[float]) -> dict:
    """Overall figures from per-frame relative RMS: RMS over frames of the per-frame RMS and its PSNR."""
    r = np.asarray([x for x in per_frame_rms if np.isfinite(x)], dtype=np.float64)
    if r.size == 0:
        return {"rms": float("nan"), "psnr": float("nan"), "frames": 0}
    overall = float(np.sqrt(np.mean(r**2)))
    return {"rms": overall, "psnr": psnr(overall), "frames": int(r.size),
            "mean_psnr": float(np.mean([psnr(x) for x in r]))}


def endpoint_error(flow: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean end-point error ``mean |flow - truth|`` (pixels), optionally inside ``mask``."""
    d = np.linalg.norm(np.asarray(flow, np.float64) - np.asarray(truth, np.float64), axis=-1)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(d.mean()) if d.size else float("nan")
