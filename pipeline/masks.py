"""Conservative 2-D flow masks from the deflection fields (paper sec. 4, Figure 4).

Thresholding ``|delta|`` fails where rays run parallel to the refractive-index gradient
(near the middle of a plume the deflection vanishes). The paper instead

1. Poisson-integrates each deflection field to a scalar potential (:func:`flow_potential`),
   which is extremal, not zero, at the plume's centre;
2. thresholds it with one threshold chosen so that a given percentile of the pixels of
   the whole sequence, all cameras, lies below it (a reduction across tasks:
   :func:`potential_summary` per camera-frame, :func:`threshold_from_summaries` over all);
3. applies a spatio-temporal dilation so that the mask is conservative (:func:`make_mask`).

Beyond the paper, :func:`make_mask` can also add the cells whose (smoothed) deflection
exceeds a small threshold: the potential threshold finds the plume's core, the
deflection its flanks (see :class:`MaskParams`).

Sign convention: the potential ``P`` solves ``grad P = -delta`` in the least-squares sense
(``delta`` in image pixels, grad in flow-grid cells). A hot plume refracts rays away from
its centre, so ``delta`` points outwards and ``P`` is *positive* in the plume (it is
proportional to the projected refractivity deficit). Its median is subtracted so that the
background is ~0; the threshold acts on ``|P|``, so dense (cold) flows with negative ``P``
are masked the same way.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import fft

from schlieren.pipeline.flow.images import nonfinite_cells
from schlieren.pipeline.params import param, parameters

__all__ = [
    "MaskParams",
    "flow_potential",
    "potential_summary",
    "sorted_quantiles",
    "threshold_from_summaries",
    "threshold_from_samples",
    "make_mask",
    "frame_evidence",
    "mask_from_evidence",
    "flow_noise",
    "static_baseline",
    "GROW_NOISE_RATIO",
]


#: :class:`MaskParams` ``grow_factor`` acts only where the noise lifts the deflection
#: criterion above this many times its floor ``deflection_threshold``: between the ratios
#: of lossless frames and of lossy video (docs/tuning.md, "Masks and hull").
GROW_NOISE_RATIO = 2.0



@parameters
class MaskParams:
    """Parameters of the mask stages (paper sec. 4; field names = keyword names of the kernels)."""

    percentile: float = param(
        95.0, unit="%", gt=0, lt=100,
        help="Percent of all camera-frame cells (whole sequence, all cameras) whose smoothed potential `|P|` "
             "lies below the mask threshold; the mask starts from the rest.")
    smooth_sigma: float = param(
        1.0, unit="flow cells", ge=0, le=100,
        help="Gaussian smoothing of the potential before thresholding.")
    dilation_radius: int = param(
        1, unit="flow cells", ge=0, le=100,
        help="Radius of the disk each mask is dilated by: the hull is carved from the dilated masks, so a "
             "tighter mask leaves fewer unknowns that the few views cannot determine.",
        tuned=True)
    temporal_radius: int = param(
        1, unit="frames", ge=0, le=10,
        help="The mask of frame `t` is the union of the thresholded frames `t - r .. t + r` (the paper's "
             "temporal dilation), which also covers for a degraded frame.",
        tuned=True)
    n_quantiles: int = param(
        2000, unit="1", ge=10, le=100000,
        help="Size of each camera-frame's summary of `|P|` (its quantiles), pooled into the sequence-wide "
             "threshold.")
    deflection_threshold: float = param(
        0.015, unit="px", ge=0, le=100,
        help="Cells whose smoothed deflection exceeds this also join the mask (0 disables): `|P|` marks the "
             "plume's core, where the deflection may vanish, the deflection its flanks.")
    flow_sigma: float = param(
        1.5, unit="flow cells", ge=0, le=100,
        help="Gaussian smoothing of the flow before the deflection criterion.")
    noise_factor: float = param(
        5.0, unit="1", ge=0, le=100,
        help="The deflection criterion is `max(deflection_threshold, noise_factor * sigma)`, `sigma` the "
             "frame's measured flow noise, so noisy captures do not mark noise as flow; 0 keeps the fixed "
             "threshold.")
    grow_factor: float = param(
        3.0, unit="1", ge=0, le=100,
        help="Hysteresis for noisy flow: cells above `max(deflection_threshold, grow_factor * sigma)` that "
             "connect to the evidence join it, where the noise lifts the criterion above `GROW_NOISE_RATIO` "
             "times `deflection_threshold` (lossy video). 0 (or at least `noise_factor`) disables it.",
        see="benchmarks/results/realistic_no_grow.md", tuned=True)
    baseline: str = param(
        "median", choices=("median", "static"),
        help="Zero of each potential: `median` subtracts the whole potential's median (the paper); `static` the "
             "quadratic surface it shows on the cells whose rays miss the volume, where a small affine bias of the "
             "flow integrates into one (lab captures, few reference frames; else the median).",
        see="benchmarks/results/realistic_labgap.md")


#: :func:`flow_potential`'s quadratic baseline needs static cells spanning at least this
#: fraction of the grid along both axes (a surface fitted on one side of the volume's image
#: would be extrapolated across it) and at least :data:`BASELINE_MIN_CELLS` of them.
BASELINE_SPAN = 0.75
BASELINE_MIN_CELLS = 100


def flow_potential(flow: np.ndarray, *, static: np.ndarray | None = None) -> np.ndarray:
    """Least-squares 2-D Poisson integration of a deflection field (paper sec. 4).

    Solves ``min_P sum_edges (P_b - P_a + <delta>_ab)^2`` over all horizontal and vertical
    neighbour pairs ``a -> b`` of the grid, where ``<delta>_ab`` is the mean of the two
    cells' deflection component along the edge: the normal equations are the 5-point
    Laplacian with Neumann boundaries, ``L P = -div(delta)``, diagonalised by the DCT-II
    and solved exactly. The constant is fixed by subtracting the median (background ~0), or
    with ``static`` the quadratic surface the potential shows where no ray crosses the volume.

    Parameters
    ----------
    flow : ndarray, shape (h, w, 2)
        Deflection on the flow grid (image pixels; component 0 = u, 1 = v).
    static : ndarray, shape (h, w), bool, optional
        Cells whose rays miss the volume (``masks.baseline: static``): the potential minus
        the quadratic surface fitted to it there (:func:`static_baseline`) instead of minus
        its median, when these cells surround the volume's image.

    Returns
    -------
    potential : ndarray, shape (h, w), float32
        ``P`` with ``grad P ~= -delta`` (units: image pixels x flow-grid cells); positive
        inside a hot (low-density) plume. NaN where the flow is NaN (cells the flow stage
        found invalid; they are integrated as zero deflection).
    """
    d = np.asarray(flow, dtype=np.float64)
    if d.ndim != 3 or d.shape[-1] != 2:
        raise ValueError(f"flow must have shape (h, w, 2), got {d.shape}")
    invalid = nonfinite_cells(d)
    if invalid.any():
        d = np.where(invalid[..., None], 0.0, d)
    h, w = d.shape[:2]
    gx = -0.5 * (d[:, 1:, 0] + d[:, :-1, 0])   # target P[:, j+1] - P[:, j], shape (h, w-1)
    gy = -0.5 * (d[1:, :, 1] + d[:-1, :, 1])   # target P[i+1] - P[i], shape (h-1, w)
    # A^T g: divergence with the missing boundary edges contributing nothing
    rhs = np.zeros((h, w))
    rhs[:, :-1] -= gx
    rhs[:, 1:] += gx
    rhs[:-1, :] -= gy
    rhs[1:, :] += gy
    # A^T A = -L (Neumann); eigenvalues 4 - 2cos(pi k / w) - 2cos(pi l / h)
    lam = (2.0 - 2.0 * np.cos(np.pi * np.arange(h) / h))[:, None] + \
          (2.0 - 2.0 * np.cos(np.pi * np.arange(w) / w))[None, :]
    r = fft.dctn(rhs, type=2, norm="ortho")
    lam[0, 0] = 1.0
    p_hat = r / lam
    p_hat[0, 0] = 0.0
    P = fft.idctn(p_hat, type=2, norm="ortho")
    base = static_baseline(P, static & ~invalid) if static is not None else None
    if base is not None:
        P -= base
    else:
        P -= np.median(P[~invalid]) if not invalid.all() else np.median(P)
    if invalid.any():
        P[invalid] = np.nan
    return P.astype(np.float32)


def static_baseline(potential: np.ndarray, cells: np.ndarray) -> np.ndarray | None:
    """The quadratic surface ``a + b x + c y + d x^2 + e x y + f y^2`` least-squares fitted to
    ``potential`` on ``cells``, over the whole grid; None when the cells are fewer than
    :data:`BASELINE_MIN_CELLS` or span less than :data:`BASELINE_SPAN` of either axis.

    Where no ray crosses the volume the potential must vanish; an affine bias of the flow
    (a camera's motion or the lighting's change removed a little off, as against a reference
    of few noisy frames) integrates into a quadratic potential over the whole image,
    which this removes; the plume's own potential, inside the volume's image, is not fitted.
    """
    cells = np.asarray(cells, bool)
    if cells.shape != potential.shape or np.count_nonzero(cells) < BASELINE_MIN_CELLS:
        return None
    h, w = potential.shape
    rows, cols = np.nonzero(cells)
    if (np.ptp(rows) + 1) < BASELINE_SPAN * h or (np.ptp(cols) + 1) < BASELINE_SPAN * w:
        return None
    y, x = np.mgrid[0:h, 0:w]
    x = (x - 0.5 * (w - 1)) / w
    y = (y - 0.5 * (h - 1)) / h
    terms = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)
    coef, *_ = np.linalg.lstsq(terms[cells], np.asarray(potential, np.float64)[cells], rcond=None)
    return terms @ coef


def _magnitude(potential: np.ndarray, smooth_sigma: float) -> np.ndarray:
    """Smoothed ``|P|``; invalid (NaN) cells count as 0 and stay 0."""
    P = np.asarray(potential, dtype=np.float32)
    bad = np.isnan(P)
    if bad.any():
        P = np.where(bad, np.float32(0.0), P)
    if smooth_sigma > 0:
        P = cv2.GaussianBlur(P, (0, 0), sigmaX=smooth_sigma, sigmaY=smooth_sigma,
                             borderType=cv2.BORDER_REFLECT)
    return np.abs(P)


def potential_summary(potential: np.ndarray, *, smooth_sigma: float = MaskParams.smooth_sigma,
                      n_quantiles: int = MaskParams.n_quantiles) -> np.ndarray:
    """Small per camera-frame summary of ``|P|`` for the threshold reduction.

    Parameters
    ----------
    potential : ndarray, shape (h, w)
    smooth_sigma : float
        As in :class:`MaskParams` (the same smoothing :func:`make_mask` applies).
    n_quantiles : int

    Returns
    -------
    summary : ndarray, shape (n_quantiles + 1,), float64
        ``[pixel count, q_0, ..., q_{n-1}]`` with ``q_i`` the ``(i + 1/2) / n`` quantile of
        the smoothed ``|P|``: each represents ``count / n`` pixels.
    """
    m = _magnitude(potential, smooth_sigma)
    m = np.sort(m[~np.isnan(np.asarray(potential))])   # invalid cells are not counted
    if m.size == 0:
        return np.zeros(n_quantiles + 1)
    probs = (np.arange(n_quantiles) + 0.5) / n_quantiles
    return np.concatenate([[float(m.size)], sorted_quantiles(m, probs)])


def sorted_quantiles(values: np.ndarray, probs: np.ndarray) -> np.ndarray:
    """``np.quantile(values, probs)`` (its default linear method) of an already sorted 1-D
    array, read off directly: numpy partitions around every requested index even when the
    data are sorted, which costs far more than the lookup (docs/tuning.md, "Speed")."""
    m = np.asarray(values, dtype=np.float64)
    pos = np.asarray(probs, dtype=np.float64) * (m.size - 1)
    lo = np.clip(np.floor(pos).astype(np.int64), 0, m.size - 1)
    hi = np.minimum(lo + 1, m.size - 1)
    t = pos - lo
    return m[lo] + (m[hi] - m[lo]) * t


def threshold_from_summaries(summaries, *, percentile: float = MaskParams.percentile) -> float:
    """Global threshold: the ``percentile`` of ``|P|`` over every summarised camera-frame.

    The reduction step: pools the quantiles of all :func:`potential_summary` results,
    each weighted by the pixels it represents, and takes the weighted percentile (exact to
    within one quantile step of each frame).

    Parameters
    ----------
    summaries : sequence of ndarray, shape (n + 1,)
    percentile : float
        In (0, 100).

    Returns
    -------
    float
    """
    summaries = [np.asarray(s, dtype=np.float64) for s in summaries]
    if not summaries:
        raise ValueError("threshold_from_summaries needs at least one summary")
    vals = np.concatenate([s[1:] for s in summaries])
    wts = np.concatenate([np.full(len(s) - 1, s[0] / (len(s) - 1)) for s in summaries])
    if not wts.sum() > 0:   # every cell of every frame invalid: nothing can be thresholded
        return float("inf")
    order = np.argsort(vals, kind="stable")
    vals, wts = vals[order], wts[order]
    cdf = (np.cumsum(wts) - 0.5 * wts) / wts.sum()
    return float(np.interp(percentile / 100.0, cdf, vals))


def threshold_from_samples(samples: np.ndarray, *, percentile: float = MaskParams.percentile) -> float:
    """Global threshold from raw samples of the (smoothed) potential magnitude.

    Parameters
    ----------
    samples : ndarray, any shape
        ``|P|`` values (or signed ``P``; the magnitude is taken) gathered from all
        camera-frames, e.g. a random subsample of each.
    percentile : float

    Returns
    -------
    float
    """
    return float(np.percentile(np.abs(np.asarray(samples, dtype=np.float64)), percentile))


def flow_noise(flow: np.ndarray) -> float:
    """Robust RMS noise of one flow component (pixels), from the flow field itself.

    ``1.4826 * MAD`` of each component about its median, combined as
    ``sqrt((s_u^2 + s_v^2) / 2)``: in a BOS frame most cells see no flow, so the median
    absolute deviation measures the noise, not the plume. NaN cells are ignored.

    Parameters
    ----------
    flow : ndarray, shape (..., 2)

    Returns
    -------
    float
    """
    f = np.asarray(flow).reshape(-1, 2)
    ok = np.isfinite(f[:, 0]) & np.isfinite(f[:, 1])
    n = int(np.count_nonzero(ok))
    if n < 10:
        return 0.0
    s2 = 0.0
    for k in range(2):  # each component as one contiguous float64 copy, medians in place
        a = np.array(f[:, k] if n == len(ok) else f[:, k][ok], dtype=np.float64)
        m = np.median(a, overwrite_input=True)  # reorders a; |a - m| keeps its values
        s = 1.4826 * np.median(np.abs(a - m), overwrite_input=True)
        s2 += s * s
    return float(np.sqrt(0.5 * s2))


def make_mask(potentials: np.ndarray, centre: int, threshold: float, *, flows=None,
              smooth_sigma: float = MaskParams.smooth_sigma, dilation_radius: int = MaskParams.dilation_radius,
              temporal_radius: int = MaskParams.temporal_radius,
              deflection_threshold: float = MaskParams.deflection_threshold,
              flow_sigma: float = MaskParams.flow_sigma, noise_factor: float = MaskParams.noise_factor,
              grow_factor: float = MaskParams.grow_factor) -> np.ndarray:
    """Conservative mask of one camera-frame: threshold, temporal union, spatial dilation.

    Paper sec. 4 / Figure 4: ``|P| > threshold`` on the smoothed potential of every frame
    within ``temporal_radius`` of ``centre`` (those present in ``potentials``), their union,
    then a dilation by a disk of ``dilation_radius`` cells. With ``flows`` the cells whose
    smoothed deflection exceeds ``deflection_threshold`` join the union (see
    :class:`MaskParams`).

    Parameters
    ----------
    potentials : ndarray, shape (k, h, w)
        Potentials of consecutive frames of one camera.
    centre : int
        Index in ``potentials`` of the frame whose mask is made.
    threshold : float
        From :func:`threshold_from_summaries`.
    flows : ndarray, shape (k, h, w, 2), optional
        The flows the potentials came from (same frames).

    Returns
    -------
    mask : ndarray, shape (h, w), bool
    """
    P = np.asarray(potentials)
    if P.ndim == 2:
        P = P[None]
    k = P.shape[0]
    if not 0 <= centre < k:
        raise ValueError(f"centre {centre} outside the {k} given frames")
    lo = max(0, centre - temporal_radius)
    hi = min(k, centre + temporal_radius + 1)
    if flows is not None:
        flows = np.asarray(flows, dtype=np.float32)
        if flows.ndim == 3:
            flows = flows[None]
        if flows.shape[:3] != P.shape:
            raise ValueError(f"flows {flows.shape} do not match potentials {P.shape}")
    kw = dict(smooth_sigma=smooth_sigma, deflection_threshold=deflection_threshold, flow_sigma=flow_sigma,
              noise_factor=noise_factor, grow_factor=grow_factor)
    evidence = [frame_evidence(P[j], threshold, flow=None if flows is None else flows[j], **kw)
                for j in range(lo, hi)]
    return mask_from_evidence(evidence, dilation_radius=dilation_radius)


def frame_evidence(potential: np.ndarray, threshold: float, *, flow=None,
                   smooth_sigma: float = MaskParams.smooth_sigma,
                   deflection_threshold: float = MaskParams.deflection_threshold,
                   flow_sigma: float = MaskParams.flow_sigma, noise_factor: float = MaskParams.noise_factor,
                   grow_factor: float = MaskParams.grow_factor, noise_cells: np.ndarray | None = None) -> np.ndarray:
    """The cells one frame marks as flow, before the temporal union and the dilation of
    :func:`make_mask` (which ORs this over the frames around its centre).

    Parameters
    ----------
    potential : ndarray, shape (h, w)
    threshold : float
    flow : ndarray, shape (h, w, 2), optional
        The flow the potential came from.
    noise_cells : ndarray, shape (h, w), bool, optional
        The cells whose flow noise sets the deflection criterion (default all). A reference
        topped up where the rays miss the volume (``capture.reference_topup``) makes the flow
        there quieter than where the plume can be; the criterion must follow the latter's
        noise, or noise inside the volume's image passes it (benchmarks/results/reference_topup.md).

    Returns
    -------
    ndarray, shape (h, w), bool
    """
    P = np.asarray(potential)
    m = _magnitude(P, smooth_sigma) > threshold
    m |= np.isnan(P)   # invalid cells: this camera cannot rule flow out there
    if flow is not None and deflection_threshold > 0:
        fl = np.nan_to_num(np.asarray(flow, dtype=np.float32), nan=0.0)
        if flow_sigma > 0:
            fl = cv2.GaussianBlur(fl, (0, 0), sigmaX=flow_sigma, sigmaY=flow_sigma,
                                  borderType=cv2.BORDER_REFLECT)
        thr = deflection_threshold
        sigma = 0.0
        if noise_factor > 0 or grow_factor > 0:
            sigma = flow_noise(fl[noise_cells]) if noise_cells is not None and noise_cells.sum() >= 100 else 0.0
            sigma = sigma or flow_noise(fl)
        if noise_factor > 0:
            thr = max(thr, noise_factor * sigma)
        mag = np.hypot(fl[..., 0], fl[..., 1])
        m |= mag > thr
        low = max(deflection_threshold, grow_factor * sigma)
        if grow_factor > 0 and thr > GROW_NOISE_RATIO * deflection_threshold and low < thr and m.any():
            m = _grow(m, mag > low)
    return m


def _grow(seed: np.ndarray, weak: np.ndarray) -> np.ndarray:
    """``seed`` plus the 8-connected components of ``weak`` that touch it (hysteresis)."""
    n, labels = cv2.connectedComponents((weak | seed).astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[np.unique(labels[seed])] = True
    keep[0] = False
    return seed | keep[labels]


def mask_from_evidence(evidence, *, dilation_radius: int = MaskParams.dilation_radius) -> np.ndarray:
    """Union of :func:`frame_evidence` maps, dilated by a Euclidean disk of ``dilation_radius`` cells."""
    m = np.zeros(np.shape(evidence[0]), bool)
    for e in evidence:
        m |= e
    if dilation_radius > 0:
        r = int(dilation_radius)
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        disk = (yy * yy + xx * xx <= r * r).astype(np.uint8)  # Euclidean disk
        m = cv2.dilate(m.astype(np.uint8), disk, borderType=cv2.BORDER_CONSTANT,
                       borderValue=0).astype(bool)
    return m
