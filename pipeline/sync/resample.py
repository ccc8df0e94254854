"""Row-wise resampling of one camera's flow fields to a common session instant (paper
sec. 4, Figure 5): each flow-grid row between the two usable frames around the instant at
which that row was exposed, warped along the motion between the fields. Flow fields are
smooth, so warping them (rather than the raw images) keeps the high frequencies the
optical flow needs.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

from schlieren.pipeline.flow.splines import spline_coefficients, warp_coefficient_rows
from schlieren.pipeline.flow.images import nonfinite_cells
from schlieren.pipeline.geometry import FlowGrid

from .motion import _digest, cached_field_motion
from .params import ResampleParams
from .timing import _fractional_frame

__all__ = ["ResampleParams", "resample_flow"]

log = logging.getLogger(__name__)


def _coefficients(field: np.ndarray) -> list:
    return [spline_coefficients(np.ascontiguousarray(field[..., k])) for k in range(field.shape[-1])]


def _warp_channel_rows(coefs: list, rows: np.ndarray, disp: np.ndarray) -> np.ndarray:
    return np.stack([warp_coefficient_rows(c, rows, disp) for c in coefs], axis=-1)


def resample_flow(raw: np.ndarray, first_frame: int, target_time: float, *, offset: float,
                  frame_rate: float, line_time: float, flow_grid: FlowGrid,
                  excluded_frames=(), params: ResampleParams = ResampleParams(),
                  digests: list | None = None) -> np.ndarray:
    """One camera's flow field at the session instant ``target_time``, row by row.

    Paper sec. 4 and Figure 5: flow-grid row ``i`` of raw frame ``f`` was exposed at
    ``offset + f / frame_rate + row_of_cell[i] * line_time``. For each row the instant
    falls between two usable frames ``a0 <= phi_i < a1`` (flash frames excluded) with
    weight ``alpha_i = (phi_i - a0) / (a1 - a0)``. With ``method="motion"`` the motion
    ``m`` between the fields (``F_a0(p) ~= F_a1(p + m)``, :func:`field_motion`) is
    estimated once per frame pair and the row is read from
    ``(1 - alpha) F_a0(p - alpha m) + alpha F_a1(p + (1 - alpha) m)``. Instants before
    the first or after the last usable frame are clamped to that frame.

    Parameters
    ----------
    raw : ndarray, shape (k, h, w, 2)
        Flow fields of the consecutive raw frames ``first_frame .. first_frame + k - 1``
        (see :func:`frames_needed`).
    first_frame : int
        Absolute index of ``raw[0]``.
    target_time : float
        Session time, seconds.
    offset, frame_rate, line_time : float
        The camera's timing (seconds, frames per second, seconds per row).
    flow_grid : FlowGrid
        Geometry of the flow grid (row centres in image rows).
    excluded_frames : iterable of int
        Absolute indices of frames that must not be used (the flash).
    params : ResampleParams
    digests : list of bytes, optional
        :func:`field_digest` of each ``raw[j]`` (``None`` entries computed here): the
        motion cache's keys, which a caller resampling neighbouring instants can keep.

    Returns
    -------
    flow : ndarray, shape (h, w, 2), float32
    """
    raw = np.asarray(raw, dtype=np.float32)
    k, h, w = raw.shape[:3]
    if (h, w) != tuple(flow_grid.shape):
        raise ValueError(f"raw flow grid {(h, w)} does not match the flow grid {flow_grid.shape}")
    excluded = set(int(e) for e in excluded_frames)
    usable = [j for j in range(k) if first_frame + j not in excluded]
    if not usable:
        raise ValueError(f"no usable frame among {first_frame}..{first_frame + k - 1} "
                         f"(excluded: {sorted(excluded)})")
    phi = _fractional_frame(target_time, flow_grid.row_of_cell(), offset=offset,
                            frame_rate=frame_rate, line_time=line_time) - first_frame
    j0, j1, alpha = _bracket_rows(phi, usable, nearest=params.method == "nearest")
    n_clamped = int(np.sum((phi < usable[0]) | (phi > usable[-1])))
    if n_clamped:
        log.debug("resample_flow: %d of %d rows clamped to the ends of frames %d..%d",
                  n_clamped, h, first_frame + usable[0], first_frame + usable[-1])
    invalid = nonfinite_cells(raw)
    if not invalid.any():
        return _blend_rows(raw, j0, j1, alpha, params, digests)
    # the motion and the spline coefficients spread a NaN over whole rows, columns and
    # pyramid blocks: blend the fields with their invalid cells at zero deflection, then
    # invalidate the output cells that read them
    filled = np.where(invalid[..., None], np.float32(0.0), raw)
    reach: dict = {}
    out = _blend_rows(filled, j0, j1, alpha, params, digests, reach=reach)
    out[_cells_reading_invalid(invalid, j0, j1, alpha, reach)] = np.nan
    return out


def _bracket_rows(phi: np.ndarray, usable: list, *, nearest: bool):
    """Per flow-grid row with fractional frame ``phi`` (relative to ``raw[0]``): the usable
    frames ``j0 <= phi < j1`` around it (clamped at the ends) and the weight ``alpha`` of
    ``j1``; with ``nearest``, ``j0`` is the nearer of the two and ``alpha`` 0."""
    ua = np.asarray(usable, dtype=np.float64)
    # bracket each row between usable frames j0 <= phi < j1 (clamped at the ends)
    pos = np.searchsorted(ua, phi, side="right")
    j0 = ua[np.clip(pos - 1, 0, len(ua) - 1)]
    j1 = ua[np.clip(pos, 0, len(ua) - 1)]
    with np.errstate(invalid="ignore", divide="ignore"):
        alpha = np.where(j1 > j0, (phi - j0) / np.where(j1 > j0, j1 - j0, 1.0), 0.0)
    alpha = np.clip(alpha, 0.0, 1.0)
    j0 = j0.astype(int)
    j1 = j1.astype(int)
    if nearest:
        j0 = np.where(alpha >= 0.5, j1, j0)
        alpha = np.zeros_like(alpha)
    return j0, j1, alpha


def _blend_rows(raw: np.ndarray, j0: np.ndarray, j1: np.ndarray, alpha: np.ndarray, params: ResampleParams,
                digests: list | None, *, reach: dict | None = None) -> np.ndarray:
    """Each flow-grid row read between its frames ``raw[j0]`` and ``raw[j1]`` at weight
    ``alpha`` (:func:`resample_flow`), one frame pair at a time: warped along the pair's
    motion (``motion``), blended (``linear``) or copied (``nearest``, ``alpha`` 0).
    ``reach`` (optional) receives per warped pair ``(a, b)`` how far (cells) its rows read
    from their own cell: the largest warp plus the cubic spline's support."""
    h, w = raw.shape[1:3]
    out = np.empty((h, w, 2), np.float32)
    coef_memo: dict = {}

    def coefs(j):  # a frame can be the end of one pair and the start of the next
        if j not in coef_memo:
            coef_memo[j] = _coefficients(raw[j])
        return coef_memo[j]

    for a, b in sorted(set(zip(j0.tolist(), j1.tolist()))):
        rows = np.flatnonzero((j0 == a) & (j1 == b))
        al = alpha[rows].astype(np.float32)[:, None, None]
        fa = raw[a]
        if a == b or params.method == "nearest" or np.all(al == 0):
            out[rows] = fa[rows]
            continue
        fb = raw[b]
        if params.method == "linear":
            out[rows] = (1 - al) * fa[rows] + al * fb[rows]
            continue
        keys = None
        if digests is not None:
            keys = tuple(digests[j] if digests[j] is not None else _digest(raw[j]) for j in (a, b))
        m = cached_field_motion(fa, fb, window=params.window, levels=params.levels,
                                iterations=params.iterations, regularisation=params.regularisation,
                                finest_level=params.finest_level, digests=keys)
        # only the rows that use this frame pair are warped
        mr = m[rows]
        wa = _warp_channel_rows(coefs(a), rows, -al * mr)
        wb = _warp_channel_rows(coefs(b), rows, (1 - al) * mr)
        if reach is not None:
            far = float(np.nanmax(np.abs(mr), initial=0.0))
            reach[(a, b)] = int(min(np.ceil(far), max(h, w))) + 2
        out[rows] = (1 - al) * wa + al * wb
    return out


