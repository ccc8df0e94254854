"""One task = one stage at one index: read inputs, call the pure kernel, write whole chunks.

Tasks take the store path, the stage name and an index, and return a small receipt
(STYLE.md example 7): frames, flow fields and the projection geometry never travel
through the task graph. Per-process caches hold the opened store, the session, the
reference images and the memory-mapped tomography geometry, keyed by the store path and
the run's token (a store deleted and made again for another run at the same path gets
fresh caches). Values an upstream task has finished writing never change during a run,
so the context also keeps the small per-camera arrays and the recently read flow and
potential chunks (a mask task reads three frames of each; each zarr read costs about a
millisecond, more in a busy worker). The completion marker is written last, so a task
killed midway is simply run again.
"""

from __future__ import annotations

import functools
import dataclasses
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline import derived, flow as flowmod, frame_quality as fq, hull as hullmod, masks as masksmod
from schlieren.pipeline import poisson, sync, tomography
from schlieren.pipeline.geometry import Camera, FlowGrid, pixel_footprint
from schlieren.pipeline.stages import RunConfig, config_from_dict, kernel_kwargs, middle_frame, stage
from schlieren.pipeline.tomography.reg_choice import RUN_SMALLEST_WEIGHT
from schlieren.pipeline.tomography.restriction import SHARED_RESTRICTIONS
from schlieren.storage import arrays_cache
from schlieren.storage.errors import SessionError
from schlieren.storage.frames import open_frames, read_reference
from schlieren.storage.session import Session, load_session
from schlieren.storage.store import ResultStore
from schlieren.workers.monitoring import log_receipt

log = logging.getLogger(__name__)

__all__ = ["run_task", "run_tasks", "flush_writes", "TaskFailed", "RunContext", "context"]


class TaskFailed(Exception):
    """A task failed on its data; the message names the stage, camera and frame."""


@dataclass
class RunContext:
    """Everything a task needs that is per run, opened once per worker process."""

    store_path: str
    store: ResultStore
    session: Session
    config: RunConfig
    flow_grid: FlowGrid
    first_frame: int  # session frame of output frame 0
    n_frames: int
    raw_first: int  # session frame of flow_raw index 0
    n_raw: int
    video_slots: dict = field(default_factory=dict)  # camera -> VideoFrames.scan() made before the run

    @property
    def cameras(self) -> list[Camera]:
        return self.session.cameras

    @property
    def ray_binning(self) -> int:
        """Flow cells per tomography ray along each image axis
        (:func:`~schlieren.pipeline.tomography.ray_binning`; ``tomography.ray_binning``)."""
        return self._once("ray_binning", lambda: tomography.ray_binning(
            self.cameras, self.session.grid, self.flow_grid, self.config.tomography.ray_binning))

    @property
    def ray_grid(self) -> FlowGrid:
        """The grid of the tomography's rays (the flow grid when :attr:`ray_binning` is 1)."""
        return tomography.ray_grid(self.flow_grid, self.ray_binning)

    def tomography_flows(self, k: int) -> np.ndarray:
        """Frame ``k``'s flow of every camera on the ray grid (block means), (C, h, w, 2)."""
        flows = np.stack(self.read_upstream_many("flow", [(c, k) for c in range(len(self.cameras))]))
        return tomography.bin_cells(flows, self.ray_binning)

    _sources: dict = field(default_factory=dict, repr=False)
    _small: dict = field(default_factory=dict, repr=False)
    _chunks: OrderedDict = field(default_factory=OrderedDict, repr=False)
    _chunk_bytes: int = 0

    #: Bytes of upstream chunks kept by :meth:`read_upstream` per process.
    CHUNK_CACHE_BYTES = 64 * 2 ** 20

    def frames(self, c: int):
        src = self._sources.get(c)
        if src is None and c in self.session.opened:  # the run's own process checked the files
            src = self._sources[c] = self.session.opened[c]
        if src is None:
            s = self.session.sources[c]
            slots = self.video_slots.get(s.name)
            src = self._sources[c] = open_frames(s, camera_name=s.name,
                                                 slots=(slots[0], tuple(slots[1])) if slots else None)
        return src

    def frame(self, c: int, f: int) -> np.ndarray:
        """Capture frame ``f`` of camera ``c``; the two latest frames read per camera are kept
        (a deflection task compares its frame with the one before, which the task of the
        previous frame read as its own). The earliest frame is dropped, not the earliest
        read: a task reads frame ``f`` and then ``f - 1``, and the next one needs ``f``."""
        kept = self._small.setdefault(("frames", c), {})
        img = kept.get(f)
        if img is None:
            img = kept[f] = self.frames(c).read(f)
            while len(kept) > 2:
                del kept[min(kept)]
        return img

    #: Entries kept by :meth:`memo` per process.
    MEMO_ITEMS = 64

    def memoized(self, key) -> bool:
        """Whether :meth:`memo` holds ``key``."""
        return key in self._small.get("__memo__", ())

    def memo(self, key, make):
        """``make()``, remembered for the last :data:`MEMO_ITEMS` keys (LRU): per-frame
        intermediate results that the tasks of neighbouring frames share. Keys must name
        everything the value depends on within the run."""
        memo = self._small.setdefault("__memo__", OrderedDict())
        if key in memo:
            memo.move_to_end(key)
            return memo[key]
        value = memo[key] = make()
        while len(memo) > self.MEMO_ITEMS:
            memo.popitem(last=False)
        return value

    def _once(self, key, make):
        if key not in self._small:
            self._small[key] = make()
        return self._small[key]

    def reference(self, c: int, parity: int | None = None) -> np.ndarray:
        """Camera ``c``'s reference (for interlaced cameras: that of the fields of ``parity``)."""
        s = self.session.sources[c]
        return self._once(("reference", c, parity), lambda: read_reference(s, camera_name=s.name, parity=parity))

    def prepared_reference(self, c: int, parity: int | None = None):
        """The reference's pyramid and spline coefficients, prepared once per camera (and field
        parity) per process."""
        params = self.config.flow
        return self._once(("prepared_reference", c, parity),
                          lambda: flowmod.prepare_reference(self.reference(c, parity), **params.reference_kwargs()))

    def time_offset(self, c: int) -> float:
        return self._once(("time_offset", c), lambda: float(self.store.read("time_offset", (c,))))

    def camera_with_offset(self, c: int) -> Camera:
        return self.cameras[c].with_time_offset(self.time_offset(c))

    def flash_frames(self, c: int) -> tuple[int, ...]:
        def read():
            lo, hi = (int(v) for v in self.store.read("flash_frames", (c,)))
            return tuple(range(lo, hi + 1)) if lo >= 0 else ()
        return self._once(("flash_frames", c), read)

    def times(self) -> np.ndarray:
        """The output frames' instants (written once by the clock stage)."""
        return self._once("time", lambda: np.asarray(self.store.read("time", ()), dtype=np.float64))

    def mask_threshold(self) -> float:
        return self._once("mask_threshold", lambda: float(self.store.read("mask_threshold", ())[0]))

    def read_upstream_many(self, name: str, indices: list[tuple[int, ...]]) -> list[np.ndarray]:
        """:meth:`read_upstream` of each of ``indices``, the uncached ones read together
        (:meth:`ResultStore.read_many`: concurrent requests in an object store)."""
        missing = [i for i in dict.fromkeys(indices) if (name, i) not in self._chunks]
        if len(missing) > 1:
            for i, a in zip(missing, self.store.read_many(name, missing)):
                self._cache_chunk((name, i), a)
        return [self.read_upstream(name, i) for i in indices]

    def _cache_chunk(self, key, a: np.ndarray) -> None:
        a.flags.writeable = False
        self._chunks[key] = a
        self._chunk_bytes += a.nbytes
        while self._chunk_bytes > self.CHUNK_CACHE_BYTES and len(self._chunks) > 1:
            _, old = self._chunks.popitem(last=False)
            self._chunk_bytes -= old.nbytes

    def read_upstream(self, name: str, index: tuple[int, ...]) -> np.ndarray:
        """``store.read(name, index)`` of a chunk an upstream task has finished, cached (LRU).

        Only for chunks whose producer this task depends on: they are final for the run.
        The returned array is shared: do not modify it.
        """
        key = (name, index)
        a = self._chunks.get(key)
        if a is not None:
            self._chunks.move_to_end(key)
            return a
        a = self.store.read(name, index)
        self._cache_chunk(key, a)
        return a


