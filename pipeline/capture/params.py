"""The run parameters of the capture corrections (:class:`CaptureParams`): camera motion
against the reference, photometric normalisation and defective pixels.

A group of the run configuration (``RunConfig.capture``), declared like every run
parameter (:func:`~schlieren.pipeline.params.parameters`).
"""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["CaptureParams", "MOTION_MODELS"]

#: Models of the background's motion against the reference.
MOTION_MODELS = ("none", "translation", "affine", "homography")


@parameters
class CaptureParams:
    """Corrections for what a lab capture adds to the flow: the camera (or background)
    moving against its reference, the lighting changing, and defective sensor pixels.
    """

    motion_model: str = param(
        "affine", choices=MOTION_MODELS,
        help="How the background may move against the reference, per camera-frame: `affine` (a shift, rotation, "
             "scale and shear of the image), `homography` (adds the two projective terms of a camera tilting in "
             "front of a plane), `translation`, or `none` (no motion estimated).")
    motion_source: str = param(
        "camera", choices=("camera", "background"),
        help="What moved: `camera` (it turned on its mount: it sees the plume, too, through other pixels, so the "
             "deflections are moved back onto the reference's pixel grid, where the calibration's rays are) or "
             "`background` (the plume stays on its pixels).")
    warp_above: float = param(
        0.4, unit="px", ge=0, le=1000,
        help="A motion that moves some pixel by more than this is removed by resampling the reference at the moved"
             " positions (cubic B-splines) before the flow; a smaller one by starting the flow from it "
             "(Lucas-Kanade then warps the reference by it in its own spline warp, with no extra resampling).")
    static_margin: float = param(
        16.0, unit="px", ge=0, le=1000,
        help="Image pixels between the volume box's image and the pixels the motion and the lighting are measured "
             "on (the flow window's reach, and a plume leaving the box).")
    min_static_fraction: float = param(
        0.05, unit="1", ge=0, le=1,
        help="Below this fraction of the image outside the box, the motion is measured on every pixel with weights"
             " that ignore the plume's (large-residual) pixels, and refined on the flow's low-deflection cells.")
    motion_tolerance: float = param(
        0.005, unit="px", ge=0, le=100,
        help="The measured motion is applied only when it moves some pixel of the image by more than this (and by "
             "more than `significance` standard deviations): smaller motions change the flow by less than its "
             "noise, and a capture without motion keeps exactly the flow it had without these corrections.")
    significance: float = param(
        10.0, unit="1", ge=0, le=1e6,
        help="A measured motion, gain or offset is removed only where it also exceeds this many of its standard "
             "deviations (from the fit's noise and normal equations): below, it cannot be told from the fit's own "
             "noise.")
    motion_warning: float = param(
        0.5, unit="px", gt=0, le=1000,
        help="A camera-frame whose motion moves some pixel by more than this is named in the run's warnings (once "
             "per camera, with its frames).")
    photometric: bool = param(
        True,
        help="Estimate each frame's gain and offset against the reference, as smooth profiles over the image rows "
             "(lamp flicker, and the row banding of a rolling shutter under mains-frequency light), and remove "
             "them before the flow.")
    banding_rows: int = param(
        48, unit="px", ge=4, le=100000,
        help="Image rows between the knots of the gain and offset profiles (piecewise linear in the row): the "
             "shortest banding period followed is about three times this. At least the image height gives one gain"
             " and one offset per frame.")
    gain_tolerance: float = param(
        0.002, unit="1", ge=0, le=1,
        help="The photometric correction is applied only when, at some knot, the gain departs from 1 by more than "
             "this, or the reference's mean grey level moves by more than `offset_tolerance` (and by more than "
             "`significance` standard deviations).")
    offset_tolerance: float = param(
        0.002, unit="1", ge=0, le=1000,
        help="See `gain_tolerance`; a fraction of the reference's grey-level standard deviation (the flow responds"
             " to an offset relative to the background's contrast).")
    defective_pixels: bool = param(
        True,
        help="Find hot, dead and stuck pixels from the reference frames and a sample of the capture frames, and "
             "give them no weight in the flow and the corrections.")
    defect_threshold: float = param(
        10.0, unit="1", gt=0, le=1000,
        help="A pixel is hot (dead) when it stands above (below) the quadratic prediction from its 8 neighbours by"
             " more than this many robust standard deviations of that residual in every frame read, and is the "
             "strongest such pixel of its 3 x 3 neighbourhood.")
    stuck_ratio: float = param(
        0.1, unit="1", ge=0, lt=1,
        help="A pixel is stuck when its standard deviation over the frames read is below this fraction of the "
             "smallest standard deviation of its 8 neighbours.")
    defect_frames: int = param(
        8, unit="frames", ge=0, le=1000,
        help="Capture frames read (evenly spread over the processed range) beside the reference frames to find "
             "defective pixels. More frames find more stuck pixels: one is flagged only where a normal pixel would "
             "not keep its values that close by chance.")
    reference_topup: int = param(
        16, unit="frames", ge=0, le=1000,
        help="Capture frames (evenly spread over the session) averaged into a reference of fewer than "
             "`topup_below` frames where the camera's rays miss the volume, each moved back by its fitted motion "
             "and normalised to the reference's lighting: a reference of few frames carries its noise into every "
             "flow. 0: off.", see="benchmarks/results/reference_topup.md", tuned=True)
    topup_below: int = param(
        8, unit="frames", ge=0, le=100000,
        help="Only a reference of 2 or more but fewer frames than this, whose noise measured against the capture "
             "frames is worth fewer capture frames too, is topped up (`reference_topup`): one of many frames, a "
             "noise-free one, or a single image (whose worth would cost the measurement itself) is left as it is.", see="benchmarks/results/reference_topup.md", tuned=True)
