"""Parameters of ``schlieren check`` (:class:`CheckParams`): what it reads and when it warns."""

from __future__ import annotations

from schlieren.pipeline.params import param, parameters

__all__ = ["CheckParams"]


@parameters
class CheckParams:
    """What ``schlieren check`` measures on, and the limits above which it warns."""

    motion_frames: int = param(
        3, unit="1", ge=1, le=100,
        help="Frames of the capture (spread over the frames to process) whose motion against the reference is "
             "measured (with the run's `capture` parameters); they also join the defective-pixel test.")
    max_shift: float = param(
        0.02, unit="px", ge=0, le=100,
        help="A camera whose frames moved more than this against the reference is flagged.")
    max_flow_noise: float = param(
        0.03, unit="px", gt=0, le=100,
        help="A camera whose predicted flow noise exceeds this is flagged (a tenth of the weakest "
             "deflections worth reconstructing).")
    max_flow_noise_excess: float = param(
        1.3, unit="1", gt=1, le=100,
        help="A camera whose predicted flow noise exceeds this multiple of what the benchmark family's in-focus "
             "background gives at its LK window is flagged (at its own sensor noise: out of focus or a weak "
             "texture; at the family's: a noisy sensor).")
    min_focus_ratio: float = param(
        0.7, unit="1", ge=0, le=1,
        help="A camera whose finest-scale texture energy is below this fraction of the rig's best "
             "camera is flagged (out of focus, or a coarser view of the background).")
    max_clipped: float = param(
        0.01, unit="1", ge=0, le=1,
        help="A camera with more than this fraction of its reference's pixels clipped black or white "
             "is flagged.")