#: Sessions this process has loaded for a run (:func:`adopt_session`), by (location, frames).
_ADOPTED: OrderedDict = OrderedDict()


def adopt_session(location: str, session: Session) -> None:
    """Let this process's contexts of runs of ``session`` (stored under ``location``, the
    store's ``session_path``) use it instead of loading the manifest again: the serial loop
    runs in the process that validated the session, and from a bucket each load is several
    requests (three loads per run before). Sessions are frozen; the latest four are kept."""
    key = (str(location), tuple(int(v) for v in session.frames))
    _ADOPTED[key] = session
    _ADOPTED.move_to_end(key)
    while len(_ADOPTED) > 4:
        _ADOPTED.popitem(last=False)


@functools.lru_cache(maxsize=4)
def context(store_path: str, run_token: str = "") -> RunContext:
    """The run's context in this process (``run_token`` tells apart runs at one path)."""
    store = ResultStore.open(store_path, write_behind=True)  # run_task(s) flush before returning
    a = store.attrs
    run = a["run"]
    session = _ADOPTED.get((str(a["session_path"]), tuple(int(v) for v in run["frames"])))
    if session is None:
        session = load_session(a["session_path"], frames=tuple(run["frames"]), check_files=False)
    cfg = config_from_dict(a["params"])
    return RunContext(store_path=store_path, store=store, session=session, config=cfg,
                      flow_grid=FlowGrid(session.cameras[0].image_size, cfg.flow_factor),
                      first_frame=int(run["frames"][0]), n_frames=int(run["n_frames"]),
                      raw_first=int(run["raw_first"]), n_raw=int(run["n_raw"]),
                      video_slots=dict(run.get("video_slots") or {}))


@functools.lru_cache(maxsize=2)
def _geometry(store_path: str, key: str):
    path = arrays_cache.cache_dir(store_path, "geometry", key)
    bad = arrays_cache.verify_arrays(path)  # once per process: a damaged cache is never used
    if bad:
        raise TaskFailed(f"geometry cache {bad[0]}; rerun with `schlieren run ... --verify` to rebuild it")
    return tomography.load_geometry(arrays_cache.load_arrays(path))


