"""The ``hull`` task: the visual hull of one frame's masks (the voxels every camera's mask sees).

:func:`~schlieren.pipeline.hull.visual_hull` carves the volume with every camera's mask;
the projection of the voxel centres into the cameras is the same for every frame and is
kept per process when it is small enough.
"""

from __future__ import annotations

import numpy as np

from schlieren.pipeline import hull as hullmod
from schlieren.workers.tasks.run_context import RunContext

__all__ = ["hull_task", "HULL_PROJECTION_BYTES"]


#: Largest :func:`~schlieren.pipeline.hull.hull_projection` a process keeps for the hulls of
#: a sequence (8 bytes per voxel and camera: 55 MB for 16 cameras on the paper-scale
#: session's 432,000 voxels, where it makes the hull task several times faster;
#: docs/tuning.md, "Speed"); above it each hull projects its candidates itself.
HULL_PROJECTION_BYTES = 256 * 2 ** 20


def hull_task(ctx: RunContext, k: int) -> dict:
    """Frame ``k``'s visual hull (stored ``hull``)."""
    ms = np.stack(ctx.store.read_many("mask", [(c, k) for c in range(len(ctx.cameras))]))
    grid = ctx.session.grid
    proj = None
    if 8 * len(ctx.cameras) * int(np.prod(grid.shape)) <= HULL_PROJECTION_BYTES:
        proj = ctx.once("hull_projection", lambda: hullmod.hull_projection(
            ctx.cameras, grid, ctx.flow_grid, params=ctx.config.hull))
    h = hullmod.visual_hull(ms, ctx.cameras, grid, ctx.flow_grid, params=ctx.config.hull, projection=proj)
    ctx.store.write("hull", (k,), np.asarray(h, dtype=bool))
    return {"voxels": int(h.sum())}