def _cells_reading_invalid(invalid: np.ndarray, j0: np.ndarray, j1: np.ndarray, alpha: np.ndarray,
                           reach: dict) -> np.ndarray:
    """The output cells of :func:`_blend_rows` that read an invalid cell of ``raw[j0]``
    (weight ``1 - alpha`` > 0) or ``raw[j1]`` (``alpha`` > 0): the invalid cells of the
    row's frames, grown by the pair's ``reach`` where the row was warped.

    Parameters
    ----------
    invalid : ndarray, shape (k, h, w), bool
    j0, j1, alpha : ndarray, shape (h,)
    reach : dict
        ``(a, b) -> cells`` for the warped frame pairs (:func:`_blend_rows`).
    """
    out = np.zeros(invalid.shape[1:], bool)
    for a, b in sorted(set(zip(j0.tolist(), j1.tolist()))):
        rows = np.flatnonzero((j0 == a) & (j1 == b))
        al = alpha[rows]
        bad = np.zeros_like(out)
        if np.any(al < 1):
            bad[rows] |= invalid[a][rows]
        if a != b and np.any(al > 0):
            bad[rows] |= invalid[b][rows]
        r = reach.get((a, b), 0)
        src = invalid[a] | invalid[b]
        if r and src.any():  # a warp reads the pair's fields within r cells (rows of other pairs too)
            bad[rows] |= ndimage.distance_transform_cdt(~src, metric="chessboard")[rows] <= r
        out |= bad
    return out
