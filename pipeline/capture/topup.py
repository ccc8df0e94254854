"""A reference of few frames topped up with the capture's own frames where nothing flows.

Paper sec. 4 measures every deflection against one reference background; its noise is the
same in every frame's flow (a fixed pattern), which the masks' potential integrates over
the whole image. A lab that records the reference from few frames gets a noisier potential,
a higher pooled mask threshold and a strict hull that carves plume voxels
(benchmarks/results/realistic_labgap.md). Where a camera's rays miss the volume
(:mod:`.static_region`) every capture frame shows the same background as the reference,
moved by the camera's motion and lit by the frame's lamp only: warped back by its fitted
motion (:func:`~.registration.register_background`, the registration the deflection stage
uses) and photometrically normalised to the reference (:func:`~.photometric.normalise_frame`),
such a frame is one more reference frame there. Inside the volume's image nothing is added:
a frame warped back by its *measured* flow would carry the flow error the reference's noise
causes, the same in every frame, and build a reference displaced by it.

The reference weighs as many frames in the average as its noise, measured against the frames,
is worth; the per-pixel count of averaged frames is returned with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import cv2
import numpy as np
from scipy import ndimage

from schlieren.pipeline.flow.reference import PreparedReference

from .motion import motion_displacement, motion_extent
from .params import CaptureParams
from .photometric import normalise_frame
from .registration import SampleRegion, register_background

__all__ = ["ReferenceTopup", "topup_reference", "reference_equivalent_frames", "warp_to_reference", "OUTLIER_NOISE", "SPLINE_ORDER"]

#: A frame whose residual against the reference on the static pixels (after its motion and
#: lighting are removed) exceeds this multiple of the median residual of the frames read is
#: not averaged in (a flash, a frame that moved in a way the model does not hold).
OUTLIER_NOISE = 1.5
#: Order of the B-splines that move a frame back onto the reference's grid.
SPLINE_ORDER = 5
#: Pixels of the image border left out beyond the motion's extent (the cubic spline's reach).
_BORDER = 3


@dataclass(frozen=True)
class ReferenceTopup:
    """What :func:`topup_reference` made.

    Attributes
    ----------
    reference : ndarray, shape (H, W), float32
        The reference with the frames added where nothing flows (bit for bit the input
        reference on every other pixel).
    count : ndarray, shape (H, W), float32
        Frames averaged at each pixel: the reference's :attr:`equivalent` frames plus the
        capture frames averaged in there.
    frames : int
        Capture frames averaged in (0: the reference was kept as it is).
    rejected : int
        Frames read but not averaged in (a registration that did not converge or fell back to
        every pixel, a gain that cannot be estimated, or a residual above :data:`OUTLIER_NOISE`
        times the frames' median).
    equivalent : float
        The reference's noise in capture frames (:func:`reference_equivalent_frames`): its
        weight in the average.
    """

    reference: np.ndarray
    count: np.ndarray
    frames: int
    rejected: int
    equivalent: float


def warp_to_reference(frame: np.ndarray, motion, *, iterations: int = 2) -> np.ndarray:
    """A frame moved back onto the reference's pixel grid.

    The motion says ``frame(p) ~= reference(p + motion(p))``, so the reference's pixel ``q`` is
    seen at ``p`` with ``p + motion(p) = q``: found by fixed-point steps ``p = q - motion(p)``
    (the motion is sub-pixel and smooth: two steps are exact to far below its noise), and the
    frame sampled there with quintic B-splines (:data:`SPLINE_ORDER`). The flow's cubic splines
    at a fraction of a pixel smooth a fine texture by as much as a frame's sensor noise, the
    same in every frame: a bias that the average would keep.

    Parameters
    ----------
    frame : ndarray, shape (H, W)
    motion : array_like, shape (8,)
        :data:`~.motion.MOTION_PARAMS`.

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    img = np.asarray(frame, np.float32)
    H, W = img.shape
    y, x = np.mgrid[0:H, 0:W]
    return _sample(_coefficients(img), motion, y.ravel(), x.ravel(), iterations=iterations).reshape(H, W)


def _coefficients(img: np.ndarray) -> np.ndarray:
    """The image's B-spline coefficients of :data:`SPLINE_ORDER` (mirrored at the border)."""
    return ndimage.spline_filter(np.asarray(img, np.float64), order=SPLINE_ORDER, mode="mirror")


def _sample(coeffs: np.ndarray, motion, y: np.ndarray, x: np.ndarray, *, iterations: int = 2) -> np.ndarray:
    """The image of B-spline coefficients ``coeffs`` moved back by ``motion``, at the reference's
    pixels ``(y, x)`` (:func:`warp_to_reference`), float32."""
    H, W = coeffs.shape
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    px, py = x, y
    for _ in range(max(int(iterations), 1)):
        dx, dy = motion_displacement(motion, px, py, (W, H))
        px, py = x - dx, y - dy
    return ndimage.map_coordinates(coeffs, [py, px], order=SPLINE_ORDER, mode="mirror",
                                   prefilter=False).astype(np.float32)


def topup_reference(reference: PreparedReference, raw: np.ndarray, frames: Iterable[np.ndarray], *,
                    n_reference: int, static: np.ndarray, region: SampleRegion,
                    defects: np.ndarray | None = None, max_frames: float = CaptureParams.topup_below,
                    capture: CaptureParams = CaptureParams()) -> ReferenceTopup:
    """Average capture frames into a reference on the pixels whose rays miss the volume.

    Each frame is registered against the reference on the static pixels (motion, gain and
    offset profiles: :func:`~.registration.register_background` with ``capture``'s model),
    normalised (when ``capture.photometric``), moved back onto the reference's grid
    (:func:`warp_to_reference`) and added to the sum on the static pixels it covers. The
    reference weighs as many frames as its measured noise is worth
    (:func:`reference_equivalent_frames`, ``n_eff``); the result there is
    ``(n_eff * reference + sum of the frames) / (n_eff + frames)``. A reference worth
    ``max_frames`` or more (a noise-free rendered one, say) is kept as it is.

    Parameters
    ----------
    reference : PreparedReference
        The camera's reference prepared as its flows use it (the registration's pyramid).
    raw : ndarray, shape (H, W), float32
        The reference itself (the mean of its ``n_reference`` frames, not pre-smoothed).
    frames : iterable of ndarray, shape (H, W)
        Capture frames (grey levels).
    n_reference : int
        Frames the reference averages.
    static : ndarray, shape (H, W), bool
        Pixels whose rays miss the volume (:func:`~.static_region.static_region`).
    region : SampleRegion
        The registration's samples (:func:`~.registration.sample_region` of ``static``).
    defects : ndarray, shape (H, W), optional
        Defective pixels (non-zero; :func:`~.defects.find_defective_pixels`): they and the
        pixels within the cubic spline's reach of them (whose warped values they touch) are
        not averaged.
    max_frames : float
        ``capture.topup_below``.
    capture : CaptureParams

    Returns
    -------
    ReferenceTopup
    """
    ref = np.asarray(raw, np.float32)
    H, W = ref.shape
    n_ref = max(int(n_reference), 1)
    usable = np.asarray(static, bool).copy()
    if defects is not None and np.any(defects):
        near = cv2.dilate((np.asarray(defects) != 0).astype(np.uint8), np.ones((2 * _BORDER + 1,) * 2, np.uint8))
        usable &= near == 0
    moved, rejected = [], 0
    if not region.fallback and not region.empty and usable.any():
        for frame in frames:
            f = _normalised_frame(reference, frame, region, capture)
            if f is None:
                rejected += 1
            else:
                moved.append(f)
    warped = [_warp(img, m, usable) for img, m in moved]
    noise = [np.sqrt(_robust_var((img - ref)[ok])) for img, ok in warped]
    keep = [i for i, s in enumerate(noise) if np.isfinite(s) and s <= OUTLIER_NOISE * float(np.median(noise))]
    rejected += len(warped) - len(keep)
    if keep:  # the registrations' common error, measured on their average and removed
        d = _common_motion(reference, ref, [warped[i] for i in keep], region, capture)
        warped = [_warp(moved[i][0], moved[i][1] + d, usable) for i in keep]
    else:
        warped = []
    keep = list(range(len(warped)))
    n_eff = reference_equivalent_frames(ref, warped, n_reference=n_ref)
    count = np.full((H, W), n_eff, np.float32)
    if not keep or n_eff >= max_frames:
        return ReferenceTopup(ref, count, 0, rejected, n_eff)
    acc = np.zeros((H, W), np.float64)
    added = np.zeros((H, W), np.int32)
    for i in keep:
        img, ok = warped[i]
        acc[ok] += img[ok]
        added[ok] += 1
    out = ref.copy()
    t = added > 0
    out[t] = ((ref[t] * n_eff + acc[t]) / (n_eff + added[t])).astype(np.float32)
    count[t] += added[t]
    return ReferenceTopup(out, count, len(keep), rejected, n_eff)


def reference_equivalent_frames(reference: np.ndarray, warped: list, *, n_reference: int) -> float:
    """How many capture frames the reference's noise is worth, measured on the static pixels.

    A frame moved back onto the reference's grid differs from the reference by both their
    noises, ``s_f^2 + s_r^2``; two such frames differ by ``2 s_f^2``. The reference weighs
    ``s_f^2 / s_r^2`` frames: ``n_reference`` for a reference averaged from ``n_reference``
    frames of the capture's noise, unbounded for a noise-free (rendered) one. Variances of the
    differences without their outliers (:func:`_robust_var`), the median over frames and pairs; with fewer than two frames, ``n_reference``.

    Parameters
    ----------
    reference : ndarray, shape (H, W)
    warped : list of (ndarray, ndarray)
        Frames moved back onto the reference's grid and their usable static pixels
        (:func:`_warped_frame`).
    n_reference : int
        The reference's frames.
    """
    if len(warped) < 2:
        return float(n_reference)
    to_ref = [_robust_var(img[ok] - reference[ok]) for img, ok in warped]
    pairs = [_robust_var(a[m] - b[m]) / 2.0 for (a, oa), (b, ob) in zip(warped[:-1], warped[1:])
             for m in (oa & ob,)]
    frame_var = float(np.median(pairs))
    ref_var = float(np.median(to_ref)) - frame_var
    return frame_var / ref_var if ref_var > 0 else float("inf")


def _robust_var(x: np.ndarray, *, clip: float = 4.0, iterations: int = 3) -> float:
    """The variance of ``x`` with values beyond ``clip`` standard deviations from the mean left
    out (iterated): robust to a few outliers, and unlike a median absolute deviation exact on
    integer grey levels (8-bit frames' differences)."""
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return float("nan")
    keep = x
    for _ in range(iterations):
        m, sd = float(np.mean(keep)), float(np.std(keep))
        keep = x[np.abs(x - m) <= clip * sd] if sd > 0 else keep
    return float(np.var(keep))


def _normalised_frame(reference: PreparedReference, frame, region: SampleRegion, capture: CaptureParams):
    """One frame normalised to the reference's lighting, as B-spline coefficients
    (:func:`_coefficients`), and its motion; None when its registration cannot be trusted."""
    fit = register_background(reference, frame, model=capture.motion_model, photometric=capture.photometric,
                              banding_rows=capture.banding_rows, region=region)
    if fit.fallback or not fit.converged or (capture.photometric and not fit.photometric.estimable()):
        return None
    img = normalise_frame(frame, fit.photometric) if capture.photometric else np.asarray(frame, np.float32)
    return _coefficients(img), fit.motion


def _warp(coeffs: np.ndarray, motion: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frame of B-spline coefficients ``coeffs`` moved back onto the reference's grid by
    ``motion`` on the usable static pixels it covers (away from the border by the motion and
    the spline's reach; NaN elsewhere), and those pixels."""
    H, W = coeffs.shape
    b = int(np.ceil(motion_extent(motion, (W, H)))) + _BORDER
    ok = usable.copy()
    ok[:b], ok[H - b:], ok[:, :b], ok[:, W - b:] = False, False, False, False
    y, x = np.nonzero(ok)
    out = np.full((H, W), np.nan, np.float32)
    out[y, x] = _sample(coeffs, motion, y, x)
    return out, ok & np.isfinite(out)


def _common_motion(reference: PreparedReference, ref: np.ndarray, warped: list, region: SampleRegion,
                   capture: CaptureParams) -> np.ndarray:
    """The motion of the warped frames' average against the reference, on the static pixels.

    Each registration against a noisy reference errs by much the same sub-pixel amount in every
    frame (the noise, resampled at a fraction of a pixel, favours some fractions): frames moved
    back by it sit slightly off the reference's grid. Their average sits there too, a
    displacement its own registration (near zero motion, where that error vanishes) measures and
    that is then added to every frame's motion: the topped-up static region stays on the grid of
    the rest of the reference (a displacement between the two is a bias of every flow inside
    the volume's image against the static cells its motion is fitted on). Applied as measured:
    shrinking it by its own noise (``1 - (sigma / extent)^2``) lowered the results it was
    meant to protect (benchmarks/results/reference_topup.md)."""
    acc = np.zeros(ref.shape, np.float64)
    n = np.zeros(ref.shape, np.int32)
    for img, ok in warped:
        acc[ok] += img[ok]
        n[ok] += 1
    mean = ref.astype(np.float64)
    mean[n > 0] = acc[n > 0] / n[n > 0]
    return register_background(reference, mean.astype(np.float32), model=capture.motion_model, photometric=False,
                               region=region).motion
