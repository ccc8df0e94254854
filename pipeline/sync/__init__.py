"""Strobe synchronisation and rolling-shutter / inter-camera resampling of flow fields.

Paper section 4 ("Camera synchronization", Figure 5). Timing model (SPEC, docs/design.md):
row ``r`` of frame ``f`` of a camera starts its exposure at
``offset + f / frame_rate + r * line_time`` on the session clock.

* Strobe: a flash of negligible duration at session time ``t = 0`` brightens every row
  whose exposure interval ``[start, start + exposure)`` contains 0. The lower edge of the
  lit band (the last row with ``start <= 0``) gives the camera's offset to within one line
  time (:func:`detect_flash`, :func:`offset_from_flash`). Frames carrying the flash are
  never used as data (:func:`flash_frames`).
* Resampling: each camera's flow fields are resampled to common instants
  (:func:`output_times`) row by row, by warping between successive flow fields with the
  motion estimated between those fields, each row weighted by its own time offset
  (:func:`resample_flow`). Flow fields are smooth, so warping them (rather than the raw
  images) keeps the high frequencies the optical flow needs (paper sec. 4).

Modules: :mod:`.params` (:class:`FlashParams`, :class:`ResampleParams`), :mod:`.strobe`
(flash detection and the offset it gives), :mod:`.timing` (row times, output instants, the
frames an instant needs), :mod:`.motion` (the motion between two flow fields and its
per-process cache) and :mod:`.resample` (the row-wise resampling).
"""

from .motion import cached_field_motion, field_digest, field_motion
from .params import FlashParams, ResampleParams
from .resample import resample_flow
from .strobe import FlashDetection, detect_flash, flash_frames, offset_from_flash, row_means
from .timing import frames_needed, output_times, row_times

__all__ = [
    "FlashDetection",
    "FlashParams",
    "ResampleParams",
    "row_means",
    "detect_flash",
    "offset_from_flash",
    "flash_frames",
    "row_times",
    "output_times",
    "frames_needed",
    "field_motion",
    "resample_flow",
    "field_digest",
    "cached_field_motion",
]
