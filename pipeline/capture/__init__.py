"""Corrections for what a lab capture adds to the flow (issue 33): the camera or the
background moving against the reference, the lighting changing (flicker, and the row
banding of a rolling shutter under mains-frequency light), and defective sensor pixels.

Paper sec. 4 computes each deflection field against one reference background, and
assumes that only the flow changed in between. Real deflections are a few tenths of a
pixel: a tripod that moves by a tenth of a pixel, or a lamp that flickers by 2 %, moves
every deflection by as much. Modules:

* :mod:`.static_region`: the pixels whose rays miss the reconstruction box (no
  deflection there: only motion and lighting);
* :mod:`.motion`: the motion model (translation, affine, homography) and its robust fit
  to a flow field;
* :mod:`.photometric`: gain and offset profiles over the rows, and their removal;
* :mod:`.registration`: motion, gain and offset measured together on the static pixels
  (robust Gauss-Newton on the flow's own pyramid), before the flow;
* :mod:`.defects`: hot, dead and stuck pixels from the frames;
* :mod:`.camera`: what a camera's frames share, prepared once (the registration's
  samples, the defective pixels prepared for the flow, the cells of the motion's refit);
* :mod:`.correction`: the per camera-frame kernel that chains them around the flow;
* :mod:`.topup`: a reference of few frames topped up with the capture's frames where
  nothing flows;
* :mod:`.params`: :class:`CaptureParams`.
"""

from .camera import CameraCapture, prepare_capture
from .correction import (CAPTURE_STATS, FALLBACK, GAIN_UNKNOWN, MOTION_APPLIED, NOT_CONVERGED, PHOTOMETRIC_APPLIED,
                         SCREEN_MARGIN, SCREENED, CaptureCorrection, corrected_crop_deflection, corrected_deflection,
                         moves, stored_fit, to_reference_grid)
from .defects import DEAD, DEFECT_NAMES, HOT, STUCK, defect_counts, find_defective_pixels, valid_pixels
from .motion import (MOTION_PARAMS, fit_flow_motion, motion_displacement, motion_extent, motion_field,
                     motion_size, motion_summary, no_motion)
from .params import MOTION_MODELS, CaptureParams
from .photometric import MIN_GAIN, Photometric, identity_photometric, normalise_frame, row_knots, row_profile
from .registration import BackgroundFit, SampleRegion, register_background, sample_region
from .static_region import box_footprint, static_cells, static_region
from .topup import ReferenceTopup, topup_reference, warp_to_reference

__all__ = ["CaptureParams", "MOTION_MODELS", "MOTION_PARAMS", "BackgroundFit", "CaptureCorrection", "Photometric",
           "CameraCapture", "SampleRegion", "register_background", "sample_region", "prepare_capture",
           "corrected_deflection", "corrected_crop_deflection", "moves", "stored_fit", "to_reference_grid", "find_defective_pixels",
           "defect_counts", "valid_pixels", "static_region", "static_cells", "box_footprint", "motion_displacement",
           "motion_field", "motion_extent", "motion_summary", "motion_size", "no_motion", "fit_flow_motion",
           "normalise_frame", "identity_photometric", "row_knots", "row_profile", "HOT", "DEAD", "STUCK",
           "DEFECT_NAMES", "CAPTURE_STATS", "MOTION_APPLIED", "PHOTOMETRIC_APPLIED", "FALLBACK", "NOT_CONVERGED",
           "GAIN_UNKNOWN", "SCREENED", "SCREEN_MARGIN", "MIN_GAIN", "ReferenceTopup", "topup_reference",
           "warp_to_reference"]