def _geometry_key(ctx: RunContext) -> str:
    return tomography.content_hash(ctx.cameras, ctx.session.grid, ctx.ray_grid,
                                   ctx.config.tomography)


# --------------------------------------------------------------------------------------
# stage glue: each returns a dict of extra receipt fields
# --------------------------------------------------------------------------------------

def _sync(ctx: RunContext, c: int) -> dict:
    cam = ctx.cameras[c]
    s = ctx.session
    if s.strobe_search is not None:
        a, b = s.strobe_search
        src = ctx.frames(c)
        b = min(b, len(src))
        src.prefetch(range(a, b))
        gone = set(src.dropped)
        rows = np.stack([src.read(f).mean(axis=1) if f not in gone else np.full(cam.height, np.nan)
                         for f in range(a, b)])
        if gone & set(range(a, b)):  # a dropped frame holds no flash: its rows at their median
            rows = np.where(np.isnan(rows), np.nanmedian(rows, axis=0, keepdims=True), rows)
        try:
            det = sync.detect_flash(rows, **kernel_kwargs(ctx.config.flash, sync.detect_flash))
        except ValueError as exc:
            raise TaskFailed(f"sync: camera {cam.name}: frames {a}..{b - 1}: {exc}") from None
        off = sync.offset_from_flash(det, first_frame=a, frame_rate=s.frame_rate,
                                     line_time=cam.line_time)
        flash = sorted(sync.flash_frames(det, first_frame=a))
        span = (flash[0], flash[-1]) if flash else (-1, -1)
        info = {"offset": off, "flash_frames": list(span)}
    else:
        off = float(cam.time_offset)
        span = (-1, -1)
        info = {"offset": off}
    ctx.store.write("time_offset", (c,), np.array([off], dtype=np.float64))
    ctx.store.write("flash_frames", (c,), np.array([span], dtype=np.int64))
    return info


def _clock(ctx: RunContext) -> dict:
    offsets = np.array([float(ctx.store.read("time_offset", (c,))) for c in range(len(ctx.cameras))])
    line_time = float(np.mean([cam.line_time for cam in ctx.cameras]))
    times = sync.output_times(ctx.first_frame, ctx.n_frames, offsets=offsets,
                              frame_rate=ctx.session.frame_rate,
                              height=ctx.cameras[0].height, line_time=line_time)
    ctx.store.write("time", (), np.asarray(times, dtype=np.float64))
    return {"t0": float(times[0])}


def _deflection(ctx: RunContext, c: int, j: int) -> dict:
    f = ctx.raw_first + j
    src = ctx.frames(c)
    if f in src.dropped:  # no frame at this time: excluded by resampling, like a dark frame
        _write_no_flow(ctx, c, j, fq.dropped_quality())
        log.warning("camera %s, frame %d: dropped by the camera; excluded from the reconstruction",
                    ctx.cameras[c].name, f)
        return {"max_px": 0.0, "excluded": fq.flag_names(fq.DROPPED)}
    if not ctx.first_frame <= f < ctx.first_frame + ctx.n_frames and not raw_frame_needed(ctx, c, f):
        # a margin frame no output instant reads (the plan made this task wait for the clock)
        _write_no_flow(ctx, c, j, fq.unused_quality())
        return {"unused": True}
    img = ctx.frame(c, f)
    parity = src.parity(f) if hasattr(src, "parity") else None  # interlaced fields
    params = flow_params(ctx, c)
    d = flowmod.deflection_stage(ctx.prepared_reference(c, parity), img, params)
    ctx.store.write("flow_raw", (c, j), d.astype(np.float32))
    # dark, saturated or frozen frames: flagged here, excluded by resampling
    q = _frame_quality(ctx, c, f, img)
    ctx.store.write("frame_quality", (c, j), q)
    out = {"max_px": float(np.nanmax(np.abs(d))) if np.isfinite(d).any() else 0.0, "window": params.window}
    bad = fq.flag_names(q[3])
    if bad:
        out["excluded"] = bad
        log.warning("camera %s, frame %d: %s; excluded from the reconstruction", ctx.cameras[c].name, f,
                    ", ".join(bad))
    return out


def _write_no_flow(ctx: RunContext, c: int, j: int, quality: np.ndarray) -> None:
    """Raw frame ``j`` of camera ``c`` has no flow (dropped, or not needed): a NaN field and
    its quality vector, so every chunk of the task exists."""
    ctx.store.write("flow_raw", (c, j), np.full(tuple(ctx.flow_grid.shape) + (2,), np.nan, np.float32))
    ctx.store.write("frame_quality", (c, j), quality)


