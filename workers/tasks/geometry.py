"""The ``geometry`` task: the tomography's projection geometry, built once per run and cached.

The rays of every camera through the volume (:func:`~schlieren.pipeline.tomography.build_geometry`)
are saved as plain arrays next to the store, keyed by a content hash of the cameras, the
grid, the ray grid and the tomography parameters; the tasks that solve load them
memory-mapped, once per process (never through the task graph, STYLE.md example 7).
"""

from __future__ import annotations

import functools
import logging

import numpy as np

from schlieren.pipeline import tomography
from schlieren.storage import arrays_cache
from schlieren.workers.tasks.run_context import RunContext, TaskFailed

__all__ = ["geometry_task", "cached_geometry", "geometry_key"]

log = logging.getLogger(__package__)  # the package's logger: log records name it as before the split


@functools.lru_cache(maxsize=2)
def cached_geometry(store_path: str, key: str):
    """The geometry cached under ``key`` for the store at ``store_path``, checked and loaded
    once per process (the latest two kept)."""
    path = arrays_cache.cache_dir(store_path, "geometry", key)
    bad = arrays_cache.verify_arrays(path)  # once per process: a damaged cache is never used
    if bad:
        raise TaskFailed(f"geometry cache {bad[0]}; rerun with `schlieren run ... --verify` to rebuild it")
    return tomography.load_geometry(arrays_cache.load_arrays(path))


def geometry_key(ctx: RunContext) -> str:
    """The content hash naming the run's geometry cache."""
    return tomography.content_hash(ctx.cameras, ctx.session.grid, ctx.ray_grid,
                                   ctx.config.tomography)


def geometry_task(ctx: RunContext) -> dict:
    """Build the run's geometry unless a complete cache of it exists."""
    key = geometry_key(ctx)
    path = arrays_cache.cache_dir(ctx.store_path, "geometry", key)
    if arrays_cache.has_arrays(path) and arrays_cache.verify_arrays(path, read=False):
        arrays_cache.remove_arrays(path)  # truncated or incomplete: build it again
    if not arrays_cache.has_arrays(path):
        geom = tomography.build_geometry(ctx.cameras, ctx.session.grid, ctx.ray_grid,
                                         params=ctx.config.tomography)
        arrays_cache.save_arrays(path, tomography.save_geometry(geom))
    b = ctx.ray_binning
    if b > 1:
        log.info("tomography: one ray per %dx%d flow cells (%d rays per camera)", b, b,
                 int(np.prod(ctx.ray_grid.shape)))
    return {"key": key, "ray_binning": b, "ray_grid": list(ctx.ray_grid.shape)}
