"""Warnings after a run: what the task receipts say looks wrong, by camera and frame, with
the likely cause (issue 15, item 6).

Each check reads the small receipts the tasks return (no store access) and produces at
most one line per problem and camera, listing the frames (capture indices) concerned.
"""

from __future__ import annotations

from collections import defaultdict

__all__ = ["diagnose", "HULL_FULL", "MASK_FULL", "DEFLECTION_LARGE_PX"]

#: Fraction of the box above which a visual hull carves nothing useful.
HULL_FULL = 0.9
#: Fraction of the image above which a flow mask is suspicious (a plume fills less).
MASK_FULL = 0.6
#: Deflections (image pixels) beyond which BOS (sub-pixel to ~1 px) is unlikely the cause.
DEFLECTION_LARGE_PX = 5.0


def _frames(frames: list[int], limit: int = 8) -> str:
    frames = sorted(set(int(f) for f in frames))
    text = ", ".join(map(str, frames[:limit]))
    more = len(frames) - limit
    return f"frame{'s' if len(frames) > 1 else ''} {text}" + (f" (and {more} more)" if more > 0 else "")


def diagnose(receipts, *, n_voxels: int, flash_frames=None, motion_warning: float | None = None) -> list[str]:
    """One-line warnings naming camera and frames, with a likely cause.

    Parameters
    ----------
    receipts : iterable of dict
        Task receipts of a run (``stage``, ``camera``, ``frame`` and the stage's fields:
        hull ``voxels``, mask ``fraction``, deflection ``max_px``, ``motion_px`` and
        ``capture_flags``).
    n_voxels : int
        Voxels in the reconstruction box.
    flash_frames : mapping of str to (int, int), optional
        Camera -> first and last frame the strobe flash lit (the stored ``flash_frames``;
        ``(-1, -1)``: none). Their large deflections are the flash, which the sync already
        excludes from the reconstruction: no warning.
    motion_warning : float, optional
        Pixels: camera-frames whose background moved more than this against the
        reference are named (``capture.motion_warning``); None: no such warning.
    """
    receipts = list(receipts)
    out = _flow_warnings(receipts, n_voxels, flash_frames)
    out += _capture_warnings(receipts, motion_warning)
    return out


def _flow_warnings(receipts, n_voxels: int, flash_frames=None) -> list[str]:
    """The hull, mask and deflection warnings of :func:`diagnose`."""
    flash = {str(c): (int(lo), int(hi)) for c, (lo, hi) in (flash_frames or {}).items()}
    full, empty = [], []
    masks: dict[str, list[int]] = defaultdict(list)
    large: dict[str, list[tuple[int, float]]] = defaultdict(list)
    for r in receipts:
        if r.get("skipped"):
            continue
        stage, frame = r.get("stage"), r.get("frame")
        if stage == "hull" and "voxels" in r and n_voxels:
            frac = r["voxels"] / n_voxels
            if frac > HULL_FULL:
                full.append(frame)
            elif r["voxels"] == 0:
                empty.append(frame)
        elif stage == "mask" and r.get("fraction", 0.0) > MASK_FULL:
            masks[r.get("camera", "?")].append(frame)
        elif stage == "deflection" and r.get("max_px", 0.0) > DEFLECTION_LARGE_PX:
            lo, hi = flash.get(str(r.get("camera")), (-1, -1))
            if not (frame is not None and lo <= int(frame) <= hi):  # the flash is no bumped camera
                large[r.get("camera", "?")].append((frame, float(r["max_px"])))
    out = []
    if full:
        out.append(f"{_frames(full)}: the visual hull fills more than {HULL_FULL:.0%} of the box: a camera moved "
                   "since its reference was recorded, or the mask threshold is too low (raise masks.percentile)?")
    if empty:
        out.append(f"{_frames(empty)}: the visual hull is empty: no camera's mask covers the plume there "
                   "(flow too weak for masks.percentile, or a camera that misses the volume)?")
    for cam, frames in sorted(masks.items()):
        out.append(f"camera {cam}, {_frames(frames)}: the flow mask covers more than {MASK_FULL:.0%} of the image: "
                   "the camera or the background moved, or the lighting changed since the reference?")
    for cam, items in sorted(large.items()):
        worst = max(v for _, v in items)
        out.append(f"camera {cam}, {_frames([f for f, _ in items])}: deflections up to {worst:.3g} px (BOS "
                   "deflections are sub-pixel to about 1 px): the camera was bumped, or the frame does not "
                   "match the reference (focus, exposure)?")
    return out


def _capture_warnings(receipts, motion_warning: float | None) -> list[str]:
    """Per camera: the frames whose background moved more than ``motion_warning`` pixels
    against the reference, and the frames whose motion had to be measured on every pixel."""
    from schlieren.pipeline.capture import FALLBACK

    moved: dict[str, list[tuple[int, float]]] = defaultdict(list)
    fallback: dict[str, list[int]] = defaultdict(list)
    for r in receipts:
        if r.get("skipped") or r.get("stage") != "deflection":
            continue
        cam, frame = r.get("camera", "?"), r.get("frame")
        if motion_warning is not None and r.get("motion_px", 0.0) > motion_warning:
            moved[cam].append((frame, float(r["motion_px"])))
        if int(r.get("capture_flags", 0)) & FALLBACK:
            fallback[cam].append(frame)
    out = []
    for cam, items in sorted(moved.items()):
        worst = max(v for _, v in items)
        out.append(f"camera {cam}, {_frames([f for f, _ in items])}: the background moved by up to {worst:.3g} px "
                   f"against the reference (more than capture.motion_warning, {motion_warning:g} px); it was "
                   "removed from the flow, but re-record the reference or fix the camera's mount?")
    for cam, frames in sorted(fallback.items()):
        out.append(f"camera {cam}, {_frames(frames)}: less of the image sees the background beside the volume than "
                   "capture.min_static_fraction: its motion was measured on every pixel (the plume told apart by "
                   "robust weights); a wider view or a smaller volume box measures it better")
    return out