def raw_frame_needed(ctx: RunContext, c: int, f: int) -> bool:
    """Whether any output instant's resampling (:func:`_resample`) will read raw frame ``f``
    of camera ``c``.

    The same ranges as :func:`_resample`'s: ``sync.frames_needed`` over each output frame's
    window, its excluded frames the flash and the flagged frames. Only the ends of a range
    move past excluded frames, so the flags needed are those of the range's end on ``f``'s
    side, added one at a time (each from the frame itself, as its own deflection task
    flags it: read here, not waited for). Unreadable: needed (its own task reports it).
    """
    halo = stage("resample").frame_halo
    near = f - ctx.first_frame  # the output frames whose window holds f are within the halo
    for k in range(max(0, near - halo), min(ctx.n_frames, near + halo + 1)):
        window = _resample_window(ctx, k)
        if not window[0] <= f < window[1]:
            continue
        excluded = set(ctx.flash_frames(c))
        while True:
            lo, hi = _raw_range(ctx, c, k, window, excluded)
            if lo <= f <= hi:
                return True
            end = lo if f < lo else hi
            if end in excluded:
                break
            try:
                bad = frame_flags(ctx, c, end) & fq.PROBLEMS
            except SessionError:
                return True
            if not bad:
                break
            excluded.add(end)
    return False


def frame_flags(ctx: RunContext, c: int, f: int) -> int:
    """The flags :func:`_deflection` stores for capture frame ``f`` of camera ``c``, from the
    frame (and the one before it) alone."""
    if f in ctx.frames(c).dropped:
        return fq.DROPPED
    return int(_frame_quality(ctx, c, f, ctx.frame(c, f))[3])


def _frame_quality(ctx: RunContext, c: int, f: int, img: np.ndarray) -> np.ndarray:
    """:func:`~schlieren.pipeline.frame_quality.frame_quality` of frame ``f`` (image ``img``)
    of camera ``c`` against its reference and the frame before it."""
    src = ctx.frames(c)
    dtype = src.raw_dtype
    full = float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None
    parity = src.parity(f) if hasattr(src, "parity") else None
    ref_mean = ctx._once(("reference_mean", c, parity),
                         lambda: float(np.mean(ctx.reference(c, parity), dtype=np.float64)))
    try:
        previous = ctx.frame(c, f - 1) if f > 0 else None
    except SessionError:  # the previous frame is unreadable (its own task reports it): not frozen
        previous = None
    if dtype == np.uint8 and src.one_channel:
        # the 8-bit samples themselves (exact): their sums are the same integers, and OpenCV
        # takes them 4x faster than float32 (1.9 -> 0.7 ms at 1440x1080, the conversions included)
        img = img.astype(np.uint8)
        previous = None if previous is None else previous.astype(np.uint8)
    # grey levels of integer samples are finite (no NaN check over the frame)
    return fq.frame_quality(img, previous, reference_mean=ref_mean, full_scale=full, finite=full is not None)


def bad_frames(ctx: RunContext, c: int, lo: int, hi: int) -> tuple[int, ...]:
    """Capture frames in ``[lo, hi]`` of camera ``c`` flagged dark, saturated or frozen."""
    out = []
    for f in range(max(lo, ctx.raw_first), min(hi, ctx.raw_first + ctx.n_raw - 1) + 1):
        q = ctx.read_upstream("frame_quality", (c, f - ctx.raw_first))
        if np.isfinite(q[3]) and int(q[3]):
            out.append(f)
    return tuple(out)


def flow_params(ctx: RunContext, c: int):
    """Camera ``c``'s flow parameters: the LK window from the voxel footprint (``window_per_voxel``)."""
    params = ctx.config.flow
    if params.window_per_voxel <= 0:
        return params

    def make():
        grid = ctx.session.grid
        centre = 0.5 * (np.asarray(grid.vmin) + np.asarray(grid.vmax))
        px = grid.voxel_size / pixel_footprint(ctx.cameras[c], centre)
        return dataclasses.replace(params, window=flowmod.window_for_voxel(px, params.window_per_voxel))

    return ctx._once(("flow_params", c), make)


def _resample_window(ctx: RunContext, k: int) -> tuple[int, int]:
    """Half-open range of the raw frames output frame ``k``'s resample task waits for (the
    plan's ``frame_halo`` window): it never reads beyond them."""
    centre = ctx.first_frame + k
    halo = stage("resample").frame_halo
    return max(ctx.raw_first, centre - halo), min(ctx.raw_first + ctx.n_raw, centre + halo + 1)


def _raw_range(ctx: RunContext, c: int, k: int, window: tuple[int, int], excluded) -> tuple[int, int]:
    """Inclusive range ``(lo, hi)`` of camera ``c``'s raw frames that output frame ``k``'s
    resampling reads: ``sync.frames_needed`` past the ``excluded`` frames, within ``window``
    and the stored raw frames."""
    cam = ctx.cameras[c]
    f0, f1 = sync.frames_needed(float(ctx.times()[k]), offset=ctx.time_offset(c),
                                frame_rate=ctx.session.frame_rate, line_time=cam.line_time,
                                height=cam.height, excluded_frames=tuple(sorted(excluded)), frame_range=window)
    last = ctx.raw_first + ctx.n_raw - 1
    lo = max(ctx.raw_first, min(f0, last))
    return lo, max(lo, min(f1 - 1, last))


