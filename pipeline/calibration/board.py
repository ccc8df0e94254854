"""The ChArUco board: its specification, its OpenCV objects and corner detection.

A :class:`BoardSpec` fixes the printed board (squares, marker size, ArUco dictionary);
:func:`detect_board` finds its inner chessboard corners in one image, the first step of
the calibration (:mod:`schlieren.pipeline.calibration`). The board frame (OpenCV): origin
at the outer top-left corner of the printed board, ``x`` along its ``squares[0]`` columns,
``y`` down the ``squares[1]`` rows, ``z = x cross y`` into the board.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["CalibrationError", "BoardSpec", "BoardDetection", "detect_board"]


class CalibrationError(ValueError):
    """The board views cannot calibrate a camera; ``camera`` names it (or is None)."""

    def __init__(self, message: str, *, camera: str | None = None):
        self.camera = camera
        super().__init__(message)


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board.

    Parameters
    ----------
    squares : tuple of int
        ``(columns, rows)`` of chessboard squares, e.g. ``(10, 7)``.
    square_size : float
        Edge of a chessboard square, metres.
    marker_size : float
        Edge of an ArUco marker, metres (< ``square_size``).
    dictionary : str
        Name of the OpenCV predefined ArUco dictionary (``cv2.aruco.DICT_*``).
    legacy_pattern : bool
        Boards printed by OpenCV < 4.6 with an even number of rows use the legacy layout.
    """

    squares: tuple[int, int]
    square_size: float
    marker_size: float
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False

    def __post_init__(self):
        sq = tuple(int(s) for s in self.squares)
        object.__setattr__(self, "squares", sq)
        object.__setattr__(self, "square_size", float(self.square_size))
        object.__setattr__(self, "marker_size", float(self.marker_size))
        if len(sq) != 2 or min(sq) < 2:
            raise CalibrationError(f"board squares must be two integers >= 2, got {self.squares}")
        if not 0.0 < self.marker_size < self.square_size:
            raise CalibrationError(
                f"marker size {self.marker_size} m must be positive and smaller than the "
                f"square size {self.square_size} m")
        if not hasattr(cv2.aruco, self.dictionary):
            raise CalibrationError(f"unknown ArUco dictionary {self.dictionary!r} "
                                   "(expected a cv2.aruco.DICT_* name, e.g. DICT_5X5_100)")
        n_markers = (sq[0] * sq[1]) // 2
        dict_size = len(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList)
        if n_markers > dict_size:
            raise CalibrationError(f"a {sq[0]}x{sq[1]} board needs {n_markers} markers but "
                                   f"{self.dictionary} has only {dict_size}")

    @property
    def n_corners(self) -> int:
        """Number of inner chessboard corners."""
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    @property
    def corner_points(self) -> np.ndarray:
        """Board-frame coordinates of the inner corners by ChArUco id, shape (N, 3), metres."""
        nx = self.squares[0] - 1
        k = np.arange(self.n_corners)
        x = (k % nx + 1) * self.square_size
        y = (k // nx + 1) * self.square_size
        return np.stack([x, y, np.zeros_like(x)], axis=1)

    @property
    def centre(self) -> np.ndarray:
        """Board-frame coordinates of the centre of the chessboard area, shape (3,)."""
        return np.array([0.5 * self.squares[0] * self.square_size,
                         0.5 * self.squares[1] * self.square_size, 0.0])

    def cv_board(self) -> "cv2.aruco.CharucoBoard":
        """The OpenCV board object (cached per spec)."""
        return _cv_board(self)

    def texture(self, pixels_per_square: int, margin_squares: int = 1) -> np.ndarray:
        """Printable board image with a white margin, uint8, shape (H, W).

        Board coordinate ``(X, Y)`` (metres) lies at image coordinate
        ``((X / square_size + margin_squares) * pixels_per_square - 0.5, ...)``
        (pixel centres at integers).
        """
        pps, m = int(pixels_per_square), int(margin_squares)
        size = ((self.squares[0] + 2 * m) * pps, (self.squares[1] + 2 * m) * pps)
        return self.cv_board().generateImage(size, marginSize=m * pps, borderBits=1)


@functools.lru_cache(maxsize=16)
def _cv_board(spec: BoardSpec):
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard(spec.squares, spec.square_size, spec.marker_size, dictionary)
    board.setLegacyPattern(bool(spec.legacy_pattern))
    return board


@functools.lru_cache(maxsize=16)
def _detector(spec: BoardSpec):
    det_params = cv2.aruco.DetectorParameters()
    det_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(spec.cv_board(), cv2.aruco.CharucoParameters(), det_params)


@dataclass(frozen=True, eq=False)
class BoardDetection:
    """ChArUco corners found in one image.

    Attributes
    ----------
    ids : ndarray of int, shape (n,)
        Corner ids (rows of :attr:`BoardSpec.corner_points`).
    corners : ndarray, shape (n, 2)
        Pixel positions ``(u, v)`` of those corners (distorted image).
    n_markers : int
        ArUco markers decoded in the image (diagnostics).
    """

    ids: np.ndarray
    corners: np.ndarray
    n_markers: int = 0

    def __len__(self) -> int:
        return int(len(self.ids))


def _to_gray8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    f = img.astype(np.float64)
    if f.max() <= 1.0:  # float images in [0, 1]
        f = f * 255.0
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def detect_board(image: np.ndarray, board: BoardSpec) -> BoardDetection:
    """Detect the ChArUco corners of ``board`` in an image.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        Grey or BGR image (uint8, uint16 or float in [0, 1]); not modified.
    board : BoardSpec

    Returns
    -------
    BoardDetection
        Possibly empty (no corners found); ids sorted ascending.
    """
    gray = _to_gray8(image)
    ch_corners, ch_ids, _marker_corners, marker_ids = _detector(board).detectBoard(gray)
    n_markers = 0 if marker_ids is None else int(len(marker_ids))
    if ch_ids is None or len(ch_ids) == 0:
        return BoardDetection(np.zeros(0, dtype=np.int64), np.zeros((0, 2)), n_markers)
    ids = np.asarray(ch_ids, dtype=np.int64).ravel()
    corners = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(ids)
    return BoardDetection(ids[order], corners[order], n_markers)


def _usable(det: BoardDetection | None, board: BoardSpec, min_corners: int) -> bool:
    if det is None or len(det) < max(int(min_corners), 4):
        return False
    pts = board.corner_points[det.ids, :2]
    # Reject (near-)collinear corner sets: they do not fix a homography.
    centred = pts - pts.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return bool(s[1] > 0.5 * board.square_size)
