"""Multi-camera calibration from ChArUco board views (paper sec. 4: "calibrated with
standard techniques" [Zhang 1999]).

The steps, all on arrays (file reading lives in :mod:`schlieren.storage.calibration_io`):

1. :func:`detect_board` finds the ChArUco chessboard corners in one image.
2. :func:`calibrate_intrinsics` runs Zhang's planar calibration for one camera
   (``cv2.calibrateCamera``): ``K``, distortion and one board pose per view.
3. :func:`calibrate_rig` chains the board poses seen by several cameras in the same
   view into camera-to-camera poses, then refines every camera's intrinsics,
   distortion and pose and every board pose jointly by bundle adjustment
   (``scipy.optimize.least_squares`` on a Huber cost, block-structured
   finite-difference Jacobian), and finally expresses the rig in the world frame
   defined by one board view.
4. :func:`background_plane` fits each camera's background plane from views of a
   board laid on the background.

Conventions
-----------
*Views*: view ``i`` of every camera shows the same board pose (frame ``i`` of
synchronised videos, or the ``i``-th image of each camera's image list); a camera
may miss the board in some views (``None``). Cameras are linked through the views
they share.

*Board frame* (OpenCV): origin at the outer top-left corner of the printed board,
``x`` along its ``squares[0]`` columns, ``y`` down the ``squares[1]`` rows of the
printed image, ``z = x cross y`` into the board (away from a viewer of the face).

*World frame* (SPEC: right-handed, ``z`` up, metres): the board pose in view
``world_board_view`` defines it, with its origin at the centre of the board's
chessboard area, and

* ``world_board_orientation="flat"`` (board lying face-up on a horizontal table):
  ``x`` along the board's columns, ``z`` out of the printed face (up),
  ``y = z cross x``;
* ``world_board_orientation="upright"`` (board standing vertically, printed top
  edge up): ``x`` along the board's columns, ``z`` towards the printed top edge
  (up), ``y`` into the board, away from its face.

Cameras are returned as SPEC camera entries: ``x_cam = R @ x_world + t``.

Modules: :mod:`.board` (the board, detection), :mod:`.projection` (camera model, poses,
PnP), :mod:`.intrinsics` (step 2), :mod:`.rig` and :mod:`.bundle` (step 3),
:mod:`.background` (step 4), :mod:`.renderer` (synthetic board views with known poses).
"""

from schlieren.pipeline.calibration.background import background_plane
from schlieren.pipeline.calibration.board import BoardDetection, BoardSpec, CalibrationError, detect_board
from schlieren.pipeline.calibration.intrinsics import IntrinsicCalibration, calibrate_intrinsics
from schlieren.pipeline.calibration.projection import board_pose, project_points
from schlieren.pipeline.calibration.renderer import BoardRenderer
from schlieren.pipeline.calibration.rig import (CalibrationParams, CameraCalibration, RigCalibration, calibrate_rig,
                                                world_from_board)

__all__ = [
    "BoardSpec",
    "BoardDetection",
    "BoardRenderer",
    "CalibrationError",
    "CalibrationParams",
    "IntrinsicCalibration",
    "CameraCalibration",
    "RigCalibration",
    "detect_board",
    "board_pose",
    "calibrate_intrinsics",
    "calibrate_rig",
    "background_plane",
    "world_from_board",
    "project_points",
]