def _resample(ctx: RunContext, c: int, k: int) -> dict:
    s = ctx.session
    cam = ctx.cameras[c]
    off = ctx.time_offset(c)
    t = float(ctx.times()[k])
    window = _resample_window(ctx, k)
    bad = bad_frames(ctx, c, window[0], window[1] - 1)
    excluded = tuple(sorted(set(ctx.flash_frames(c)) | set(bad)))
    lo, hi = _raw_range(ctx, c, k, window, excluded)
    # the raw flows are final once their deflection tasks (this task's dependencies) are
    # done: neighbouring instants of a batched task share them, read and keyed once
    fields = [ctx.read_upstream("flow_raw", (c, f - ctx.raw_first)) for f in range(lo, hi + 1)]
    raw = np.stack(fields)
    digests = [ctx.memo(("flow_raw_digest", c, f), lambda a=a: sync.field_digest(a))
               for f, a in zip(range(lo, hi + 1), fields)]
    out = sync.resample_flow(raw, lo, t, offset=off, frame_rate=s.frame_rate,
                             line_time=cam.line_time, flow_grid=ctx.flow_grid,
                             excluded_frames=excluded, params=ctx.config.resample, digests=digests)
    ctx.store.write("flow", (c, k), np.asarray(out, dtype=np.float32))
    return {"raw_frames": [lo, hi], **({"excluded_frames": list(bad)} if bad else {})}


def _potential(ctx: RunContext, c: int, k: int) -> dict:
    """Potential of one camera-frame (the flow Poisson-integrated, paper sec. 4) and its summary.

    The summary (:func:`~schlieren.pipeline.masks.potential_summary`) is the map step of
    the sequence-wide threshold, computed here while the potential is in memory so the
    single ``threshold`` task that every mask waits for only pools small vectors.
    """
    f = ctx.read_upstream("flow", (c, k))
    p = np.asarray(masksmod.flow_potential(f), dtype=np.float32)
    kw = kernel_kwargs(ctx.config.masks, masksmod.potential_summary)
    ctx.store.write("potential", (c, k), p)
    ctx.store.write("potential_summary", (c, k), masksmod.potential_summary(p, **kw))
    return {}


def _threshold(ctx: RunContext) -> dict:
    params = ctx.config.masks
    # stores of versions that wrote no summaries are not resumed (no chunk checksums), so
    # every summary under a set potential marker exists (a lost one raises ChunkError)
    summaries = [ctx.store.read("potential_summary", (c, k))
                 for c in range(len(ctx.cameras)) for k in range(ctx.n_frames)]
    thr = masksmod.threshold_from_summaries(
        summaries, **kernel_kwargs(params, masksmod.threshold_from_summaries))
    ctx.store.write("mask_threshold", (), np.array([thr], dtype=np.float64))
    return {"threshold": float(thr)}


def _mask(ctx: RunContext, c: int, k: int) -> dict:
    params = ctx.config.masks
    h = params.temporal_radius
    ks = [min(max(i, 0), ctx.n_frames - 1) for i in range(k - h, k + h + 1)]
    thr = ctx.mask_threshold()
    kw = kernel_kwargs(params, masksmod.frame_evidence)

    def evidence(i):  # masksmod.make_mask, with each frame's evidence made once per process
        return masksmod.frame_evidence(ctx.read_upstream("potential", (c, i)), thr,
                                       flow=ctx.read_upstream("flow", (c, i)), **kw)

    keys = {i: ("mask_evidence", c, i, thr) for i in ks}
    todo = [(c, i) for i, key in keys.items() if not ctx.memoized(key)]
    if todo:  # read the frames still needed together (concurrent requests on object stores)
        ctx.read_upstream_many("potential", todo)
        ctx.read_upstream_many("flow", todo)
    ev = [ctx.memo(key, lambda i=i: evidence(i)) for i, key in keys.items()]
    m = masksmod.mask_from_evidence(ev, **kernel_kwargs(params, masksmod.mask_from_evidence))
    ctx.store.write("mask", (c, k), np.asarray(m, dtype=bool))
    return {"fraction": float(np.mean(m))}


def _geometry_stage(ctx: RunContext) -> dict:
    key = _geometry_key(ctx)
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


#: Largest :func:`~schlieren.pipeline.hull.hull_projection` a process keeps for the hulls of
#: a sequence (8 bytes per voxel and camera: 55 MB for 16 cameras on the paper-scale
#: session's 432,000 voxels, where it takes the hull task from 247 to 43 ms); above
#: it each hull projects its candidates itself.
HULL_PROJECTION_BYTES = 256 * 2 ** 20


def _hull(ctx: RunContext, k: int) -> dict:
    ms = np.stack(ctx.store.read_many("mask", [(c, k) for c in range(len(ctx.cameras))]))
    grid = ctx.session.grid
    proj = None
    if 8 * len(ctx.cameras) * int(np.prod(grid.shape)) <= HULL_PROJECTION_BYTES:
        proj = ctx._once("hull_projection", lambda: hullmod.hull_projection(
            ctx.cameras, grid, ctx.flow_grid, params=ctx.config.hull))
    h = hullmod.visual_hull(ms, ctx.cameras, grid, ctx.flow_grid, params=ctx.config.hull, projection=proj)
    ctx.store.write("hull", (k,), np.asarray(h, dtype=bool))
    return {"voxels": int(h.sum())}


