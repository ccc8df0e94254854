"""One frame's flows measured again around its tomographic solution (``refine.passes`` > 0).

Beyond the paper: the tomography task of frame ``k`` predicts every camera's deflection from
its solution (:func:`~schlieren.pipeline.residuals.predict_flows` on the ray grid,
:func:`~schlieren.pipeline.flow.cells_to_pixels` to the pixels), re-measures the flow of each
raw frame that frame ``k``'s resampling reads around that prediction
(:func:`~schlieren.pipeline.flow.refined_deflection` with the deflection task's capture
correction: its stored registration, :func:`~schlieren.pipeline.capture.stored_fit`, is
not measured again), and resamples them to the output instant as the ``resample`` task does. With ``refine.crop``
each camera's flows are measured only on the crop where its prediction reaches
(:func:`~schlieren.pipeline.flow.refine_region`), the stored ``flow_raw`` elsewhere; a frame
whose stored registration applied a motion is measured on the whole image. The
raw frames' deflection tasks are done by then (the tomography waits for its resampling),
and nothing is stored but the solve the task writes.
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline import capture, sync
from schlieren.pipeline import flow as flowmod
from schlieren.pipeline.residuals import predict_flows
from schlieren.workers.tasks.capture import camera_capture
from schlieren.workers.tasks.deflection import flow_params
from schlieren.workers.tasks.resample import frames_read
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["refined_flows"]


def refined_flows(ctx: RunContext, k: int, geom, gradient: np.ndarray, *, crop: bool = True) -> np.ndarray:
    """Frame ``k``'s flows of every camera (C, h, w, 2) on the flow grid, each raw frame's
    measured around the deflections ``gradient`` (nz, ny, nx, 3) predicts (``crop``
    (``refine.crop``): only where the prediction reaches)."""
    predicted = predict_flows(geom, ctx.cameras, np.asarray(gradient, np.float64),
                              n_ambient=ctx.session.medium.n_ambient)
    return np.stack([_camera_flow(ctx, c, k, predicted[c], crop) for c in range(len(ctx.cameras))])


def _camera_flow(ctx: RunContext, c: int, k: int, predicted: np.ndarray, crop: bool = True) -> np.ndarray:
    """Camera ``c``'s refined flow at output instant ``k`` from its prediction on the ray grid."""
    cam = ctx.cameras[c]
    params = flow_params(ctx, c)
    src = ctx.frames(c)
    lo, hi, excluded, _ = frames_read(ctx, c, k)
    region = _region(ctx, predicted, params, cam.image_size) if crop else None
    shared: dict = {}
    raw = []
    for f in range(lo, hi + 1):
        j = f - ctx.raw_first
        if f in excluded or f in src.dropped:  # skipped by the resampling: its stored (NaN or flagged) flow
            raw.append(ctx.read_upstream("flow_raw", (c, j)))
            continue
        parity = src.parity(f) if hasattr(src, "parity") else None
        # the camera's fixed inputs of the corrections depend on the reference's shape and
        # levels only, not its values: the deflection tasks' apply to the warped reference too
        fixed = camera_capture(ctx, c, parity, params)
        fit = _stored_fit(ctx, c, j)
        prep = ctx.prepared_reference(c, parity)
        if region is not None and not capture.moves(fit, ctx.config.capture, cam.image_size):
            raw.append(_region_flow(ctx, c, f, region, params, prep, fixed, fit,
                                    lambda: _around(ctx, predicted, params, prep, region.crop, shared, parity)))
            continue

        def corrected(ref, img, p, fixed=fixed, fit=fit):
            return capture.corrected_deflection(ref, img, p, ctx.config.capture, camera=fixed, fit=fit)[0]

        pixels, around = _around(ctx, predicted, params, prep, None, shared, parity)
        raw.append(flowmod.refined_deflection(prep, ctx.frame(c, f), pixels, params, deflection=corrected,
                                              around=around))
    return sync.resample_flow(np.stack(raw), lo, float(ctx.times()[k]), offset=ctx.time_offset(c),
                              frame_rate=ctx.session.frame_rate, line_time=cam.line_time, flow_grid=ctx.flow_grid,
                              excluded_frames=excluded, params=ctx.config.resample)


def _around(ctx: RunContext, predicted: np.ndarray, params, prep, box, shared: dict, parity):
    """The prediction's pixels on ``box`` (None: the whole image) and the reference (of field
    ``parity``) resampled around them, made once for the raw frames that share them (kept in
    ``shared``)."""
    key = (parity, box)
    if key not in shared:
        H, W = prep.shape
        pixels = flowmod.cells_to_pixels(predicted, ctx.ray_grid.factor, (W, H), box=box)
        ref = prep if box is None else prep.image[box[1]:box[3], box[0]:box[2]]
        shared[key] = pixels, flowmod.predicted_reference(ref, pixels, presmooth=params.presmooth,
                                                           levels=params.levels)
    return shared[key]


def _region(ctx: RunContext, predicted: np.ndarray, params, image_size) -> flowmod.RefineRegion | None:
    """Where a camera's refined flow can differ from its plain flow (None: the whole image,
    for flows other than Lucas-Kanade's)."""
    if params.method != "lk":
        return None
    reach = flowmod.flow_reach(window=params.window, levels=params.levels, factor=params.factor,
                               presmooth=params.presmooth, smoothing_sigma=params.smoothing_sigma,
                               adaptive_sigma=params.adaptive_sigma)
    return flowmod.refine_region(predicted, ctx.ray_grid.factor, image_size, reach=reach, factor=params.factor,
                                 levels=params.levels)


def _region_flow(ctx: RunContext, c: int, f: int, region, params, prep, fixed, fit, around) -> np.ndarray:
    """Raw frame ``f``'s refined flow computed on ``region`` alone, its stored plain flow
    elsewhere (``around()``: the prediction's pixels on the crop and the crop's reference
    resampled around them)."""
    plain = ctx.read_upstream("flow_raw", (c, f - ctx.raw_first))
    if region.empty:
        return np.asarray(plain, np.float32)

    def corrected(ref, img, p):
        return capture.corrected_crop_deflection(ref, img, p, ctx.config.capture, fit=fit, crop=region.crop,
                                                 whole=prep, bad=fixed.bad)

    pixels, moved = around()
    return flowmod.refined_deflection_in_region(prep.image, ctx.frame(c, f), pixels, plain, region, params,
                                                deflection=corrected, around=moved)


def _stored_fit(ctx: RunContext, c: int, j: int) -> capture.BackgroundFit:
    """The registration camera ``c``'s deflection task measured for raw frame ``j`` (its
    stored ``background_motion``, ``photometric`` and ``capture_fit``)."""
    cam = ctx.cameras[c]
    return capture.stored_fit(ctx.read_upstream("background_motion", (c, j)), ctx.read_upstream("photometric", (c, j)),
                              ctx.read_upstream("capture_fit", (c, j)),
                              capture.row_knots(cam.height, ctx.config.capture.banding_rows))
