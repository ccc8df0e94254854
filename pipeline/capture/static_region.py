"""Where a camera sees its background through still air: the pixels whose rays miss the
reconstruction box.

The deflection of a ray is the integral of grad n along it (paper eq. 3), so a ray that
never enters the box (where the flow is) is not deflected: the flow there measures only
what moved between the reference and the frame (the camera, the background, the
lighting). The box is convex, so its image is the convex hull of the images of its
edges (sampled along each edge, which also follows lens distortion); a margin keeps the
flow's windows and a plume leaving the box's faces out of the static region.
"""

from __future__ import annotations

import cv2
import numpy as np

from schlieren.pipeline.geometry import Camera, FlowGrid

__all__ = ["box_footprint", "static_region", "static_cells"]

#: Points sampled along each of the box's 12 edges.
_EDGE_SAMPLES = 33


def _box_edge_points(vmin, vmax, n: int = _EDGE_SAMPLES) -> np.ndarray:
    """Points along the 12 edges of the box ``[vmin, vmax]``, shape (12 * n, 3)."""
    a, b = np.asarray(vmin, np.float64), np.asarray(vmax, np.float64)
    s = np.linspace(0.0, 1.0, n)
    pts = []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for i in (0, 1):
            for j in (0, 1):
                p = np.empty((n, 3))
                p[:, axis] = a[axis] + s * (b[axis] - a[axis])
                p[:, others[0]] = (a, b)[i][others[0]]
                p[:, others[1]] = (a, b)[j][others[1]]
                pts.append(p)
    return np.concatenate(pts)


def box_footprint(camera: Camera, vmin, vmax) -> np.ndarray:
    """The pixels whose rays cross the box ``[vmin, vmax]`` (world x, y, z, metres).

    Returns
    -------
    footprint : ndarray, shape (H, W), bool
        The filled convex hull of the box's projected edges (every pixel when a part of
        the box lies behind the camera).
    """
    W, H = camera.image_size
    uv = camera.project(_box_edge_points(vmin, vmax))
    if not np.isfinite(uv).all():  # the camera is inside the box or behind one of its faces
        return np.ones((H, W), bool)
    # far outside the image the hull only needs its shape: clip to a generous frame so the
    # integer polygon stays in range
    big = 4.0 * max(W, H)
    uv = np.clip(uv, -big, big)
    hull = cv2.convexHull(np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2))
    out = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def static_region(camera: Camera, vmin, vmax, *, margin: float = 16.0) -> np.ndarray:
    """The pixels whose rays miss the box, at least ``margin`` pixels from its image.

    Parameters
    ----------
    camera : Camera
    vmin, vmax : sequence of 3 float
        The reconstruction box (world x, y, z, metres).
    margin : float
        Image pixels between the box's image and the static region: the flow at a pixel
        averages its LK window, and a plume may leave the box a little.

    Returns
    -------
    static : ndarray, shape (H, W), bool
    """
    fp = box_footprint(camera, vmin, vmax)
    r = int(np.ceil(margin))
    if r > 0 and fp.any():
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        fp = cv2.dilate(fp.astype(np.uint8), k).astype(bool)
    return ~fp


def static_cells(static: np.ndarray, factor: int) -> np.ndarray:
    """Flow-grid cells (``FlowGrid((W, H), factor)``) all of whose pixels are static."""
    H, W = static.shape
    rows, cols = FlowGrid((W, H), factor).shape
    s = static[:rows * factor, :cols * factor].reshape(rows, factor, cols, factor)
    return s.all(axis=(1, 3))