def _regularisation(ctx: RunContext) -> dict:
    """The tomography weight for the run: Morozov's discrepancy principle on the middle frame.

    The noise of the right-hand side is measured on the rays outside every camera's mask
    (no flow: pure measurement noise); the weight whose data residual matches it is
    chosen on the middle frame's hull and used for every frame (one weight per run keeps
    the frames comparable and costs one frame's search: a cold solve at the search's start
    and about 1-5 warm-started ones bracketing the crossing, :func:`~schlieren.pipeline.
    tomography.reg_choice.choose_reg_weight`).
    """
    params = ctx.config.tomography
    out = {"reg_choice": params.reg_choice}
    weight, noise = float(params.reg_weight), np.full(3, np.nan)
    C = len(ctx.cameras)
    window = choose_flow_window(ctx)
    ctx.store.write("flow_window", (), window.astype(np.float64))
    out["flow_window"] = [float(v) for v in window]
    # The weight is chosen with the image-space model whatever flow_window_space says: it
    # fits the cell data to their noise, which the discrepancy principle needs; the volume
    # model's misfit stays above it on 16 cameras (the search would end at its smallest
    # weight). Measured on the realistic family's tune cases: volume solves with the weight
    # chosen this way +0.03 to +0.18 dB over volume solves with their own choice.
    blur = _window_model(ctx, window, space="image")
    if params.reg_choice == "discrepancy" and ctx.n_frames > 0:
        k = middle_frame(ctx.n_frames)  # the plan's "middle" dependency: these masks are done
        geom = _geometry(ctx.store_path, _geometry_key(ctx))
        masks = np.stack([ctx.store.read("mask", (c, k)) for c in range(C)])
        flows = ctx.tomography_flows(k)
        rhs = tomography.rhs_from_flows(geom, flows, n_ambient=params.n_ambient)
        quiet = tomography.bin_quiet(~masks, ctx.ray_binning)
        noise = tomography.rhs_noise(rhs, quiet)
        if np.all(np.isfinite(noise)):
            snr = tomography.rhs_snr(rhs, ~quiet, noise)
            out["ray_snr"] = [float(v) for v in snr]
            log.info("regularisation: rays in the masks carry %s x their noise (RMS; x, y, z)",
                     np.array2string(snr, precision=3))
        hull = hullmod.visual_hull(masks, ctx.cameras, ctx.session.grid, ctx.flow_grid, params=ctx.config.hull)
        if np.all(np.isfinite(noise)) and noise.any() and hull.any():
            choice = tomography.choose_reg_weight(geom, flows, hull, noise, params=params,
                                                  smallest=RUN_SMALLEST_WEIGHT, **blur)
            weight = choice.reg_weight
            out["path"] = [[float(a), float(b)] for a, b in choice.path]
            log.info("regularisation: weight %.4g from the discrepancy principle (noise %s, frame %d)",
                     weight, np.array2string(noise, precision=3), k)
        else:
            log.warning("regularisation: no noise measurable outside the masks; using reg_weight %.4g", weight)
    ctx.store.write("reg_weight", (), np.array([weight], dtype=np.float64))
    ctx.store.write("rhs_noise", (), np.asarray(noise, dtype=np.float64))
    out.update({"reg_weight": weight, "rhs_noise": [float(v) for v in noise]})
    return out


def choose_flow_window(ctx: RunContext) -> np.ndarray:
    """Per-camera width (flow cells) of the flow averaging the tomography models
    (``TomoParams.model_flow_window``; :func:`schlieren.pipeline.flow.measurement_sigma` times
    ``TomoParams.flow_window_scale``), 0 = none."""
    C = len(ctx.cameras)
    if not ctx.config.tomography.model_flow_window:
        return np.zeros(C)
    scale = float(ctx.config.tomography.flow_window_scale)
    return np.array([scale * flowmod.measurement_sigma(flow_params(ctx, c)) / ctx.flow_grid.factor
                     for c in range(C)])


def _window_model(ctx: RunContext, window: np.ndarray, space: str | None = None) -> dict:
    """The solver's keyword for the flow averaging of per-camera widths ``window`` (flow
    cells): ``blur`` (:class:`~schlieren.pipeline.tomography.MeasurementBlur`, image space)
    or ``volume_blur`` (sigma in voxels, :func:`~schlieren.pipeline.tomography.volume_sigma`)
    as ``space`` (default ``TomoParams.flow_window_space``) says; empty if every width is 0."""
    window = np.asarray(window, dtype=np.float64)
    if not np.any(window > 0):
        return {}
    window = tomography.binned_sigma(window, ctx.ray_binning)  # in ray-grid cells
    rays = ctx.ray_grid
    if (space or ctx.config.tomography.flow_window_space) == "image":
        return {"blur": tomography.MeasurementBlur((len(ctx.cameras),) + tuple(rays.shape), window)}
    return {"volume_blur": tomography.volume_sigma(window, ctx.cameras, ctx.session.grid, rays.factor)}


def flow_blur(ctx: RunContext) -> dict:
    """The flow averaging the regularisation stage chose (stored ``flow_window``), as the
    solver's keyword (:func:`_window_model`)."""
    return ctx._once("flow_blur", lambda: _window_model(
        ctx, np.asarray(ctx.store.read("flow_window", ()), dtype=np.float64)))


