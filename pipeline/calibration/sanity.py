"""Calibration sanity before any work: is this rig one that can image the volume?

A calibration can be valid (orthonormal ``R``, positive focal lengths, a background in
front of the camera) and still describe a rig that cannot be: translations in
millimetres with the volume in metres put every camera kilometres away and the volume
at a fraction of a pixel; a camera inside or touching the box starts its rays in the
reconstruction; a background nearer than the volume is not behind the flow (paper
sec. 4, Figure 2: the background is placed *behind* the scan volume). These are pure
checks on :class:`~schlieren.pipeline.geometry.Camera` and the volume's corners;
:func:`rig_problems` returns every problem found, and the session reader and
``schlieren init`` (storage/) raise the first fatal one naming the file and camera, and
log the others.

Where a factor of 1000 would make the numbers plausible, the message asks
"calibration in millimetres?": that is the unit mistake a new user makes first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schlieren.pipeline.geometry import Camera
from schlieren.pipeline.params import param, parameters

__all__ = ["RigSanityParams", "RigProblem", "rig_problems", "centre_inside", "sees_box",
           "visible_fraction", "MM_HINT"]

#: The hint added where a factor of 1000 explains the numbers.
MM_HINT = "calibration in millimetres? (t, background and volume must all be in metres)"


@parameters
class RigSanityParams:
    """Thresholds of :func:`rig_problems` (field names = its keyword names)."""

    max_distance_ratio: float = param(
        200.0, unit="1", gt=1, le=1e6,
        help="A camera farther from the volume centre than this many times the volume's diagonal is "
             "refused (a BOS rig puts its cameras 5-50 diagonals away).")
    min_footprint_px: float = param(
        1.0, unit="px", ge=0, le=1e4,
        help="A camera in which the volume's diagonal spans fewer pixels is refused.")
    max_footprint_ratio: float = param(
        20.0, unit="1", gt=1, le=1e6,
        help="A camera in which the volume's diagonal spans more than this many image diagonals is "
             "refused (it would see a sliver of the box).")
    touch_fraction: float = param(
        0.02, unit="1", ge=0, le=10,
        help="A camera centre closer to the box than this fraction of the volume's diagonal touches "
             "it, and is refused.")
    min_visible_fraction: float = param(
        0.5, unit="1", ge=0, le=1,
        help="A camera that sees less than this fraction of the volume (sampled on a 9^3 lattice) gets"
             " a warning.")
    max_volume_size: float = param(
        100.0, unit="m", gt=0, le=1e6,
        help="A volume whose diagonal exceeds this many metres is refused.")


@dataclass(frozen=True)
class RigProblem:
    """One problem of a rig.

    Attributes
    ----------
    camera : str or None
        The camera concerned (None: the volume).
    field : str
        The calibration field at fault: ``"t"``, ``"K"``, ``"background"`` or ``"volume"``.
    message : str
        One line, in plain words; a warning's is a verb phrase with the camera as subject
        ("does not see the volume").
    fatal : bool
        Refuse the session (else warn).
    """

    camera: str | None
    field: str
    message: str
    fatal: bool


def centre_inside(cam: Camera, vmin, vmax) -> str | None:
    """Why camera ``cam`` cannot image the box ``[vmin, vmax]``: its centre lies in it
    (rays would start inside the reconstruction), or None."""
    C = np.asarray(cam.center, dtype=np.float64)
    if np.all(C >= np.asarray(vmin)) and np.all(C <= np.asarray(vmax)):
        return (f"the camera centre {np.round(C, 4).tolist()} m (-R^T t) lies inside the volume "
                f"{[round(float(v), 4) for v in vmin]} .. {[round(float(v), 4) for v in vmax]}: a camera must "
                "look at the flow from outside the box (check t, and the volume's world frame)")
    return None


def _corners(vmin, vmax) -> np.ndarray:
    lo, hi = np.asarray(vmin, dtype=np.float64), np.asarray(vmax, dtype=np.float64)
    return np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                     for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def sees_box(cam: Camera, vmin, vmax) -> bool:
    """Conservative test: False only if no part of the box ``[vmin, vmax]`` can be in the image."""
    lo, hi = np.asarray(vmin, dtype=np.float64), np.asarray(vmax, dtype=np.float64)
    pts = np.vstack([_corners(lo, hi), 0.5 * (lo + hi)[None, :]])
    Xc = pts @ cam.R.T + cam.t
    front = Xc[:, 2] > 0
    if not front.any():
        return False
    if not front.all():  # the box straddles the camera plane: the camera is next to or in it
        return True
    uv = cam.project(pts)
    W, H = cam.image_size
    low, high = -0.5, np.array([W - 0.5, H - 0.5])
    if np.any(np.all((uv >= low) & (uv <= high), axis=1)):
        return True
    # the projected box may still cover the image without a corner inside it
    umin, umax = uv.min(axis=0), uv.max(axis=0)
    return bool(np.all(umin <= high) and np.all(umax >= low))


def visible_fraction(cam: Camera, vmin, vmax, *, n: int = 9) -> float:
    """Fraction of an ``n^3`` lattice of points of the box in front of ``cam`` and inside its image."""
    axes = [np.linspace(a, b, n) for a, b in zip(np.asarray(vmin, float), np.asarray(vmax, float))]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    uv = cam.project(pts)
    W, H = cam.image_size
    ok = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) \
        & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)
    return float(ok.mean())


def _background_depth(cam: Camera) -> float:
    """Distance along the optical axis at which it meets the background plane (inf if parallel)."""
    denom = float(cam.optical_axis @ cam.bg_normal)
    if abs(denom) < 1e-12:
        return float("inf")
    return float((cam.bg_point - cam.center) @ cam.bg_normal) / denom


def _camera_problems(cam: Camera, lo: np.ndarray, hi: np.ndarray, *, max_distance_ratio: float,
                     min_footprint_px: float, max_footprint_ratio: float, touch_fraction: float,
                     min_visible_fraction: float) -> list[RigProblem]:
    """The problems of one camera against the box; at most one fatal (the first found)."""
    def fatal(field, text):
        return [RigProblem(cam.name, field, text, True)]

    diag = float(np.linalg.norm(hi - lo))
    centre = 0.5 * (lo + hi)
    C = cam.center
    dist = float(np.linalg.norm(C - centre))
    inside = centre_inside(cam, lo, hi)
    if inside is not None:
        return fatal("t", inside)
    ratio = dist / diag
    if ratio > max_distance_ratio:
        hint = MM_HINT if ratio / 1000.0 <= max_distance_ratio else "check t (metres) and the volume"
        return fatal("t", f"the camera is {dist:.4g} m from the volume centre, {ratio:.0f} times the volume's "
                          f"size ({diag:.3g} m): {hint}")
    gap = float(np.linalg.norm(np.clip(C, lo, hi) - C))
    if gap < touch_fraction * diag:
        return fatal("t", f"the camera centre is {1e3 * gap:.3g} mm from the volume's surface: a camera touching "
                          "the box cannot image it (check t, and the volume's world frame)")
    if not sees_box(cam, lo, hi):  # nothing else about it matters
        return [RigProblem(cam.name, "R", "does not see the volume; it will contribute nothing", False)]
    depth = float((centre - C) @ cam.optical_axis)
    f = 0.5 * float(cam.K[0, 0] + cam.K[1, 1])
    if depth > 0:
        span = f * diag / dist
        if span < min_footprint_px:
            return fatal("K", f"the volume spans {span:.3g} px in this camera's image (focal length {f:.4g} px at "
                              f"{dist:.4g} m): {MM_HINT[:-1]}, K's focal lengths in pixels)")
        sensor = float(np.hypot(*cam.image_size))
        if span > max_footprint_ratio * sensor:
            return fatal("K", f"the volume spans {span:.3g} px in this camera's image, {span / sensor:.0f} times "
                              f"the sensor's diagonal: check K (focal lengths in pixels) and t (metres)")
        bg = _background_depth(cam)
        if 0 < bg <= depth:
            hint = f": {MM_HINT}" if depth / bg > 100.0 else " (check background and t)"
            return fatal("background", f"the background plane ({bg:.4g} m along the optical axis) is nearer than "
                                       f"the volume centre ({depth:.4g} m): it must lie behind the flow{hint}")
    return _camera_warnings(cam, lo, hi, min_visible_fraction=min_visible_fraction)


def _camera_warnings(cam: Camera, lo: np.ndarray, hi: np.ndarray, *, min_visible_fraction: float
                     ) -> list[RigProblem]:
    """The background plane cutting the box; a camera seeing little of the volume."""
    out = []
    side = (_corners(lo, hi) - cam.bg_point) @ cam.bg_normal
    if np.any(side < 0) and np.any(side > 0):
        out.append(RigProblem(cam.name, "background", "has a background plane that cuts the volume: part of "
                                                      "the box lies behind the background", False))
    frac = visible_fraction(cam, lo, hi)
    if frac < min_visible_fraction:
        out.append(RigProblem(cam.name, "R", f"sees only {100 * frac:.0f} % of the volume (check R, t and the "
                                             "volume)", False))
    return out


def rig_problems(cameras, vmin, vmax, *, max_distance_ratio: float = 200.0, min_footprint_px: float = 1.0,
                 max_footprint_ratio: float = 20.0, touch_fraction: float = 0.02,
                 min_visible_fraction: float = 0.5, max_volume_size: float = 100.0) -> list[RigProblem]:
    """Every problem of the rig ``cameras`` around the box ``[vmin, vmax]`` (world metres).

    Per camera, the first fatal problem of: centre inside the box; farther than
    ``max_distance_ratio`` volume diagonals; touching the box; the volume spanning fewer
    than ``min_footprint_px`` pixels or more than ``max_footprint_ratio`` image diagonals;
    the background plane nearer than the volume centre. Then warnings: the background
    plane cutting the box, the camera seeing none, or less than ``min_visible_fraction``,
    of the volume. A volume larger than ``max_volume_size`` metres is one fatal problem
    (camera None); so is a rig in which no camera sees the volume.

    Parameters
    ----------
    cameras : sequence of Camera
    vmin, vmax : array-like, shape (3,)
        The box's corners, metres.

    Returns
    -------
    list of RigProblem
        In camera order; empty for a sane rig.
    """
    lo, hi = np.asarray(vmin, dtype=np.float64), np.asarray(vmax, dtype=np.float64)
    diag = float(np.linalg.norm(hi - lo))
    if diag > max_volume_size:
        return [RigProblem(None, "volume", f"the volume is {diag:.4g} m across: volume in millimetres? (the "
                                           "volume, t and the background must all be in metres)", True)]
    out: list[RigProblem] = []
    for cam in cameras:
        out += _camera_problems(cam, lo, hi, max_distance_ratio=max_distance_ratio,
                                min_footprint_px=min_footprint_px, max_footprint_ratio=max_footprint_ratio,
                                touch_fraction=touch_fraction, min_visible_fraction=min_visible_fraction)
    fatal_any = any(p.fatal for p in out)
    if not fatal_any and all(any(p.camera == c.name and "does not see" in p.message for p in out) for c in cameras):
        out.append(RigProblem(None, "volume", "no camera sees the volume: no part of it is in any image (check volume, R and t)", True))
    return out
