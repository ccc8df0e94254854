"""``schlieren check``'s kernels: a rig's fitness for BOS, measured in seconds before any
reconstruction (issue 33).

Per camera: the sensor noise and the flow noise it predicts against the reference's
texture (:mod:`.noise`: the Lucas-Kanade window's Cramer-Rao bound, paper sec. 4), the
focus, exposure and hot pixels of the reference (:mod:`.image`), the global shift of a
few frames against the reference (:mod:`.motion`), the strobe flash (reusing
:mod:`schlieren.pipeline.sync`) and the volume's footprint (:mod:`.camera`); across the
rig, the focus against the best camera and the accuracy the benchmark family reached
with a rig like it (:mod:`.expect`). Reading the files is storage's
(:mod:`schlieren.storage.rigcheck`); the command is ``workers/commands/check.py``.
"""

from schlieren.pipeline.rigcheck.camera import CameraCheck, Footprint, check_camera, footprint
from schlieren.pipeline.rigcheck.expect import FamilyCase, expected_accuracy
from schlieren.pipeline.rigcheck.image import clipped_fractions, focus_energy, hot_pixels
from schlieren.pipeline.rigcheck.motion import GlobalShift, global_shift
from schlieren.pipeline.rigcheck.noise import predicted_flow_noise, sensor_noise, sensor_noise_from_pairs
from schlieren.pipeline.rigcheck.params import CheckParams

__all__ = ["CameraCheck", "CheckParams", "FamilyCase", "Footprint", "GlobalShift", "check_camera",
           "clipped_fractions", "expected_accuracy", "focus_energy", "footprint", "global_shift", "hot_pixels",
           "predicted_flow_noise", "sensor_noise", "sensor_noise_from_pairs"]