def tomo_params(ctx: RunContext):
    """The run's tomography parameters with the weight the regularisation stage chose."""
    params = ctx.config.tomography
    w = ctx._once("reg_weight", lambda: float(ctx.store.read("reg_weight", ())[0]))
    return dataclasses.replace(params, reg_weight=w) if np.isfinite(w) else params


def _tomography(ctx: RunContext, k: int) -> dict:
    geom = _geometry(ctx.store_path, _geometry_key(ctx))
    flows = ctx.tomography_flows(k)
    hull = ctx.store.read("hull", (k,))
    x0 = None
    if k % max(ctx.config.warm_start_block, 1) != 0:
        x0 = ctx.store.read("gradient", (k - 1,))
    if ctx.config.reconstruction == "direct":
        # beyond the paper: solve for n - 1 directly; the gradient stored is its derivative
        r0 = ctx.store.read("refractivity", (k - 1,)).astype(np.float64) if x0 is not None else None
        r, info = tomography.solve_refractivity(
            geom, flows, hull, ctx.session.grid, r_ambient=ctx.session.medium.refractivity_ambient,
            params=ctx.config.direct, x0=r0)
        h = ctx.session.grid.voxel_size
        gz, gy, gx = np.gradient(np.asarray(r, dtype=np.float64), h)
        ctx.store.write("refractivity", (k,), np.asarray(r, dtype=np.float32))
        ctx.store.write("gradient", (k,), np.stack([gx, gy, gz], axis=-1).astype(np.float32))
        return _info_dict(info)
    params = tomo_params(ctx)
    grad, info = tomography.solve_gradient(geom, flows, hull, params=params, x0=x0,
                                           support=_block_support(ctx, k, params.hull_dilation), **flow_blur(ctx))
    ctx.store.write("gradient", (k,), np.asarray(grad, dtype=np.float32))
    return _info_dict(info)


def _block_support(ctx: RunContext, k: int, dilation: int) -> np.ndarray:
    """The union of the basis sets of frame ``k``'s warm-start block (the plan makes every
    tomography task wait for its block's hulls): each frame's system is selected inside
    this shared restriction, which a worker builds once per block (``solve_gradient``'s
    ``support``; the same system as the frame's own restriction)."""
    B = max(ctx.config.warm_start_block, 1)
    lo = k - k % B
    frames = range(lo, min(lo + B, len(ctx.times())))
    key = (lo, dilation)
    # as many blocks as the solver keeps restrictions for (a worker alternates two blocks)
    held = ctx._small.setdefault("block_support", {})
    if key not in held:
        while len(held) >= SHARED_RESTRICTIONS:
            held.pop(next(iter(held)))
        held[key] = tomography.block_support([ctx.store.read("hull", (i,)) for i in frames], dilation)
    return held[key]


def _integrate(ctx: RunContext, k: int) -> dict:
    grad = np.asarray(ctx.store.read("gradient", (k,)), dtype=np.float64)
    hull = ctx.store.read("hull", (k,))
    medium = ctx.session.medium
    if ctx.config.reconstruction == "direct":  # refractivity came out of the solve already
        r = ctx.store.read("refractivity", (k,)).astype(np.float64)
        info = None
    else:
        r, info = poisson.integrate(grad, hull, ctx.session.grid,
                                    r_ambient=medium.refractivity_ambient, params=ctx.config.poisson)
        ctx.store.write("refractivity", (k,), np.asarray(r, dtype=np.float32))
    ctx.store.write("density", (k,), np.asarray(derived.density(r, medium), dtype=np.float32))
    ctx.store.write("temperature", (k,), np.asarray(derived.temperature(r, medium), dtype=np.float32))
    return _info_dict(info)


def _info_dict(info) -> dict:
    out = {}
    for name in ("iterations", "residual", "relative_residual", "converged", "unknowns", "rays", "restriction",
                 "sign", "clipped"):
        if hasattr(info, name):
            v = getattr(info, name)
            out[name] = v.tolist() if isinstance(v, np.ndarray) else v
    return out


_GLUE = {
    "sync": _sync, "clock": _clock, "deflection": _deflection,
    "regularisation": _regularisation,
    "resample": _resample, "potential": _potential, "threshold": _threshold, "mask": _mask,
    "geometry": _geometry_stage, "hull": _hull, "tomography": _tomography,
    "integrate": _integrate,
}


def _describe(stage_name: str, index: tuple[int, ...], ctx: RunContext | None) -> str:
    st = stage(stage_name)
    parts = [stage_name]
    for dim, i in zip(st.over, index):
        if dim == "camera" and ctx is not None:
            parts.append(f"camera {ctx.cameras[i].name}")
        elif dim == "frame" and ctx is not None:
            parts.append(f"frame {ctx.first_frame + i}")
        elif dim == "raw_frame" and ctx is not None:
            parts.append(f"frame {ctx.raw_first + i}")
        else:
            parts.append(f"{dim} {i}")
    return ", ".join(parts)


