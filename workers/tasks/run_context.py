"""What every stage's task shares: the run's context in this process, and the task error.

:func:`context` opens a run once per worker process (cached by the store path and the
run's token, so a store deleted and made again for another run at the same path gets
fresh caches): the store, the session, the run's parameters and the flow grid. The
:class:`RunContext` then keeps what the tasks of one process read again and again: the
frame readers, the reference images, the small per-camera arrays and the recently read
upstream chunks (values an upstream task has finished writing never change during a
run; a mask task reads three frames of each; each zarr read costs about a millisecond,
more in a busy worker).
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from schlieren.pipeline import flow as flowmod
from schlieren.pipeline import tomography
from schlieren.pipeline.flow.focus import AUTO
from schlieren.pipeline.geometry import Camera, FlowGrid
from schlieren.pipeline.stages import RunConfig, config_from_dict
from schlieren.storage.frames import open_frames, read_reference
from schlieren.storage.session import Session, load_session
from schlieren.storage.store import ResultStore

__all__ = ["TaskFailed", "RunContext", "context", "adopt_session", "solver_receipt"]


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
        return self.once("ray_binning", lambda: tomography.ray_binning(
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

    def once(self, key, make):
        """``make()`` the first time ``key`` is asked for in this process, then the same value
        (for values fixed for the whole run: references, per-camera arrays, parameters)."""
        if key not in self._small:
            self._small[key] = make()
        return self._small[key]

    def reference(self, c: int, parity: int | None = None) -> np.ndarray:
        """Camera ``c``'s reference (for interlaced cameras: that of the fields of ``parity``)."""
        s = self.session.sources[c]
        return self.once(("reference", c, parity), lambda: self._stored_reference(c, parity) if (
            parity is None and self.config.capture.reference_topup > 0) else
            read_reference(s, camera_name=s.name, parity=parity))

    def _stored_reference(self, c: int, parity: None) -> np.ndarray:
        """Camera ``c``'s reference topped up by its capture task (stored ``reference``), or
        the reference's frames' average when it was not topped up."""
        if int(self.store.read("reference_topup", (c,))) > 0:
            return np.asarray(self.store.read("reference", (c,)))
        s = self.session.sources[c]
        return read_reference(s, camera_name=s.name, parity=parity)

    def reference_topped_up(self, c: int, reference: np.ndarray) -> None:
        """Camera ``c``'s reference is ``reference`` from now on (its capture task topped it up
        and stored it): what this process prepared from the recorded one is dropped."""
        self._small[("reference", c, None)] = reference
        for key in (("prepared_reference", c, None), ("camera_capture", c, None), ("reference_mean", c, None)):
            self._small.pop(key, None)

    def reference_averaged(self, c: int, make) -> np.ndarray:
        """Camera ``c``'s reference (not interlaced) from ``make()``, a task's own average of its
        frames as :func:`read_reference` averages them, unless this process has it already."""
        return self.once(("reference", c, None), make)

    def presmooth(self, c: int) -> float:
        """Camera ``c``'s flow pre-smoothing (pixels): ``flow.presmooth``, or with ``auto`` the
        capture stage's choice from the camera's reference (stored ``presmooth``)."""
        p = self.config.flow.presmooth
        if p != AUTO:
            return float(p)
        return self.once(("presmooth", c), lambda: float(self.store.read("presmooth", (c,))))

    def prepared_reference(self, c: int, parity: int | None = None):
        """The reference's pyramid and spline coefficients, prepared once per camera (and field
        parity) per process."""
        return self.once(("prepared_reference", c, parity),
                          lambda: flowmod.prepare_reference(self.reference(c, parity), presmooth=self.presmooth(c),
                                                            levels=self.config.flow.levels))

    def time_offset(self, c: int) -> float:
        return self.once(("time_offset", c), lambda: float(self.store.read("time_offset", (c,))))

    def camera_with_offset(self, c: int) -> Camera:
        return self.cameras[c].with_time_offset(self.time_offset(c))

    def flash_frames(self, c: int) -> tuple[int, ...]:
        def read():
            lo, hi = (int(v) for v in self.store.read("flash_frames", (c,)))
            return tuple(range(lo, hi + 1)) if lo >= 0 else ()
        return self.once(("flash_frames", c), read)

    def times(self) -> np.ndarray:
        """The output frames' instants (written once by the clock stage)."""
        return self.once("time", lambda: np.asarray(self.store.read("time", ()), dtype=np.float64))

    def mask_threshold(self) -> float:
        return self.once("mask_threshold", lambda: float(self.store.read("mask_threshold", ())[0]))

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


def solver_receipt(info) -> dict:
    """The receipt fields of a solver's result (iterations, residuals, ...), JSON-able."""
    out = {}
    for name in ("iterations", "residual", "relative_residual", "converged", "unknowns", "rays", "restriction",
                 "sign", "clipped"):
        if hasattr(info, name):
            v = getattr(info, name)
            out[name] = v.tolist() if isinstance(v, np.ndarray) else v
    return out

