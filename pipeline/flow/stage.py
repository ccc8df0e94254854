"""The flow entry points: :func:`deflection_field` (full-resolution flow by one of
:data:`~.params.METHODS` behind one pyramid driver) and :func:`deflection_stage` (the
per camera-frame stage kernel of paper sec. 4: flow at full resolution, then area
downsampling to the flow grid, invalid cells, outliers, texture-bias correction and
smoothing, in named steps).
"""

from __future__ import annotations

import logging

import numpy as np

from schlieren.pipeline.geometry import FlowGrid

from .correlation import _correlation_flow
from .dis import _dis_flow
from .focus import AUTO, AUTO_METHODS, PRESMOOTH_IN_FOCUS
from .hs import _hs_level
from .images import _as_image, _fill_nonfinite, _normalisation, _standardise
from .lk import _lk_level, _texture_bias, _upsample_cells, ici_windows
from .params import METHODS, FlowParams, uses_cell_solve
from .invalid import InvalidPixels, _fill_bad_cells
from .post import _block_mean, _median_test, _smooth_cells
from .reference import PreparedReference, _weight_pyramid, frame_pyramid, invalid_pixels, prepare_reference
from .splines import prolong_flow

__all__ = ["deflection_field", "deflection_stage"]

log = logging.getLogger(__name__)


def _pyramid_flow(level_solver, prep: PreparedReference, frame_pyr, *, iterations,
                  fine_iterations, keep=None, weights=None, cells=0, start=None, **kw):
    """Coarse to fine: ``level_solver`` (:func:`_lk_level`, :func:`_hs_level`) on each level
    of the prepared pyramid, from zero flow (or from ``start``, a displacement field
    ``start(x, y) -> (dx, dy)`` in full-resolution pixels), each level's flow prolonged to
    start the next."""
    kw0 = kw
    h, w = prep.pyramid[-1].shape
    if start is None:
        u = np.zeros((h, w), np.float32)
        v = np.zeros((h, w), np.float32)
    else:
        u, v = _level_field(start, len(prep.pyramid) - 1, (h, w))
    for lev in range(len(prep.pyramid) - 1, -1, -1):
        if "gradient" in kw0:  # coarse levels only initialise: frame gradient (cheapest)
            kw = dict(kw0, gradient=kw0["gradient"] if lev == 0 else "frame")
        if u.shape != prep.pyramid[lev].shape:
            u, v = prolong_flow(u, v, prep.pyramid[lev].shape)
        it = fine_iterations if lev == 0 else iterations
        w = weights[lev] if weights is not None and lev < len(weights) else None
        extra = {} if lev == 0 or "ici" not in kw else {"ici": None}
        if cells > 1:  # every level on f x f cells of its pixels; the finest returns the cell grid
            extra["cells"] = cells
        u, v = level_solver(prep.coefficients[lev], frame_pyr[lev], u, v, iterations=it,
                            keep=keep if lev == 0 else None, weight=w, **{**kw, **extra})
        if lev > 0 and cells > 1:  # a coarse level's cells -> its pixels, for the prolongation
            u, v = _upsample_cells(u, v, cells, prep.pyramid[lev].shape)
    return u, v


