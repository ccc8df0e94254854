"""``schlieren check``'s kernels: a rig's fitness for BOS, measured in seconds before any
reconstruction (issue 33).

Per camera: the sensor noise and the flow noise it predicts against the reference's
texture (:mod:`.noise`: the Lucas-Kanade window's Cramer-Rao bound, paper sec. 4), the
focus and exposure of the reference (:mod:`.image`), the motion of a few frames against
the reference and the defective pixels (the run's own kernels,
:mod:`schlieren.pipeline.capture`), the strobe flash (reusing
:mod:`schlieren.pipeline.sync`) and the volume's footprint (:mod:`.camera`); across the
rig, the focus against the best camera and the accuracy the benchmark family reached
with a rig like it (:mod:`.expect`). Reading the files is storage's
(:mod:`schlieren.storage.rigcheck`); the command is ``workers/check.py``.
"""

from schlieren.pipeline.rigcheck.camera import (CameraCheck, Footprint, FrameMotion, check_camera, footprint,
                                               frame_motions)
from schlieren.pipeline.rigcheck.expect import FLOW_NOISE_SHARE, FamilyCase, expected_accuracy, expected_psnr
from schlieren.pipeline.rigcheck.image import clipped_fractions, focus_energy
from schlieren.pipeline.rigcheck.noise import predicted_flow_noise, sensor_noise, sensor_noise_from_pairs
from schlieren.pipeline.rigcheck.params import CheckParams

__all__ = ["CameraCheck", "CheckParams", "FLOW_NOISE_SHARE", "FamilyCase", "Footprint", "FrameMotion", "check_camera",
           "clipped_fractions", "expected_accuracy", "expected_psnr", "focus_energy", "footprint", "frame_motions",
           "predicted_flow_noise", "sensor_noise", "sensor_noise_from_pairs"]
