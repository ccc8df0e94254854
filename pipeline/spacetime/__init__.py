"""Space-time reconstruction (beyond the paper): each frame's volume from its neighbours too.

The paper solves every frame alone (sec. 5). Here a second stage moves the per-frame
gradients of a frame's neighbours onto it along the motion between their volumes and
averages them (:func:`motion_compensated_mean`), which averages down the errors the frames
do not share. Modules: :mod:`.motion` (3D pyramidal Lucas-Kanade between two volumes and
the warp along it), :mod:`.average` (the motion-compensated mean over a window of frames)
and :mod:`.params` (:class:`SpaceTimeParams`).
"""

from schlieren.pipeline.spacetime.average import (
    SpaceTimeInfo,
    motion_compensated_mean,
    support_box,
    window_frames,
    window_weights,
)
from schlieren.pipeline.spacetime.motion import downsample2, upsample_motion, volume_motion, warp_volume
from schlieren.pipeline.spacetime.params import SpaceTimeParams

__all__ = ["SpaceTimeParams", "SpaceTimeInfo", "motion_compensated_mean", "window_frames", "window_weights", "support_box",
           "volume_motion", "warp_volume", "downsample2", "upsample_motion"]