def _worker_address() -> str | None:
    """The Dask worker running this task, or None (the serial loop)."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return None


def run_task(store_path: str, stage_name: str, index: tuple[int, ...], *_deps, run_token: str = "") -> dict:
    """Run one stage at one index and return its receipt.

    Extra positional arguments are the receipts of the tasks this one waits for (the Dask
    executor passes them so the graph carries the dependencies); they are ignored.
    ``run_token`` (the plan's) keys this process's caches of the run.
    """
    receipt = _run_one(store_path, stage_name, index, run_token)
    flush_writes(store_path, run_token, stage_name)
    return receipt


def flush_writes(store_path: str, run_token: str = "", stage_name: str = "store") -> None:
    """Wait until this process's writes to the run's store are stored.

    In an object store chunks and markers go out in the background (storage/remote.py);
    a task's dependents may run elsewhere, so every Dask task calls this before it
    returns. A failed write raises :class:`TaskFailed` naming the array and index (its
    marker was not sent, so a rerun computes it again).
    """
    try:
        context(str(store_path), str(run_token)).store.flush()
    except OSError as exc:
        raise TaskFailed(f"{stage_name}: {exc}") from None


def _run_one(store_path: str, stage_name: str, index: tuple[int, ...], run_token: str) -> dict:
    index = tuple(int(i) for i in index)
    try:
        return _run_task(store_path, stage_name, index, run_token)
    except TaskFailed:
        raise
    except Exception as exc:  # the store unreadable, the disk full while marking...: one line
        raise TaskFailed(_failure_text(f"{stage_name} {list(index)}", exc)) from exc


def _failure_text(where: str, exc: BaseException) -> str:
    """``where: Type: message`` on one line; a full disk says so and that nothing is lost."""
    import errno

    msg = f"{where}: {type(exc).__name__}: {exc}"
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        msg += " (the disk is full: free space and rerun; completed chunks are kept)"
    return " ".join(msg.split())


def _run_task(store_path: str, stage_name: str, index: tuple[int, ...], run_token: str) -> dict:
    t0 = time.perf_counter()
    c0 = time.thread_time()
    ctx = context(str(store_path), str(run_token))
    receipt = {"stage": stage_name, "index": list(index), "skipped": False}
    worker = _worker_address()
    if worker:
        receipt["worker"] = worker
    st = stage(stage_name)
    labels = dict(zip(st.over, index))
    if "camera" in labels:
        receipt["camera"] = ctx.cameras[labels["camera"]].name
    if "frame" in labels:
        receipt["frame"] = ctx.first_frame + labels["frame"]
    if "raw_frame" in labels:
        receipt["frame"] = ctx.raw_first + labels["raw_frame"]
    if ctx.store.is_done(stage_name, index):
        receipt["skipped"] = True
        receipt["seconds"] = time.perf_counter() - t0
        receipt["cpu_seconds"] = time.thread_time() - c0
        return receipt
    try:
        extra = _GLUE[stage_name](ctx, *index)
    except TaskFailed:
        raise
    except Exception as exc:  # name the camera/frame; the original type stays in the text
        raise TaskFailed(_failure_text(_describe(stage_name, index, ctx), exc)) from exc
    try:
        ctx.store.mark_done(stage_name, index)
    except Exception as exc:  # noqa: BLE001 - e.g. the disk filled up right now
        raise TaskFailed(_failure_text(_describe(stage_name, index, ctx), exc)) from exc
    receipt.update(extra)
    receipt["seconds"] = time.perf_counter() - t0
    # CPU of this thread only: below ``seconds`` when other processes took the core
    receipt["cpu_seconds"] = time.thread_time() - c0
    log_receipt(receipt)
    return receipt


def _prefetch_frames(store_path: str, run_token: str, stage_name: str, indices) -> None:
    """The input frames a batch of ``deflection`` indices reads, fetched together
    (one concurrent batch from an object store; nothing happens for folders)."""
    if stage_name != "deflection" or not indices:
        return
    try:
        ctx = context(str(store_path), str(run_token))
        by_camera: dict[int, list[int]] = {}
        for c, k in indices:
            by_camera.setdefault(int(c), []).append(ctx.raw_first + int(k))
        for c, frames in by_camera.items():
            ctx.frames(c).prefetch(frames)
    except Exception:  # noqa: BLE001 - only a hint: each read reports its own problem, naming the frame
        log.debug("prefetching the frames of %s %s failed", stage_name, indices, exc_info=True)


def run_tasks(store_path: str, stage_name: str, indices, *_deps, run_token: str = "",
              flush: bool = True) -> list[dict]:
    """Run one stage at each of ``indices`` in order (a batched task) and return the receipts.

    Every index is attempted even after one fails, so everything computable is written
    and marked; then the first failure is raised (its message names the camera and
    frame, with how many more failed in this task). ``flush=False`` returns without
    waiting for background writes (the serial loop, which reads them back in this
    process, calls :func:`flush_writes` at its end).
    """
    receipts: list[dict] = []
    failed: list[str] = []
    _prefetch_frames(store_path, run_token, stage_name, indices)
    for index in indices:
        try:
            receipts.append(_run_one(store_path, stage_name, index, run_token))
        except TaskFailed as exc:
            failed.append(str(exc))
    if flush:
        try:
            flush_writes(store_path, run_token, stage_name)
        except TaskFailed as exc:
            failed.append(str(exc))
    if failed:
        more = f" (and {len(failed) - 1} more frame(s) of this task)" if len(failed) > 1 else ""
        raise TaskFailed(failed[0] + more)
    return receipts
