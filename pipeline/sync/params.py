"""Parameters of the sync and resampling stages: :class:`FlashParams` (the strobe flash's
detection, :func:`~.strobe.detect_flash`) and :class:`ResampleParams` (the rolling-shutter
resampling, :func:`~.resample.resample_flow`, and the motion between flow fields it warps
along, :func:`~.motion.field_motion`). Their own module, so the kernels of both can take
their defaults from them."""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["FlashParams", "ResampleParams"]



@parameters
class FlashParams:
    """Parameters of :func:`~schlieren.pipeline.sync.detect_flash` (field names = its keyword names)."""

    min_snr: float = param(
        10.0, unit="1", gt=0, le=1e6,
        help="The flash band's brightening must exceed this many robust noise sigmas of the "
             "frame-to-frame row-mean fluctuations.")
    min_contrast: float = param(
        2.0, unit="grey levels", ge=0, le=65535,
        help="The flash band's brightening must also exceed this many grey levels.")


@parameters
class ResampleParams:
    """Parameters of :func:`~schlieren.pipeline.sync.resample_flow` (rolling-shutter resampling, paper sec. 4)."""

    method: str = param(
        "motion", choices=("motion", "linear", "nearest"),
        help="`motion`: warp between successive flow fields along the motion estimated between them (paper "
             "sec. 4); `linear`: per-row blend without motion; `nearest`: per row, the field nearest in time.")
    window: int = param(
        15, unit="flow cells", ge=3, le=101, odd=True,
        help="Window of the Lucas-Kanade motion estimate between flow fields.")
    levels: int = param(
        3, unit="1", ge=1, le=8,
        help="Pyramid levels of the motion estimate.")
    iterations: int = param(
        2, unit="1", ge=1, le=50,
        help="Warping iterations per level of the motion estimate.",
        tuned=True)
    regularisation: float = param(
        1e-2, unit="1", ge=0, le=1e3,
        help="Tikhonov weight of the motion estimate relative to the strongest structure: pulls the motion "
             "of flow-free regions to zero.")
    finest_level: int = param(
        1, unit="1", ge=0, le=7,
        help="Finest pyramid level the motion is estimated on (0: the flow grid itself); the levels below "
             "take it prolonged, since the motion between flow fields is smooth and a full-grid estimate "
             "mostly fits their noise.",
        tuned=True)