def _level_field(field, lev: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A full-resolution displacement field ``field(x, y) -> (dx, dy)`` on pyramid level
    ``lev`` (its pixel ``i`` sits on full-resolution pixel ``2^lev i``, its pixels are
    ``2^lev`` wide), as two float32 arrays."""
    s = float(2 ** lev)
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    dx, dy = field(s * x, s * y)
    return (np.asarray(dx, np.float64) / s).astype(np.float32), (np.asarray(dy, np.float64) / s).astype(np.float32)


def deflection_field(
    reference,
    frame: np.ndarray,
    *,
    method: str = FlowParams.method,
    window: int = FlowParams.window,
    window_type: str = FlowParams.window_type,
    levels: int = FlowParams.levels,
    iterations: int = FlowParams.iterations,
    fine_iterations: int = FlowParams.fine_iterations,
    presmooth: float | str = FlowParams.presmooth,
    regularisation: float = FlowParams.regularisation,
    gradient: str = FlowParams.gradient,
    alpha: float = FlowParams.alpha,
    inner_iterations: int = FlowParams.inner_iterations,
    dis_preset: str = FlowParams.dis_preset,
    corr_window: int = FlowParams.corr_window,
    corr_step: int = FlowParams.corr_step,
    corr_taper: bool = FlowParams.corr_taper,
    ici_gamma: float = FlowParams.ici_gamma,
    ici_min_window: int = FlowParams.ici_min_window,
) -> np.ndarray:
    """Full-resolution BOS deflection field between a reference background and a frame.

    Paper sec. 4 ("Computing BOS deflections"): dense pyramidal Lucas-Kanade (default),
    Horn-Schunck, OpenCV DIS, or window cross-correlation. Keyword parameters are those of
    :class:`FlowParams` (see there for units); each method uses its own subset.

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        Background without flow, grey levels (any range; float32 internally).
    frame : ndarray, shape (H, W)
        Image through the flow.

    Returns
    -------
    flow : ndarray, shape (H, W, 2), float32
        ``delta`` in pixels such that ``frame(p) ~= reference(p + delta)``;
        ``[..., 0]`` = u (columns), ``[..., 1]`` = v (rows).
    """
    kw = {k: val for k, val in locals().items() if k not in ("reference", "frame")}
    u, v = _flow_components(reference, frame, **kw)
    out = np.empty(u.shape + (2,), np.float32)
    out[..., 0] = u
    out[..., 1] = v
    return out


def _flow_components(reference, frame, *, method, window, window_type, levels, iterations,
                     fine_iterations, presmooth, regularisation, gradient, alpha,
                     inner_iterations, dis_preset, corr_window, corr_step, corr_taper,
                     ici_gamma, ici_min_window, keep=None, valid=None, info=None, cells=0, start=None,
                     weights=None, pyramid=None):
    """:func:`deflection_field` as two (H, W) float32 arrays (u, v); for LK, ``keep``
    (a dict) receives the full-resolution frame gradients ``gx``, ``gy``. ``valid``
    (H, W) bool: pixels the flow may use (LK and HS weight the others out; every method
    gets NaN-free images). ``cells`` = f > 1 with LK (frame gradient, no ICI): the finest
    level is solved per f x f cell (:func:`_lk_cells`) and (u, v) are (H // f, W // f);
    ``keep["mom"]`` then holds the block moments. Other methods ignore it. ``start``
    (LK and HS): the displacement field ``start(x, y) -> (dx, dy)`` the pyramid starts from
    (:func:`_pyramid_flow`); the other methods ignore it. ``weights`` (LK and HS): the
    per-level weights of ``valid`` when already made (:func:`_weight_pyramid`); ``pyramid``
    (LK and HS): the frame's :func:`frame_pyramid` when already made."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    frm = _as_image(frame, "frame")
    if isinstance(reference, PreparedReference):
        prep = reference
        if method in ("lk", "hs") and ((presmooth != AUTO and prep.presmooth != presmooth) or prep.levels != levels):
            raise ValueError("PreparedReference was built with presmooth="
                             f"{prep.presmooth}, levels={prep.levels}; the flow asks for "
                             f"presmooth={presmooth}, levels={levels}")
    elif method in ("lk", "hs"):
        prep = prepare_reference(reference, presmooth=PRESMOOTH_IN_FOCUS if presmooth == AUTO and
                                 method not in AUTO_METHODS else presmooth, levels=levels)
    else:
        img = _as_image(reference, "reference")
        mean, scale = _normalisation(img)
        prep = PreparedReference(_fill_nonfinite(img, mean), mean, scale, 0.0, 1, (), ())
    if prep.shape != frm.shape:
        raise ValueError(f"reference {prep.shape} and frame {frm.shape} differ in shape")
    if method in ("lk", "hs"):
        fpyr = frame_pyramid(prep, frm) if pyramid is None else pyramid
        if weights is None:
            weights = None if valid is None or valid.all() else _weight_pyramid(valid, len(prep.pyramid))
        if method == "lk":
            ici = None
            if ici_gamma > 0 and gradient == "frame":
                ici = {"windows": ici_windows(min(ici_min_window, window), window), "gamma": ici_gamma,
                       "info": info}
            u, v = _pyramid_flow(_lk_level, prep, fpyr, window=window, window_type=window_type,
                                 iterations=iterations, fine_iterations=fine_iterations,
                                 regularisation=regularisation, gradient=gradient,
                                 keep=keep, weights=weights, ici=ici, cells=cells, start=start)
        else:
            u, v = _pyramid_flow(_hs_level, prep, fpyr, iterations=iterations,
                                 fine_iterations=fine_iterations, alpha=alpha,
                                 inner_iterations=inner_iterations, weights=weights, start=start)
    else:
        frm = _fill_nonfinite(frm, prep.mean)
        ref = _standardise(prep.image, prep.mean, prep.scale, 0.0)
        frs = _standardise(frm, prep.mean, prep.scale, 0.0)
        if method == "dis":
            u, v = _dis_flow(ref, frs, dis_preset=dis_preset)
        else:
            u, v = _correlation_flow(ref, frs, corr_window=corr_window, corr_step=corr_step,
                                     corr_taper=corr_taper)
    return u, v


# over 80 lines only by its numpydoc docstring: the steps are the functions it calls
def deflection_stage(reference, frame: np.ndarray, params: FlowParams = FlowParams(), *,
                     info: dict | None = None, motion=None, invalid=None, pyramid: list | None = None) -> np.ndarray:
    """Per camera-frame deflection stage: flow, area downsampling, outliers, smoothing.

    Paper sec. 4: full-resolution optical flow, downsampled to the flow grid
    ``FlowGrid((W, H), params.factor)`` *after* the flow, smoothed and filtered for
    outliers. The normalised median test and the smoothing run on the flow grid: the LK
    flow is correlated over its window (``window`` > ``factor``), so its outliers are
    window-sized, not single pixels, and filtering the ``factor**2`` times smaller grid is
    far cheaper.
    ``smoothing_sigma`` is given in full-resolution pixels (``sigma / factor`` on the grid).

    With ``texture_correction`` (LK), the first-order bias of the LK window mean is
    subtracted after the outlier test (:func:`_texture_bias`): where the deflection varies
    across the window, LK returns its structure-tensor weighted mean, centred on the
    texture's weighted centroid rather than on the pixel: the largest error term on the
    buoyant-plume phantom (benchmarks/results/flow.md; its cost: docs/tuning.md, "Flow").
    Finally, with ``adaptive_sigma`` > 0, :func:`_adaptive_smoothing` smooths more where
    the flow is smooth (weak, slowly varying deflections: mostly noise) and keeps the
    ``smoothing_sigma`` result across structure.

    With ``invalid_check``, pixels of the reference or the frame that cannot carry a
    deflection (:func:`invalid_pixels`) get zero weight in the flow, and the flow-grid
    cells where they hold half or more of the cell or of its LK window come back as NaN
    (the masks treat them as "possibly flow", the tomography drops their rays).

    Parameters
    ----------
    reference : ndarray, shape (H, W), or PreparedReference
        Background (float32 grey levels, 8- or 16-bit range). Passing the
        :class:`PreparedReference` of the camera saves its per-call preparation.
    frame : ndarray, shape (H, W)
    params : FlowParams
    info : dict, optional
        Receives what the data chose (with ICI: the image noise, the median window, the
        fraction of pixels per window and the median predicted flow noise in pixels).
    motion : callable, optional
        The background's own displacement against the reference, ``motion(x, y) -> (dx,
        dy)`` at full-resolution image positions (a camera that moved:
        :mod:`schlieren.pipeline.capture`). LK and HS start their pyramid from it, so the
        flow only has to find the deflections (a Lucas-Kanade step underestimates large
        displacements); it is subtracted from the result, which is then the deflection alone.
    invalid : ndarray, shape (H, W), bool, or InvalidPixels, optional
        Pixels known to be unusable (defective sensor pixels, mostly isolated): weighted out
        like those of ``invalid_check`` (whether or not that is on), but the cells they
        alone empty get their nearest valid cell's deflection rather than NaN. The camera's
        :func:`~.invalid.prepare_invalid` saves their per-frame preparation.
    pyramid : list of ndarray, optional
        The frame's :func:`~.reference.frame_pyramid` when the caller already made it (LK
        and HS; a :class:`PreparedReference` ``reference``).

    Returns
    -------
    flow : ndarray, shape (H // f, W // f, 2), float32
        Deflection in original-image pixels (component 0 = u, 1 = v).
    """
    f = params.factor
    H, W = np.shape(frame)[:2]
    rows, cols = FlowGrid((W, H), f).shape
    checked = _valid_pixels(reference, frame, params.texture_threshold) if params.invalid_check else None
    prepared = invalid if isinstance(invalid, InvalidPixels) and checked is None else None
    valid, weights = (prepared.valid, prepared.weights) if prepared is not None else \
        (_combined_valid(checked, invalid), None)
    on_cells = uses_cell_solve(params)
    ici = params.method == "lk" and params.ici_gamma > 0 and params.gradient == "frame"
    texture = params.method == "lk" and params.texture_correction and not ici
    keep = {} if texture or on_cells else None
    p = params
    u, v = _flow_components(reference, frame, method=p.method, window=p.window, window_type=p.window_type,
                            levels=p.levels, iterations=p.iterations, fine_iterations=p.fine_iterations,
                            presmooth=p.presmooth, regularisation=p.regularisation, gradient=p.gradient,
                            alpha=p.alpha, inner_iterations=p.inner_iterations, dis_preset=p.dis_preset,
                            corr_window=p.corr_window, corr_step=p.corr_step, corr_taper=p.corr_taper,
                            ici_gamma=p.ici_gamma, ici_min_window=p.ici_min_window,
                            keep=keep, valid=valid, info=info, cells=f if on_cells else 0, start=motion,
                            weights=weights, pyramid=pyramid)
    if u.shape == (rows, cols) and on_cells:
        comps = [u, v]
    else:
        comps = [_block_mean(u, f, (rows, cols)), _block_mean(v, f, (rows, cols))]
    if motion is not None:  # the deflection alone: the flow minus the motion (at the cells' centres)
        centres = FlowGrid((W, H), f).pixel_centres()
        mx, my = motion(centres[..., 0], centres[..., 1])
        comps = [comps[0] - np.asarray(mx, np.float32), comps[1] - np.asarray(my, np.float32)]
    bad_cells = None
    if valid is not None:
        comps, bad_cells = prepared.fill(comps) if prepared is not None else \
            _fill_bad_cells(comps, valid, checked, params)
        if comps is None:
            return np.full((rows, cols, 2), np.nan, np.float32)
    if params.outlier_threshold > 0:
        comps = _replace_outliers(comps, params.outlier_threshold, params.outlier_epsilon)
    if keep and params.texture_correction:
        bu, bv = _texture_bias(keep["gx"], keep["gy"], comps[0], comps[1], window=params.window,
                               window_type=params.window_type, factor=params.factor, mom=keep.get("mom"),
                               linear=on_cells, T=keep.get("T"))
        comps = [comps[0] - bu, comps[1] - bv]
    out = _smooth_cells(comps, params.smoothing_sigma / f, params.adaptive_sigma / f, params.adaptive_threshold)
    if bad_cells is not None and bad_cells.any():
        out[bad_cells] = np.nan
    return out


def _combined_valid(checked: np.ndarray | None, invalid) -> np.ndarray | None:
    """The pixels valid for ``invalid_check`` (``checked``, None: all) and not in the
    caller's ``invalid`` (a map or :class:`~.invalid.InvalidPixels`); None: all."""
    if isinstance(invalid, InvalidPixels):
        invalid = invalid.mask
    if invalid is None or not np.any(invalid):
        return checked
    return ~np.asarray(invalid, bool) if checked is None else checked & ~np.asarray(invalid, bool)


def _valid_pixels(reference, frame: np.ndarray, texture_threshold: float) -> np.ndarray | None:
    """Pixels of both the reference and the frame that can carry a deflection
    (:func:`invalid_pixels`; a :class:`PreparedReference` keeps its own map); ``None``
    when all can."""
    inv_ref = reference.invalid(texture_threshold) if isinstance(reference, PreparedReference) \
        else invalid_pixels(reference, texture_threshold=texture_threshold)
    inv = inv_ref | invalid_pixels(frame, texture_threshold=texture_threshold)
    return ~inv if inv.any() else None


def _replace_outliers(comps: list, threshold: float, epsilon: float) -> list:
    """The normalised median test on the flow grid's (u, v) (:func:`_median_test`)."""
    cu, cv_, bad = _median_test(comps[0], comps[1], threshold, epsilon)
    n_out = int(np.count_nonzero(bad))
    if n_out:
        log.debug("deflection_stage: replaced %d outlier vectors (%.3f%%)",
                  n_out, 100.0 * n_out / bad.size)
    return [cu, cv_]
