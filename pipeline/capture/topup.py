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

The per-pixel count of averaged frames is returned with the reference (the reference's frames
where nothing was added).
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

__all__ = ["ReferenceTopup", "topup_reference", "warp_to_reference", "OUTLIER_NOISE", "SPLINE_ORDER"]

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
    count : ndarray, shape (H, W), uint16
        Frames averaged at each pixel (the reference's own included).
    frames : int
        Capture frames averaged in.
    rejected : int
        Frames read but not averaged in (a registration that did not converge or fell back to
        every pixel, a gain that cannot be estimated, or a residual above :data:`OUTLIER_NOISE`
        times the frames' median).
    """

    reference: np.ndarray
    count: np.ndarray
    frames: int
    rejected: int


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
    img = np.asarray(frame, np.float64)
    H, W = img.shape
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    px, py = x, y
    for _ in range(max(int(iterations), 1)):
        dx, dy = motion_displacement(motion, px, py, (W, H))
        px, py = x - dx, y - dy
    out = ndimage.map_coordinates(img, [py, px], order=SPLINE_ORDER, mode="mirror")
    return out.astype(np.float32)


def topup_reference(reference: PreparedReference, raw: np.ndarray, frames: Iterable[np.ndarray], *,
                    n_reference: int, static: np.ndarray, region: SampleRegion,
                    defects: np.ndarray | None = None,
                    capture: CaptureParams = CaptureParams()) -> ReferenceTopup:
    """Average capture frames into a reference on the pixels whose rays miss the volume.

    Each frame is registered against the reference on the static pixels (motion, gain and
    offset profiles: :func:`~.registration.register_background` with ``capture``'s model),
    normalised (when ``capture.photometric``), moved back onto the reference's grid
    (:func:`warp_to_reference`) and added to the sum on the static pixels it covers. The
    result there is ``(n_reference * reference + sum of the frames) / count``.

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
    warped, noise, rejected = [], [], 0
    if not region.fallback and not region.empty and usable.any():
        for frame in frames:
            w = _warped_frame(reference, frame, region, usable, capture)
            if w is None:
                rejected += 1
                continue
            img, ok = w
            r = (img - ref)[ok]
            noise.append(1.4826 * float(np.median(np.abs(r - np.median(r)))) if r.size else np.inf)
            warped.append(w)
    keep = [i for i, s in enumerate(noise) if np.isfinite(s) and s <= OUTLIER_NOISE * float(np.median(noise))]
    rejected += len(warped) - len(keep)
    acc = ref.astype(np.float64) * n_ref
    count = np.full((H, W), n_ref, np.uint16)
    for i in keep:
        img, ok = warped[i]
        acc[ok] += img[ok]
        count[ok] += 1
    out = (acc / count).astype(np.float32)
    return ReferenceTopup(out, count, len(keep), rejected)


def _warped_frame(reference: PreparedReference, frame, region: SampleRegion, usable: np.ndarray,
                  capture: CaptureParams):
    """One frame registered, normalised and moved back onto the reference's grid, with the
    usable static pixels it covers; None when its registration cannot be trusted."""
    H, W = reference.shape
    fit = register_background(reference, frame, model=capture.motion_model, photometric=capture.photometric,
                              banding_rows=capture.banding_rows, region=region)
    if fit.fallback or not fit.converged or (capture.photometric and not fit.photometric.estimable()):
        return None
    img = normalise_frame(frame, fit.photometric) if capture.photometric else np.asarray(frame, np.float32)
    img = warp_to_reference(img, fit.motion)
    b = int(np.ceil(motion_extent(fit.motion, (W, H)))) + _BORDER
    ok = usable.copy()
    ok[:b], ok[H - b:], ok[:, :b], ok[:, W - b:] = False, False, False, False
    ok &= np.isfinite(img)
    return img, ok
