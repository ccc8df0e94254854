"""Calibration files and board images: everything of the calibration that touches files.

* :func:`resolve_source` / :func:`iter_board_frames` read one camera's board views from a
  video file, a folder of images or a glob pattern of images (view ``i`` = frame
  ``i * step`` of a video, or the ``i * step``-th image in name order).
* :func:`write_calibration` / :func:`read_calibration` store a calibrated rig as YAML,
  ``format: schlieren-calibration/1``, whose camera entries use the field names of the
  SPEC session manifest (``name, image_size, K, dist, R, t, background``) so that
  ``schlieren init`` copies them as they are; extra fields ``rms`` (pixels),
  ``n_views`` and ``n_points`` report the calibration's quality.

Example::

    format: schlieren-calibration/1
    board: {type: charuco, squares: [10, 7], square_size: 0.03, marker_size: 0.022,
            dictionary: DICT_5X5_100, legacy_pattern: false}
    world: {board_view: 0, orientation: flat, convention: "..."}
    cameras:
    - name: cam00
      image_size: [1440, 1080]
      K: [[3300.0, 0.0, 720.0], [0.0, 3300.0, 540.0], [0.0, 0.0, 1.0]]
      dist: [-0.1, 0.05, 0.0, 0.0, 0.0]
      R: [[...], [...], [...]]
      t: [0.0, 0.0, 2.5]
      rms: 0.12
      n_views: 24
      background: {point: [0.0, -2.5, 0.15], normal: [0.0, 1.0, 0.0]}   # or {distance: 5.0}

The package: :mod:`.board_views` (board views from videos and images, printable board
images), :mod:`.calibration_file` (the ``schlieren-calibration/1`` file) and
:mod:`.foreign` (calibrations of OpenCV and Kalibr read into that form).
"""

from schlieren.storage.calibration_io.board_views import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    BoardSource,
    iter_board_frames,
    read_image,
    resolve_source,
    write_print_image,
)
from schlieren.storage.calibration_io.calibration_file import (
    CALIBRATION_FORMAT,
    CalibrationFile,
    read_calibration,
    validate_camera_entry,
    write_calibration,
)
from schlieren.storage.calibration_io.foreign import import_calibration, read_kalibr_camchain, read_opencv_camera

__all__ = [
    "CALIBRATION_FORMAT",
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "BoardSource",
    "CalibrationFile",
    "resolve_source",
    "iter_board_frames",
    "read_image",
    "write_calibration",
    "read_calibration",
    "validate_camera_entry",
    "import_calibration",
    "write_print_image",
    "read_opencv_camera",
    "read_kalibr_camchain",
]
