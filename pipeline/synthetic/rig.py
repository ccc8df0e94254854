"""Virtual camera rigs: calibrated pinhole cameras on a half or full ring (paper sec. 4, 6).

Each camera stands on a horizontal circle around the volume centre, looks at the centre
(z up, OpenCV axes: x right, y down, z forward) and has its own background plane
perpendicular to its optical axis, ``background_distance`` behind the volume centre.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from schlieren.pipeline.geometry import Camera, Grid

__all__ = ["make_rig", "ring_angles", "look_at"]


def ring_angles(n_cameras: int, ring: str = "half") -> np.ndarray:
    """Azimuths (radians) of the cameras.

    ``half``: ``pi * i / n`` for ``i = 0..n-1`` - viewing directions spaced evenly over
    180 degrees, so no two cameras look along the same line (the paper's half ring).
    ``full``: ``2 pi * i / n`` (use an odd ``n`` so no two cameras face each other, as the
    paper recommends).
    """
    if n_cameras < 1:
        raise ValueError("n_cameras must be >= 1")
    i = np.arange(n_cameras, dtype=np.float64)
    if ring == "half":
        return np.pi * i / n_cameras
    if ring == "full":
        return 2 * np.pi * i / n_cameras
    raise ValueError(f"ring must be 'half' or 'full', not {ring!r}")


def look_at(centre: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera rotation ``R`` and translation ``t`` of a camera at ``centre`` looking at ``target``."""
    c = np.asarray(centre, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - c
    f /= np.linalg.norm(f)
    right = np.cross(f, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f])
    return R, -R @ c


def make_rig(n_cameras: int, *, ring: str = "half", grid: Grid, radius: float = 2.5,
             image_size: tuple[int, int] = (1440, 1080), focal_px: float | None = None,
             background_distance: float = 2.5, height_jitter: float = 0.0,
             distortion: Sequence[float] | None = None, line_time: float = 1.54e-5,
             seed: int = 0, fill: float = 0.95) -> list[Camera]:
    """Calibrated pinhole cameras around the volume.

    Parameters
    ----------
    n_cameras : int
    ring : {"half", "full"}
        See :func:`ring_angles`.
    grid : Grid
        The volume; cameras look at its centre.
    radius : float
        Distance (metres) of each camera from the vertical axis through the centre.
    image_size : (int, int)
        ``(width, height)`` in pixels.
    focal_px : float, optional
        Focal length in pixels; default: the largest focal length for which the box is
        inside every camera's frame with margin ``fill`` (the volume fills the frame).
    background_distance : float
        Distance (metres) of each background plane behind the volume centre, measured
        along the camera's optical axis.
    height_jitter : float
        Standard deviation (metres) of random camera heights around the centre height.
    distortion : sequence of float, optional
        OpenCV distortion coefficients (k1 k2 p1 p2 [k3]) applied to every camera.
    line_time : float
        Rolling-shutter line time (seconds; 0 = global shutter).
    seed : int
        Seeds the height jitter.
    fill : float
        Fraction of the half-frame the box may fill with the automatic focal length.

    Returns
    -------
    list of Camera
        Named ``cam00``, ``cam01``, ... with ``time_offset=None``.
    """
    rng = np.random.default_rng(seed)
    ctr = grid.center
    W, H = int(image_size[0]), int(image_size[1])
    ang = ring_angles(n_cameras, ring)
    dz = rng.normal(0.0, height_jitter, n_cameras) if height_jitter > 0 else np.zeros(n_cameras)
    poses = []
    for a, h in zip(ang, dz):
        C = ctr + np.array([radius * np.cos(a), radius * np.sin(a), h])
        poses.append(look_at(C, ctr))
    if focal_px is None:
        corners = grid.corners()
        extent = 0.0
        for R, t in poses:
            Xc = corners @ R.T + t
            xn = Xc[:, 0] / Xc[:, 2]
            yn = Xc[:, 1] / Xc[:, 2]
            extent = max(extent, np.abs(xn).max() / (0.5 * W), np.abs(yn).max() / (0.5 * H))
        focal_px = fill / extent
    K = np.array([[focal_px, 0.0, (W - 1) / 2.0], [0.0, focal_px, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
    dist = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    cams = []
    for i, (R, t) in enumerate(poses):
        C = -R.T @ t
        dist_to_centre = float(np.linalg.norm(ctr - C))
        bg_point, bg_normal = Camera.background_from_distance(R, t, dist_to_centre + background_distance)
        cams.append(Camera(f"cam{i:02d}", K, dist, R, t, (W, H), bg_point, bg_normal, line_time, None))
    return cams
