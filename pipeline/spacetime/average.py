"""Space-time reconstruction: a frame's gradient as the motion-compensated mean of its neighbours'.

Beyond the paper, which solves every frame alone (sec. 5). The cameras film a flow that
moves a few voxels between frames, and each frame's solve errs independently where its
data err independently (the optical flow's noise, the texture under a moving pattern, a
lossy codec's coding error): the frames ``k - W .. k + W`` of the per-frame solve, each
moved onto frame ``k`` along the motion between its volume and frame ``k``'s
(:func:`~schlieren.pipeline.spacetime.motion.volume_motion`), average those errors down
while the structure that moved with the flow stays. A translation seen by fixed cameras
adds no new view angle, so what the views cannot determine (the smoothness prior's and
the limited angles' share of the error) is not reduced: the neighbours bring noise
averaging only (``benchmarks/results/spacetime.md``).

:func:`motion_compensated_mean` is the kernel: the weighted mean ``sum_j w_j x_j(p +
u_kj(p)) / sum_j w_j`` over the window, with ``u_kj`` the motion from frame ``k`` to frame
``j`` estimated at a reduced resolution inside the window's support.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline.spacetime.motion import downsample2, volume_motion, warp_volume
from schlieren.pipeline.spacetime.params import SpaceTimeParams

__all__ = ["SpaceTimeInfo", "motion_compensated_mean", "window_frames", "window_weights", "support_box"]

#: Voxels added around the window's support before the motion is estimated (the
#: structures near its edge must stay inside the box when they move).
BOX_MARGIN = 6


@dataclass(frozen=True)
class SpaceTimeInfo:
    """Receipt of one space-time frame.

    Attributes
    ----------
    frames : tuple of int
        Offsets of the frames averaged (0 = the frame itself).
    weights : tuple of float
        Their weights (normalised to sum 1).
    mean_motion : tuple of float
        Mean displacement magnitude (voxels) over the support, per neighbour.
    seconds : float
    """

    frames: tuple = field(default=())
    weights: tuple = field(default=())
    mean_motion: tuple = field(default=())
    seconds: float = 0.0


def window_frames(k: int, n_frames: int, window: int) -> range:
    """The frames averaged into frame ``k`` of ``n_frames``: ``k - w .. k + w`` with ``w`` the
    largest half-width up to ``window`` that stays inside the run, so every window is
    symmetric about its frame (a change of the flow that is linear in time, which no
    motion describes, cancels in a symmetric mean and biases a one-sided one; the first
    and last frames keep their own solve)."""
    w = max(min(int(window), int(k), int(n_frames) - 1 - int(k)), 0)
    return range(int(k) - w, int(k) + w + 1)


def window_weights(offsets, neighbour_weight: float) -> np.ndarray:
    """Weights of the window's frames at ``offsets`` from the frame (``neighbour_weight``
    to the power of the distance), normalised to sum 1."""
    d = np.abs(np.asarray(offsets, dtype=np.float64))
    w = float(neighbour_weight) ** d
    return w / w.sum()


def support_box(support: np.ndarray, margin: int = BOX_MARGIN) -> tuple[slice, slice, slice]:
    """The bounding box of ``support`` (bool volume) grown by ``margin`` voxels, clipped to
    the volume (an empty support gives an empty box)."""
    support = np.asarray(support, dtype=bool)
    out = []
    for axis in range(3):
        hit = np.flatnonzero(support.any(axis=tuple(a for a in range(3) if a != axis)))
        if not len(hit):
            return (slice(0, 0),) * 3
        out.append(slice(max(int(hit[0]) - margin, 0), min(int(hit[-1]) + 1 + margin, support.shape[axis])))
    return tuple(out)


def _motion(ref: np.ndarray, mov: np.ndarray, params: SpaceTimeParams) -> np.ndarray:
    """``u`` with ``mov(p + u) ~ ref(p)``, estimated and returned on the grid ``motion_scale``
    times coarser than the volumes' (voxels of that grid; :func:`~schlieren.pipeline.spacetime.
    motion.warp_volume`'s ``scale`` takes it so)."""
    halvings = {1: 0, 2: 1, 4: 2}.get(int(params.motion_scale))
    if halvings is None:
        raise ValueError(f"motion_scale must be 1, 2 or 4, not {params.motion_scale}")
    a, b = ref, mov
    for _ in range(halvings):
        a, b = downsample2(a), downsample2(b)
    return volume_motion(a, b, levels=params.motion_levels, sigma=params.motion_window,
                         iterations=params.motion_iterations, reg=params.motion_reg)


def motion_compensated_mean(volumes, offsets, support: np.ndarray, *, params: SpaceTimeParams = SpaceTimeParams(),
                            region: np.ndarray | None = None) -> tuple[np.ndarray, SpaceTimeInfo]:
    """Frame ``k``'s gradient from the per-frame gradients of its window.

    Parameters
    ----------
    volumes : sequence of ndarray, each shape (nz, ny, nx, 3)
        The per-frame gradients (1/m) of the window's frames.
    offsets : sequence of int
        Each volume's frame minus ``k`` (one of them 0: frame ``k`` itself).
    support : ndarray, shape (nz, ny, nx) bool
        Where the result is wanted (frame ``k``'s basis set); zero elsewhere.
    params : SpaceTimeParams
        Weights (``neighbour_weight``) and the motion estimator's settings.
    region : ndarray, shape (nz, ny, nx) bool, optional
        Where the window's volumes may be non-zero (the union of their basis sets): the
        motion is estimated in its bounding box with ``support`` (:func:`support_box`).
        Default: found from the volumes.

    Returns
    -------
    gradient : ndarray, shape (nz, ny, nx, 3) float32
    info : SpaceTimeInfo
    """
    t0 = time.perf_counter()
    offsets = [int(o) for o in offsets]
    if len(offsets) != len(volumes) or offsets.count(0) != 1:
        raise ValueError("motion_compensated_mean: one offset per volume, exactly one of them 0")
    support = np.asarray(support, dtype=bool)
    c = offsets.index(0)
    ref = np.asarray(volumes[c], dtype=np.float32)
    if ref.shape != support.shape + (3,):
        raise ValueError(f"volumes {ref.shape} and support {support.shape} do not match")
    out = np.zeros(ref.shape, np.float32)
    if not support.any() or len(volumes) == 1:
        out[support] = ref[support]
        return out, SpaceTimeInfo((0,), (1.0,), (), time.perf_counter() - t0)
    w = window_weights(offsets, params.neighbour_weight)
    if region is None:
        region = np.zeros(support.shape, bool)
        for v in volumes:
            region |= np.any(np.asarray(v) != 0, axis=-1)
    box = support_box(np.asarray(region, dtype=bool) | support)
    a = np.ascontiguousarray(ref[box])
    acc = w[c] * a
    s = int(params.motion_scale)
    inside = support[box][::s, ::s, ::s]
    moved = []
    for j, (o, v) in enumerate(zip(offsets, volumes)):
        if o == 0:
            continue
        b = np.ascontiguousarray(np.asarray(v, dtype=np.float32)[box])
        u = _motion(a, b, params)
        acc += w[j] * warp_volume(b, u, order=3, scale=s)
        moved.append(float(s * np.mean(np.linalg.norm(u[inside], axis=-1))) if inside.any() else 0.0)
    out[box] = acc
    out[~support] = 0.0
    return out, SpaceTimeInfo(tuple(offsets), tuple(float(x) for x in w), tuple(moved), time.perf_counter() - t0)
