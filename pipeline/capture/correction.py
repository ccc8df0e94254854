"""One camera-frame's flow with the capture's defects removed: the per camera-frame
kernel of the ``deflection`` stage with :class:`~.params.CaptureParams`.

1. :func:`~.registration.register_background` measures the background's motion and the
   frame's gain and offset profiles on the pixels whose rays miss the volume (on the
   coarse pyramid levels alone when their fit shows nothing that would be applied:
   :data:`SCREEN_MARGIN`), on the frame's pyramid that the flow then uses too;
2. the frame's gain and offset are removed (when they depart from 1 and 0 by more than
   their tolerances);
3. the flow (:func:`~schlieren.pipeline.flow.deflection_stage`) starts from the motion
   (or, beyond ``warp_above``, runs against the reference resampled at the moved
   positions), gives the defective pixels no weight, and returns the deflection alone;
4. what motion the flow still shows on the static cells is fitted robustly
   (:func:`~.motion.fit_flow_motion`) and, whenever a motion was applied, removed too,
   however small: the registration's error is a bias on every cell, which the masks'
   potential (:func:`~schlieren.pipeline.masks.flow_potential`) integrates into a ramp
   across the image. When the registration's motion exceeds ``motion_tolerance`` but was
   not applied (below its significance, as against a reference of few noisy frames) and
   this fit of thousands of cells confirms it (the same motion within half of it, above the
   tolerance and its own significance), that is the motion and is removed the same way; where the static region
   is too small the
   registration used every pixel, and this fit on the flow's low-deflection cells is what
   separates the plume from the motion;
5. with ``motion_source: camera`` the deflections are moved back onto the reference's
   pixel grid (a camera that turned sees the plume through other pixels: the calibrated
   ray of pixel ``q`` is seen at ``q - motion(q)`` in the frame).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from schlieren.pipeline.flow import FlowParams, deflection_stage, frame_pyramid, nonfinite_cells, prepare_reference
from schlieren.pipeline.flow.splines import warp_image

from .camera import CameraCapture, prepare_capture
from .motion import fit_flow_motion, motion_displacement, motion_extent, motion_field
from .params import CaptureParams
from .photometric import Photometric, normalise_frame
from .registration import BackgroundFit, register_background

__all__ = ["CaptureCorrection", "corrected_deflection", "corrected_crop_deflection", "moves", "stored_fit", "to_reference_grid", "MOTION_APPLIED",
           "PHOTOMETRIC_APPLIED", "FALLBACK", "NOT_CONVERGED", "GAIN_UNKNOWN", "SCREENED", "CAPTURE_STATS",
           "SCREEN_MARGIN"]

#: Bits of :attr:`CaptureCorrection.flags`. ``GAIN_UNKNOWN``: the frame's gain could not be
#: estimated (:meth:`~.photometric.Photometric.estimable`: a dark or clipped frame), so it
#: was not normalised. ``SCREENED``: the registration ended on its coarse levels (their fit
#: showed nothing to apply, :data:`SCREEN_MARGIN`).
MOTION_APPLIED, PHOTOMETRIC_APPLIED, FALLBACK, NOT_CONVERGED, GAIN_UNKNOWN, SCREENED = 1, 2, 4, 8, 16, 32
#: The registration's screen: when the fit of the coarse pyramid levels shows no motion,
#: gain or offset beyond this fraction of their tolerances and of ``significance`` times
#: its own standard deviations, the full-resolution level is not fitted: its result would
#: not be applied either. The coarse fit's standard deviations are about twice the
#: full-resolution fit's, so half the significance on them is the full fit's threshold;
#: half the tolerances leave a margin where the tolerances decide (large images, whose
#: fits are the most precise).
SCREEN_MARGIN = 0.5
#: Entries of :meth:`CaptureCorrection.stats` (the store's ``capture_fit``).
CAPTURE_STATS = ("static_fraction", "noise", "samples", "residual_motion", "flags")


@dataclass(frozen=True)
class CaptureCorrection:
    """What :func:`corrected_deflection` measured and removed.

    Attributes
    ----------
    motion : ndarray, shape (8,)
        The background's motion (:data:`~.motion.MOTION_PARAMS`): the registration's plus
        what the flow still showed on the static cells.
    fit : BackgroundFit
        The registration (its gain and offset profiles are the frame's).
    residual : float
        Largest displacement (pixels) of the motion the flow still showed on the static
        cells after the registration's was removed (before that, too, was removed).
    flags : int
        Bit sum of :data:`MOTION_APPLIED`, :data:`PHOTOMETRIC_APPLIED`, :data:`FALLBACK`,
        :data:`NOT_CONVERGED` and :data:`GAIN_UNKNOWN`.
    """

    motion: np.ndarray
    fit: BackgroundFit
    residual: float
    flags: int

    def stats(self) -> np.ndarray:
        """:data:`CAPTURE_STATS`: the static fraction of the image, the registration's
        residual noise (grey levels), its samples, :attr:`residual` and :attr:`flags`."""
        f = self.fit
        return np.array([f.static_fraction, f.noise, f.samples, self.residual, self.flags], np.float32)


def corrected_deflection(reference, frame: np.ndarray, flow: FlowParams = FlowParams(),
                         capture: CaptureParams = CaptureParams(), *, static: np.ndarray | None = None,
                         defects: np.ndarray | None = None, info: dict | None = None,
                         camera: CameraCapture | None = None,
                         fit: BackgroundFit | None = None) -> tuple[np.ndarray, CaptureCorrection]:
    """The deflection stage of one camera-frame with its motion, lighting and defective
    pixels removed.

    Parameters
    ----------
    reference : PreparedReference or ndarray, shape (H, W)
        The camera's reference background (prepared with ``flow``'s pre-smoothing and levels).
    frame : ndarray, shape (H, W)
    flow : FlowParams
    capture : CaptureParams
    static : ndarray, shape (H, W), bool, optional
        Pixels whose rays miss the volume (:func:`~.static_region.static_region`); None:
        every pixel may carry motion only (the plume is then told apart by the robust fits).
    defects : ndarray, shape (H, W), optional
        Defective pixels (non-zero; :func:`~.defects.find_defective_pixels`).
    info : dict, optional
        Passed to :func:`~schlieren.pipeline.flow.deflection_stage`.
    camera : CameraCapture, optional
        The camera's :func:`~.camera.prepare_capture` of ``reference``, ``flow``,
        ``capture``, ``static`` and ``defects`` (saves their preparation on every frame;
        ``static`` and ``defects`` are then not read).
    fit : BackgroundFit, optional
        The frame's registration when it is known already (e.g. :func:`stored_fit` of what
        the run's deflection task measured, for a flow measured again): used as step 1's
        result instead of measuring it; the rest is as without it.

    Returns
    -------
    flow : ndarray, shape (H // f, W // f, 2), float32
    correction : CaptureCorrection
    """
    from schlieren.pipeline.flow.reference import PreparedReference

    prep = reference if isinstance(reference, PreparedReference) else \
        prepare_reference(reference, presmooth=flow.presmooth, levels=flow.levels)
    H, W = prep.shape
    size = (W, H)
    cam = camera if camera is not None else prepare_capture(prep, flow, capture, static=static, defects=defects)
    pyramid = frame_pyramid(prep, frame)  # the registration's and, unless normalised, the flow's
    if fit is None:
        fit = register_background(prep, frame, model=capture.motion_model, photometric=capture.photometric,
                                  banding_rows=capture.banding_rows, region=cam.region, pyramid=pyramid,
                                  stop_early=functools.partial(_nothing_to_apply, capture=capture, prep=prep))
    flags = (FALLBACK if fit.fallback else 0) | (0 if fit.converged else NOT_CONVERGED) | \
        (SCREENED if fit.level > 0 else 0)
    img = frame
    if capture.photometric and not fit.photometric.estimable():
        flags |= GAIN_UNKNOWN
    elif _photometric_applies(fit, capture, prep):
        img, pyramid = normalise_frame(frame, fit.photometric), None
        flags |= PHOTOMETRIC_APPLIED
    warp_above, source = capture.warp_above, capture.motion_source  # read on every frame (test_params_wiring)
    motion = fit.motion.copy()
    extent = motion_extent(motion, size)
    moved = _motion_applies(fit, capture, size)
    bad = cam.invalid
    if moved:  # the frame's border shows what the reference does not hold
        bad = _border(cam.bad, (H, W), int(np.ceil(extent)) + 1)
    if moved and extent > warp_above:
        d = _flow_on_moved_reference(prep, img, flow, motion, size, bad, info)
    else:
        start = functools.partial(motion_displacement, motion, image_size=size) if moved else None
        d = deflection_stage(prep, img, flow, info=info, motion=start, invalid=bad, pyramid=pyramid)
    residual = float("nan")
    if capture.motion_model != "none":
        extra, finfo = fit_flow_motion(d, cam.cells, size, flow.factor, model=capture.motion_model)
        residual = motion_extent(extra, size)
        if not moved and _flow_confirms(fit.motion, extra, residual, finfo, capture, size):
            # the registration's motion beyond the tolerance was not applied (below its
            # significance against a noisy reference), but the flow's static cells confirm it
            moved, motion = True, np.zeros_like(motion)
        if moved:  # a bias left on every cell becomes a ramp of the masks' potential
            d = d - motion_field(extra, size, flow.factor)
            motion = motion + extra
        if moved:
            flags |= MOTION_APPLIED
            if source == "camera":
                d = to_reference_grid(d, motion, size, flow.factor)
    return d.astype(np.float32), CaptureCorrection(motion, fit, residual, flags)


def moves(fit: BackgroundFit, capture: CaptureParams, image_size) -> bool:
    """Whether :func:`corrected_deflection` applies ``fit``'s motion to a frame of
    ``image_size`` (width, height)."""
    return _motion_applies(fit, capture, tuple(image_size))


def corrected_crop_deflection(reference, frame: np.ndarray, flow: FlowParams = FlowParams(),
                              capture: CaptureParams = CaptureParams(), *, fit: BackgroundFit,
                              crop: tuple[int, int, int, int], whole, bad: np.ndarray | None = None) -> np.ndarray:
    """Steps 2 and 3 of :func:`corrected_deflection` on a crop of a frame, with a known
    registration that applies no motion (:func:`moves`; e.g. :func:`stored_fit` of a frame
    measured before): the frame's gain and offset removed at the crop's rows where the
    decision for the whole frame says so, the defective pixels weighted out, the flow of
    the crop. The motion the flow still shows on the static cells (step 4) is not fitted: the
    static cells lie mostly outside the crop, and the stored fit already holds it.

    Parameters
    ----------
    reference : PreparedReference or ndarray, shape (h, w)
        The crop of the reference (or of a reference resampled around a prediction).
    frame : ndarray, shape (h, w)
        The crop of the frame.
    flow, capture
        As :func:`corrected_deflection`'s.
    fit : BackgroundFit
        The frame's registration (image-wide row profiles).
    crop : (x0, y0, x1, y1)
        Where the crop lies in the image.
    whole : PreparedReference
        The camera's prepared reference over the whole image: its normalisation decides the
        gain and offset as for the whole frame.
    bad : ndarray, shape (H, W), bool, optional
        The camera's defective pixels over the whole image.

    Returns
    -------
    ndarray, shape (h // f, w // f, 2), float32
    """
    H, W = whole.shape
    if moves(fit, capture, (W, H)):
        raise ValueError("corrected_crop_deflection: the registration applies a motion; use corrected_deflection")
    x0, y0, x1, y1 = crop
    img = np.asarray(frame, np.float32)
    if fit.photometric.estimable() and _photometric_applies(fit, capture, whole):
        img = normalise_frame(img, fit.photometric, first_row=y0, image_rows=H)
    invalid = None if bad is None else np.asarray(bad, bool)[y0:y1, x0:x1]
    return deflection_stage(reference, img, flow, invalid=invalid)


def stored_fit(motion, photometric, stats, knots) -> BackgroundFit:
    """A frame's registration rebuilt from what :func:`corrected_deflection` returned and a
    run stores, for measuring the frame's flow again without registering it again.

    The motion is the correction's (the registration's plus what the flow still showed on
    the static cells, when a motion was applied), so a flow started from it has nothing
    left to remove there; the gain and offset profiles are the registration's. The
    standard deviations are not stored: they are set so that the decisions of
    :func:`corrected_deflection` are the stored flags' (0 where a correction was applied:
    its tolerance alone decides; where not, an infinite motion and an unknown (NaN) gain
    and offset deviation).

    Parameters
    ----------
    motion : array_like, shape (8,)
        :attr:`CaptureCorrection.motion`.
    photometric : array_like, shape (2, K)
        The gain and the offset at the knots.
    stats : array_like
        :meth:`CaptureCorrection.stats` (:data:`CAPTURE_STATS`).
    knots : array_like, shape (K,)
        Image rows of the profiles' knots (:func:`~.photometric.row_knots`).
    """
    st = dict(zip(CAPTURE_STATS, np.asarray(stats, np.float64)))
    flags = int(st["flags"])
    ph = np.asarray(photometric, np.float64)
    knots = np.asarray(knots, np.float64)
    applied = 0.0 if flags & PHOTOMETRIC_APPLIED else np.nan  # NaN: no estimate, never departs
    return BackgroundFit(np.asarray(motion, np.float64).copy(), Photometric(knots, ph[0].copy(), ph[1].copy()),
                         noise=float(st["noise"]), samples=int(st["samples"]),
                         static_fraction=float(st["static_fraction"]), fallback=bool(flags & FALLBACK),
                         converged=not flags & NOT_CONVERGED,
                         motion_sigma=0.0 if flags & MOTION_APPLIED else np.inf,
                         gain_sigma=np.full(len(knots), applied), level_sigma=np.full(len(knots), applied),
                         level=1 if flags & SCREENED else 0)


def _motion_applies(fit: BackgroundFit, capture: CaptureParams, size, margin: float = 1.0) -> bool:
    """Whether the registration's motion moves some pixel by more than ``margin`` times
    ``motion_tolerance`` and by more than ``margin`` times ``significance`` of its standard
    deviations."""
    extent = motion_extent(fit.motion, size)
    return capture.motion_model != "none" and extent > margin * capture.motion_tolerance and \
        not extent <= margin * capture.significance * fit.motion_sigma


def _flow_confirms(registered, flow_motion, extent: float, info: dict, capture: CaptureParams, size) -> bool:
    """Whether the flow's static cells confirm a registration's motion that was not applied:
    both beyond ``motion_tolerance``, the flow's fit significant (:func:`_flow_motion_applies`),
    and the two the same motion within half of it (their difference moves no pixel by more
    than half the registration's extent)."""
    reg = motion_extent(registered, size)
    return reg > capture.motion_tolerance and _flow_motion_applies(extent, info, capture) and \
        motion_extent(np.asarray(flow_motion) - np.asarray(registered), size) < 0.5 * reg


def _flow_motion_applies(extent: float, info: dict, capture: CaptureParams) -> bool:
    """Whether the motion the flow shows on the static cells (:func:`~.motion.fit_flow_motion`,
    largest displacement ``extent``) moves some pixel by more than ``motion_tolerance`` and by
    more than ``significance`` of its standard deviation (the fit's residual RMS over the
    square root of its cells: the translation's, a lower bound of the extent's)."""
    cells = int(info.get("cells", 0))
    if capture.motion_model == "none" or cells == 0 or not np.isfinite(extent):
        return False
    sigma = float(info.get("rms", np.inf)) / np.sqrt(cells)
    return extent > capture.motion_tolerance and extent > capture.significance * sigma


def _photometric_applies(fit: BackgroundFit, capture: CaptureParams, prep, margin: float = 1.0) -> bool:
    """Whether the registration's gain or offset departs from 1 or 0 by more than
    ``margin`` times their tolerances and by more than ``margin`` times ``significance`` of
    their standard deviations (:meth:`~.photometric.Photometric.departs`)."""
    return capture.photometric and fit.photometric.departs(
        gain_tolerance=margin * capture.gain_tolerance, offset_tolerance=margin * capture.offset_tolerance / prep.scale,
        mean=prep.mean, gain_sigma=fit.gain_sigma, level_sigma=fit.level_sigma,
        significance=margin * capture.significance)


def _nothing_to_apply(fit: BackgroundFit, *, capture: CaptureParams, prep) -> bool:
    """The screen of the registration's coarse levels (``stop_early`` of
    :func:`~.registration.register_background`): no motion, gain or offset beyond
    :data:`SCREEN_MARGIN` of the tolerances and of the significance, and a gain that can be
    estimated."""
    size = prep.shape[::-1]
    return not _motion_applies(fit, capture, size, SCREEN_MARGIN) and \
        not _photometric_applies(fit, capture, prep, SCREEN_MARGIN) and \
        (not capture.photometric or fit.photometric.estimable())


def _flow_on_moved_reference(prep, frame, flow: FlowParams, motion, size, bad, info) -> np.ndarray:
    """The deflection against the reference resampled at ``p + motion(p)`` (exact cubic
    B-splines), for motions beyond ``capture.warp_above``. The reference's defective pixels
    move with it: the invalid pixels grow by the motion's reach."""
    W, H = size
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    mx, my = motion_displacement(motion, x, y, size)
    ref = np.where(np.isfinite(prep.image), prep.image, np.float32(prep.mean)).astype(np.float32)
    moved = warp_image(ref, np.dstack([mx, my]).astype(np.float32))
    if bad is not None:
        r = int(np.ceil(motion_extent(motion, size))) + 2
        bad = cv2.dilate(bad.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
    return deflection_stage(prepare_reference(moved, presmooth=prep.presmooth, levels=flow.levels), frame, flow,
                            info=info, invalid=bad)


def _border(bad: np.ndarray | None, shape: tuple[int, int], width: int) -> np.ndarray:
    """``bad`` with a band of ``width`` pixels along the image's edges."""
    out = np.zeros(shape, bool) if bad is None else bad.copy()
    out[:width] = True
    out[-width:] = True
    out[:, :width] = True
    out[:, -width:] = True
    return out


def to_reference_grid(flow: np.ndarray, motion, image_size, factor: int) -> np.ndarray:
    """Deflections of a frame whose camera moved, on the reference's pixel grid:
    ``out(q) = flow(q - motion(q))`` (cubic B-spline interpolation on the flow grid; cells
    whose source lies next to a NaN cell stay NaN).

    Parameters
    ----------
    flow : ndarray, shape (h, w, 2)
    motion : array_like, shape (8,)
    image_size : (int, int)
    factor : int
    """
    shift = -motion_field(motion, image_size, factor) / np.float32(factor)  # flow cells
    bad = nonfinite_cells(flow)
    src = np.where(bad[..., None], 0.0, flow).astype(np.float32)
    out = np.dstack([warp_image(src[..., k], shift) for k in range(2)])
    if bad.any():
        near = cv2.dilate(bad.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        out[near] = np.nan
    return out
