"""Memory and disk a run needs: the measured model the preflight check uses.

The coefficients are *measured* by ``benchmarks/memory.py`` (peak resident memory of each
kind of task, run by the real task code in a fresh process, fitted over several image
sizes, grids and camera counts; ``benchmarks/results/memory.json`` and ``.md``) and copied
here; a test keeps them equal to the recorded results. The model:

* a 2-D task (one camera-frame of deflection, resampling, potential or mask) needs
  ``c + p * pixels`` (:data:`PIXEL_MODEL`, per stage);
* a 3-D task (geometry, tomography or integration of one frame) needs
  ``c + a * voxels + b * crossings + q * rays`` with ``crossings`` the number of
  (ray, voxel) pairs the projection matrix holds, estimated by :func:`ray_crossings` from
  the cameras and grid (every flow-grid ray's path through the box, in voxel lengths) and
  ``rays`` the flow-grid pixels of all cameras (:data:`TASK_MODEL`, per stage; ``c``
  includes one-off costs of a process's first task such as compiling numba kernels);
* every estimate is multiplied by :data:`MODEL_MARGIN`, the fit's largest
  under-estimate of a measurement;
* every worker process carries ``PROCESS_BYTES`` of code and libraries;
* a worker that runs tomography tasks keeps one more block restriction of the projection
  than its running task holds (``pipeline.tomography.restriction.SHARED_RESTRICTIONS``):
  :data:`HELD_BYTES_PER_CROSSING` per ray-voxel crossing, a bound rather than a fit (half
  the session matrix's bytes, i.e. a hull over half the box, plus the buffers' 25 %
  headroom; the paper-scale benchmark's hull covers 31 % of its box, the realistic
  family's 8 %).

Pure numpy: no files, no Dask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BYTES_PER_PIXEL", "BYTES_PER_VOXEL", "PROCESS_BYTES", "HELD_BYTES_PER_CROSSING", "PIXEL_MODEL", "TASK_MODEL", "CACHE_MODEL",
           "MODEL_MARGIN",
           "ray_crossings",
           "MemoryEstimate", "estimate_memory", "estimate_disk"]

# --- measured by benchmarks/memory.py (results/memory.json); do not edit by hand ---------
#: 2-D tasks: ``(bytes, bytes per image pixel)`` of each per-camera-frame stage.
PIXEL_MODEL: dict[str, tuple[float, float]] = {
    'deflection': (51790209.2120285, 74.19268689154205),
    'resample': (49898905.05014693, 19.971032399106072),
    'potential': (2899621.3131103087, 9.967190542601195),
    'mask': (2863093.1525048483, 9.015632143556486),
}
#: 3-D tasks: ``(bytes, bytes per voxel, bytes per ray-voxel crossing, bytes per flow-grid
#: ray)`` of each stage.
TASK_MODEL: dict[str, tuple[float, float, float, float]] = {
    'geometry': (45845118.152265266, 72.36303530854521, 16.089318179921612, 270.2437806527056),
    'tomography': (55116127.30276086, 292.0214414464918, 13.132682012889807, 214.37094187161588),
    'integrate': (55794092.23504497, 111.33096781173964, 0.0, 0.0),
}
#: The geometry cache on disk: ``(bytes per flow-grid ray, bytes per crossing)``.
CACHE_MODEL: tuple[float, float] = (90.66880794904968, 25.120435587894406)
#: A worker process with the pipeline's libraries and ``distributed`` imported.
PROCESS_BYTES = 194662400.0
#: Bytes per ray-voxel crossing of a block restriction a tomography worker keeps between
#: tasks (see the module docstring): half the geometry cache's bytes per crossing x 1.25.
HELD_BYTES_PER_CROSSING = 0.5 * 1.25 * CACHE_MODEL[1]
#: The largest under-estimate of any measurement by the fitted model; tasks are scaled by it.
MODEL_MARGIN = 1.0636795834531168
# -------------------------------------------------------------------------------------------
#: The largest per-voxel coefficient of the 3-D stages (a lower bound per voxel and frame).
BYTES_PER_VOXEL = max((a for _, a, _, _ in TASK_MODEL.values()), default=0.0)
#: The largest per-pixel coefficient of the 2-D stages.
BYTES_PER_PIXEL = max((p for _, p in PIXEL_MODEL.values()), default=0.0)


def ray_crossings(cameras, grid, flow_grid, *, max_rays: int = 4096) -> tuple[float, int]:
    """``(crossings, rays)``: total path of every flow-grid ray through the grid's box, in
    voxel lengths, and the number of flow-grid rays.

    Rays are sampled on a regular sub-grid of at most ``max_rays`` per camera and the
    sum scaled to all rays (the path varies smoothly across the image).
    """
    rows, cols = flow_grid.shape
    stride = max(1, int(math.ceil(math.sqrt(rows * cols / max_rays))))
    uv = flow_grid.pixel_centres()[::stride, ::stride].reshape(-1, 2)
    lo, hi = np.asarray(grid.vmin, dtype=np.float64), np.asarray(grid.vmax, dtype=np.float64)
    total = 0.0
    for cam in cameras:
        origin, d = cam.rays(uv)
        d = np.where(np.abs(d) < 1e-15, 1e-15, d)  # axis-parallel rays: the slab test still works
        t1, t2 = (lo - origin) / d, (hi - origin) / d
        t_in = np.maximum(np.minimum(t1, t2).max(axis=1), 0.0)
        t_out = np.maximum(t1, t2).min(axis=1)
        total += float(np.clip(t_out - t_in, 0.0, None).sum()) * (rows * cols) / len(uv)
    return total / float(grid.voxel_size), len(cameras) * rows * cols


@dataclass(frozen=True)
class MemoryEstimate:
    """Peak memory of one task of each kind and of one worker process (bytes)."""

    task_2d: float
    task_3d: float
    stage_3d: str
    voxels: int
    crossings: float
    pixels: int
    held_3d: float = 0.0

    def worker(self, slots: int = 1, tomo_slots: int = 1) -> float:
        """A worker running ``slots`` tasks at once, at most ``tomo_slots`` of them 3-D, each
        3-D thread keeping ``held_3d`` between its tasks."""
        slots = max(int(slots), 1)
        three_d = min(max(int(tomo_slots), 1), slots)
        return PROCESS_BYTES + three_d * self.held_3d + max(
            slots * self.task_2d, three_d * self.task_3d + (slots - three_d) * self.task_2d)


def estimate_memory(cameras, grid, flow_grid, image_size) -> MemoryEstimate:
    """The measured model (:data:`TASK_MODEL`, :data:`BYTES_PER_PIXEL`) for one session."""
    crossings, rays = ray_crossings(cameras, grid, flow_grid)
    nvox = int(math.prod(grid.shape))
    w, h = image_size
    per_stage = {s: MODEL_MARGIN * (c + a * nvox + b * crossings + q * rays)
                 for s, (c, a, b, q) in TASK_MODEL.items()}
    stage = max(per_stage, key=per_stage.get) if per_stage else "tomography"
    task_2d = MODEL_MARGIN * max((c + p * w * h for c, p in PIXEL_MODEL.values()), default=0.0)
    return MemoryEstimate(task_2d=task_2d, task_3d=per_stage.get(stage, 0.0), stage_3d=stage,
                          voxels=nvox, crossings=crossings, pixels=int(w * h),
                          held_3d=HELD_BYTES_PER_CROSSING * crossings)


def estimate_disk(array_bytes: float, cameras, grid, flow_grid) -> float:
    """Bytes a finished store needs: its arrays uncompressed (noisy float32 fields barely
    compress) plus the geometry cache (:data:`CACHE_MODEL`)."""
    crossings, rays = ray_crossings(cameras, grid, flow_grid)
    return float(array_bytes) + CACHE_MODEL[0] * rays + CACHE_MODEL[1] * crossings
