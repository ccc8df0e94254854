"""Honest preflight: will the run fit in the workers' memory and on the store's disk?

Checked before the store is created (nothing is scheduled, nothing written), with the
model measured by ``benchmarks/memory.py`` (:mod:`schlieren.pipeline.resources`):

* **memory**: a worker runs ``threads`` tasks at once, at most ``TOMO`` of them 3-D; its
  peak is its process baseline plus those tasks' peaks. Every worker must fit its own
  memory limit, and the workers on this machine (a local cluster, or the serial loop)
  must fit its memory together;
* **disk**: the store's arrays uncompressed (noisy float32 fields barely compress) plus
  the geometry cache, minus what an existing store (a resume) already holds, must fit the
  free space of the store's file system.

A refusal is one line naming what does not fit, the estimate and how it was made.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schlieren.pipeline import resources
from schlieren.pipeline.geometry import FlowGrid
from schlieren.pipeline.tomography.binning import ray_binning, ray_grid
from schlieren.storage import location
from schlieren.storage.errors import ResourceError

log = logging.getLogger(__name__)

__all__ = ["Preflight", "WorkerSlots", "preflight", "workers_of_client", "human_bytes"]


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"  # pragma: no cover


@dataclass(frozen=True)
class WorkerSlots:
    """One worker: concurrent task slots, TOMO slots, memory limit (bytes, None = none)."""

    threads: int = 1
    tomo: int = 1
    memory_limit: float | None = None
    local: bool = True  # on this machine


@dataclass(frozen=True)
class Preflight:
    memory: resources.MemoryEstimate
    worker_peak: list[float]
    local_total: float
    machine_memory: float
    disk_needed: float
    disk_free: float | None


def _machine_memory() -> float:
    import psutil

    return float(psutil.virtual_memory().total)


def workers_of_client(client) -> list[WorkerSlots]:
    """The workers a Dask client sees (threads, TOMO resource, memory limit, local or not)."""
    import socket

    info = client.scheduler_info(n_workers=-1)
    here = {"127.0.0.1", "localhost", "::1", socket.gethostname()}
    try:
        here.add(socket.gethostbyname(socket.gethostname()))
    except OSError:
        pass
    out = []
    for addr, w in info.get("workers", {}).items():
        host = str(w.get("host") or addr.split("://")[-1].rsplit(":", 1)[0])
        limit = w.get("memory_limit") or None
        out.append(WorkerSlots(threads=int(w.get("nthreads") or 1),
                               tomo=int((w.get("resources") or {}).get("TOMO", w.get("nthreads") or 1)),
                               memory_limit=float(limit) if limit else None, local=host in here))
    return out


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p.parent != p:
        p = p.parent
    return p


def _stored_bytes(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total


def preflight(session, cfg, layout, out_path, *, workers: list[WorkerSlots]) -> Preflight:
    """Refuse (:class:`~schlieren.storage.errors.ResourceError`) a run that does not fit.

    Parameters
    ----------
    session : Session
    cfg : RunConfig
    layout : list of ArraySpec
        The store's arrays (sizes for the disk estimate).
    out_path : path or zarr store
        The store; the disk check applies to folder stores.
    workers : list of WorkerSlots
        The workers that will run the tasks (one local slot for the serial loop).
    """
    cams = session.cameras
    size = cams[0].image_size
    # the projection's rays: the tomography's ray grid (flow cells binned where they oversample the voxels)
    fg = FlowGrid(size, cfg.flow_factor)
    fg = ray_grid(fg, ray_binning(cams, session.grid, fg, cfg.tomography.ray_binning))
    est = resources.estimate_memory(cams, session.grid, fg, size)
    peaks = [est.worker(w.threads, w.tomo) for w in workers]
    machine = _machine_memory()
    local = sum(p for p, w in zip(peaks, workers) if w.local)
    how = (f"{human_bytes(est.task_3d)} per {est.stage_3d} task ({est.voxels} voxels, {est.crossings:.3g} "
           f"ray-voxel crossings) and {human_bytes(est.task_2d)} per 2-D task ({size[0]}x{size[1]} images), "
           f"plus {human_bytes(resources.PROCESS_BYTES)} per process, as measured by benchmarks/memory.py, and "
           f"up to {human_bytes(est.held_3d)} of a warm-start block's projection kept between solves")
    for w, p in zip(workers, peaks):
        if w.memory_limit is not None and p > w.memory_limit:
            raise ResourceError(
                f"a worker running {w.threads} task(s) at once ({w.tomo} TOMO) needs about {human_bytes(p)}, more "
                f"than its memory limit of {human_bytes(w.memory_limit)}: {how}; give workers more memory, fewer "
                "threads, or use a larger voxel_size", file=str(session.manifest_path), field="volume.voxel_size")
    n_local = sum(1 for w in workers if w.local)
    if n_local and local > machine:
        fit = max(1, int(machine // max(peaks)))
        raise ResourceError(
            f"{n_local} worker(s) on this machine need about {human_bytes(local)} together, more than its "
            f"{human_bytes(machine)}: {how}; use at most {fit} worker(s) (--workers {fit}) or a larger "
            "voxel_size", file=str(session.manifest_path), field="volume.voxel_size")
    arrays = 0.0
    for spec in layout:
        itemsize = 16 if spec.dtype == "str" else np.dtype(spec.dtype).itemsize
        arrays += math.prod(spec.shape) * itemsize
    need = resources.estimate_disk(arrays, cams, session.grid, fg)
    free = None
    if isinstance(out_path, (str, os.PathLike)) and not location.is_url(os.fspath(out_path)):
        out = Path(os.fspath(out_path))
        have = _stored_bytes(out) if out.is_dir() else 0
        free = float(shutil.disk_usage(_nearest_existing(out)).free)
        if need - have > free:
            raise ResourceError(
                f"the store needs about {human_bytes(need)} (arrays uncompressed plus the tomography geometry "
                f"cache{'; ' + human_bytes(have) + ' already written' if have else ''}) but only "
                f"{human_bytes(free)} are free there: free space or choose another --out", file=str(out),
                field="disk")
    log.info("preflight: worker peak %s, store %s", human_bytes(max(peaks)), human_bytes(need))
    return Preflight(memory=est, worker_peak=peaks, local_total=local, machine_memory=machine,
                     disk_needed=need, disk_free=free)
