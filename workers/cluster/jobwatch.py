"""The batch jobs of a SLURM / PBS cluster: replacing the ones that end, failing when none can run.

distributed's ``SpecCluster`` (which dask-jobqueue's clusters are) forgets a job only when
a departing worker's name equals the job's name. A job that runs several worker
processes names them ``<job>-0``, ``<job>-1``..., so a job that dies (``scancel``, a node
failure) or whose workers retire at their ``--lifetime`` stays in ``cluster.workers``
forever: ``adapt`` sees its plan met and never submits a replacement, and the run waits
with no worker (dask-jobqueue issue 611). A job killed before any worker joined sends no
event at all.

:class:`WatchedJobs`, mixed in before dask-jobqueue's cluster class, fixes both:

* when the last worker of a job leaves, the job is dropped once the batch system no
  longer runs it (or after ``distributed.deploy.lost-worker-timeout``, if its workers did
  not come back), and a replacement job is submitted under a new name;
* a watch polls the batch system (``squeue`` / ``qstat``) for the jobs the cluster holds
  and drops the ones that ended, with or without workers ever joining;
* closing the cluster first asks every worker to close and lets the jobs end by
  themselves, before the scheduler stops and ``scancel`` runs (the job logs stay free of
  the tracebacks of workers whose scheduler vanished under them);
* the run fails with one line (:class:`ClusterStalled`) instead of waiting forever when
  no worker and no job pending or running has been seen for ``stall-timeout`` seconds,
  when :data:`CRASH_LOOP_JOBS` jobs in a row ended before any of their workers joined,
  when every job has been pending for ``stall-timeout`` seconds for a reason the batch
  system does not clear by itself (SLURM's ``PartitionConfig``, ``BadConstraints``...: a
  job asking for more cores, memory or time than the partition has), or when the workers
  have been gone for ``wait-timeout`` seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import dask
from dask.utils import parse_timedelta
from distributed.core import Status

log = logging.getLogger(__name__)

#: Seconds between two looks at the batch system's job list.
JOB_POLL_SECONDS = 10.0
#: Jobs in a row that end before any of their workers joined: the run fails (a broken
#: job script, a python that does not start, a node that cannot reach the scheduler).
CRASH_LOOP_JOBS = 3

# job states in which a job will still run workers; any other state (or none: the batch
# system forgot the job) means it ended
_ALIVE = {
    "slurm": frozenset({"PENDING", "CONFIGURING", "RUNNING", "SUSPENDED", "REQUEUED", "REQUEUE_FED",
                        "REQUEUE_HOLD", "RESIZING"}),
    "pbs": frozenset({"Q", "R", "H", "W", "T", "S", "U", "B"}),
}
_PENDING = {"slurm": frozenset({"PENDING", "CONFIGURING", "REQUEUED", "REQUEUE_FED", "REQUEUE_HOLD"}),
            "pbs": frozenset({"Q", "H", "W", "T"})}
#: SLURM's reasons for a pending job that no other job's end clears: the job asks for more
#: than the partition or its account allows (``squeue %r``; ``man squeue``, JOB REASON CODES).
NEVER_CLEARS = frozenset({
    "PartitionConfig", "PartitionNodeLimit", "PartitionTimeLimit", "BadConstraints", "InvalidAccount",
    "InvalidQOS", "QOSMaxCpuPerJobLimit", "QOSMaxNodePerJobLimit", "QOSMaxWallDurationPerJobLimit",
    "QOSMaxMemoryPerJob", "AssocMaxCpuPerJobLimit", "AssocMaxNodesPerJobLimit",
    "AssocMaxWallDurationPerJobLimit", "DependencyNeverSatisfied"})


class ClusterStalled(RuntimeError):
    """The batch cluster cannot run the session's tasks (one line saying why)."""


@dataclass(frozen=True)
class WatchSettings:
    """What the job watch of a batch cluster waits for, in seconds.

    ``stall_timeout``: no worker and no job pending or running; ``wait_timeout`` (None:
    forever): no worker after the workers had joined (the first wait is the client's);
    ``poll``: between two looks at the batch system; ``log_directory``: where the job logs
    are, named in the messages.
    """

    kind: str = "slurm"
    stall_timeout: float = 120.0
    wait_timeout: float | None = None
    poll: float = JOB_POLL_SECONDS
    log_directory: str | None = None


def parse_squeue(text: str) -> dict[str, str]:
    """``squeue -h -o "%i %T"`` (or ``"%i %T %r"``) output as ``{job id: state}``."""
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 2:
            out[parts[0]] = parts[1].upper()
    return out


def parse_squeue_reasons(text: str) -> dict[str, str]:
    """``squeue -h -o "%i %T %r"`` output as ``{job id: reason}`` (``None`` for a running job)."""
    out = {}
    for line in text.splitlines():
        parts = line.split(None, 2)
        if len(parts) == 3:
            out[parts[0]] = parts[2].strip()
    return out


def parse_qstat(text: str) -> dict[str, str]:
    """``qstat`` output (PBS Pro or Torque: ``Job id  Name  User  Time Use  S  Queue``) as
    ``{numeric job id: state letter}``."""
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 6 and parts[0][:1].isdigit():
            out[parts[0].split(".")[0]] = parts[4].upper()
    return out


def _job_key(kind: str, job_id: str) -> str:
    return str(job_id).split(".")[0] if kind == "pbs" else str(job_id)


def is_alive(kind: str, state: str | None) -> bool:
    """Whether a job in ``state`` (None: unknown to the batch system) will still run workers."""
    return state is not None and state in _ALIVE.get(kind, frozenset())


async def batch_states(kind: str, timeout: float = 30.0) -> dict[str, str] | None:
    """``{job id: state}`` of this user's jobs, as the batch system lists them; None when it
    cannot be asked (a command missing or failing: nothing is concluded from that)."""
    listing = await batch_listing(kind, timeout)
    return None if listing is None else (parse_squeue if kind == "slurm" else parse_qstat)(listing)


async def batch_listing(kind: str, timeout: float = 30.0) -> str | None:
    """The batch system's job list of this user (``squeue -o "%i %T %r"`` / ``qstat``), or None
    when it cannot be asked."""
    user = getpass.getuser()
    cmd = (["squeue", "-h", "-o", "%i %T %r", "-t", "all", "-u", user] if kind == "slurm" else ["qstat"])
    try:
        proc = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.PIPE,
                                                    stderr=asyncio.subprocess.PIPE)
    except OSError:
        return None
    try:
        out, _err = await asyncio.wait_for(proc.communicate(), timeout)
    except asyncio.TimeoutError:  # a controller that does not answer: ask again next poll
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        await proc.wait()
        return None
    if proc.returncode != 0:
        return None
    return out.decode(errors="replace")


def submit_error_line(exc: BaseException) -> str:
    """The batch system's own words from dask-jobqueue's failed-submission error (its
    ``stderr:`` part), else the error's first line."""
    text = str(exc)
    if "stderr:" in text:
        lines = [ln.strip() for ln in text.split("stderr:", 1)[1].splitlines() if ln.strip()]
        if lines:
            return lines[0]
    return next((ln.strip() for ln in text.splitlines() if ln.strip()), type(exc).__name__)


def recording_job_class(base: type) -> type:
    """``base`` (a dask-jobqueue ``Job`` class) that keeps a failed submission's error
    (for the watch) instead of raising it into the cluster's event loop, and that ends in
    ``Status.closed`` when closed (``SpecCluster`` checks it when the cluster closes)."""

    class RecordingJob(base):  # type: ignore[misc, valid-type]
        submit_error: str | None = None

        async def start(self):
            try:
                await super().start()
            except Exception as exc:  # sbatch / qsub refused it: the watch drops and replaces it
                self.submit_error = submit_error_line(exc)
                self.status = Status.running

        async def close(self):
            await super().close()
            self.status = Status.closed
            self._event_finished.set()

    RecordingJob.__name__ = RecordingJob.__qualname__ = f"Recording{base.__name__}"
    return RecordingJob


class WatchedJobs:
    """Mixin for a dask-jobqueue cluster class (listed before it): replaces jobs that end,
    fails the run with one line when none can run (see the module docstring).

    ``stalled`` holds that line once it is known; ``on_stall(line)`` is called once then
    (from the cluster's event loop thread).
    """

    def __init__(self, *args: Any, watch: WatchSettings | None = None, **kwargs: Any) -> None:
        self.watch_settings = watch or WatchSettings()
        now = time.monotonic()
        self._last_worker = self._last_job = now
        self._ever_worker = False
        self._joined: set[str] = set()  # jobs a worker of which joined the scheduler
        self._silent_ends = 0  # jobs in a row that ended before any worker joined
        self._submit_error: str | None = None
        self._held_since: float | None = None  # every job pending for a reason that never clears
        self._held_reason = ""
        self._jobs_closing = False
        self._watch_task: asyncio.Task | None = None
        self._kick: asyncio.Event | None = None
        self._new_names = 0
        self.stalled: str | None = None
        self.on_stall: Callable[[str], None] | None = None
        self.replaced = 0  # jobs dropped and replaced (tests and the log read it)
        super().__init__(*args, **kwargs)

    # -- which job a worker belongs to ---------------------------------------------------

    def job_of(self, worker_name: Any) -> str | None:
        """The job (its name in ``cluster.workers``) whose worker is named ``worker_name``."""
        name = str(worker_name)
        for job in set(self.workers) | set(self.worker_spec):
            spec = self.worker_spec.get(job) or {}
            suffixes = spec.get("group") or ([""] if spec else None)
            if suffixes is not None:
                if name in {f"{job}{s}" for s in suffixes}:
                    return job
            elif name == str(job) or (name.startswith(f"{job}-") and name[len(str(job)) + 1:].isdigit()):
                return job
        return None

    def new_worker_spec(self) -> dict:
        # a replacement never reuses a name: a dead job's workers may still be listed by the
        # scheduler (a failed node's, until worker-ttl), and names must be unique there
        while True:
            name = self._new_worker_name(self._new_names)
            self._new_names += 1
            if name not in self.worker_spec and name not in self.workers:
                return {name: self.new_spec}

    # -- events ---------------------------------------------------------------------------

    def _update_worker_status(self, op: str, msg: Any) -> None:
        if op == "remove":
            info = self.scheduler_info.get("workers", {}).get(msg) or {}
            job = self.job_of(info.get("name"))
            if job is not None:
                self._joined.add(job)
                loop = asyncio.get_running_loop()
                loop.call_later(1.0, self._look_now)  # the batch system may already say it ended
                delay = parse_timedelta(dask.config.get("distributed.deploy.lost-worker-timeout"))
                loop.call_later(delay, self._workers_gone, job, self.workers.get(job))
        elif op == "add":
            self._saw_workers([w.get("name") for w in (msg.get("workers") or {}).values()])
        super()._update_worker_status(op, msg)

    def _saw_workers(self, names: list) -> None:
        jobs = {self.job_of(n) for n in names} - {None}
        if names:
            self._last_worker = time.monotonic()
            self._ever_worker = True
            self._silent_ends = 0
        self._joined |= jobs  # type: ignore[arg-type]

    def _worker_names(self) -> list:
        return [w.get("name") for w in self.scheduler_info.get("workers", {}).values()]

    def _workers_gone(self, job: str, proc: Any) -> None:
        """``lost-worker-timeout`` after a worker of ``job`` left: drop the job if none of its
        workers came back (a nanny restarts a crashed worker under the same name)."""
        if proc is None or self.workers.get(job) is not proc:
            return
        if any(self.job_of(n) == job for n in self._worker_names()):
            return
        self._drop_job(job, proc, "lost its workers")

    def _look_now(self) -> None:
        if self._kick is not None:
            self._kick.set()

    # -- the watch --------------------------------------------------------------------------

    async def _start(self) -> None:
        await super()._start()
        self._kick = asyncio.Event()
        self._watch_task = asyncio.ensure_future(self._watch_jobs())

    async def _watch_jobs(self) -> None:
        while self.status == Status.running and not self._jobs_closing:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._kick.wait(), self.watch_settings.poll)  # type: ignore[union-attr]
            self._kick.clear()  # type: ignore[union-attr]
            if self.status != Status.running or self._jobs_closing:
                return
            try:
                await self._check_jobs()
            except Exception:  # the watch must outlive a surprise; say it once per surprise
                log.warning("checking the batch jobs failed", exc_info=True)

    async def _check_jobs(self) -> None:
        kind = self.watch_settings.kind
        names = self._worker_names()
        self._saw_workers(names)
        present = {self.job_of(n) for n in names}
        listing = await batch_listing(kind)
        states = None if listing is None else (parse_squeue if kind == "slurm" else parse_qstat)(listing)
        reasons = parse_squeue_reasons(listing) if listing is not None and kind == "slurm" else {}
        alive = 0
        held: set[str] = set()  # reasons of the alive jobs that pend for good
        free = 0  # alive jobs that run, or pend for a reason that clears
        for job, proc in list(self.workers.items()):
            if self.workers.get(job) is not proc:
                continue
            error = getattr(proc, "submit_error", None)
            if error:
                if error != self._submit_error:
                    log.warning("submitting a worker job failed: %s", error)
                self._submit_error = error
                self._drop_job(job, proc, "could not be submitted")
                continue
            if getattr(proc, "job_id", None) is None or states is None:
                alive += 1  # being submitted, or the batch system cannot be asked now
                continue
            state = states.get(_job_key(kind, proc.job_id))
            if is_alive(kind, state):
                alive += 1
                reason = reasons.get(_job_key(kind, proc.job_id), "")
                if state in _PENDING.get(kind, ()) and reason in NEVER_CLEARS:
                    held.add(reason)
                else:
                    free += 1
            elif job not in present:  # ended; a job whose workers are still listed waits for them
                self._drop_job(job, proc, f"ended ({state or 'no longer listed by the batch system'})")
        now = time.monotonic()
        if held and not free:
            if self._held_since is None:
                self._held_since = now
            self._held_reason = ", ".join(sorted(held))
        else:
            self._held_since = None
        if alive or not self.worker_spec:  # jobs run or wait, or none is wanted
            self._last_job = now
        if not self.worker_spec:
            self._last_worker = now
        if not names:
            self._judge(now, states, alive)

    def _judge(self, now: float, states: dict | None, alive: int) -> None:
        """No worker is connected: decide whether the run can still go on."""
        w = self.watch_settings
        logs = f"see their logs in {w.log_directory}" if w.log_directory else "see their logs"
        if self._silent_ends >= CRASH_LOOP_JOBS:
            self._stall(f"{self._silent_ends} worker jobs in a row ended before any of their workers joined "
                        f"the scheduler: {logs}")
        elif self._held_since is not None and now - self._held_since > w.stall_timeout:
            self._stall(f"every worker job has been pending for {w.stall_timeout:g} s (schlieren.stall-timeout) "
                        f"for a reason the batch system does not clear by itself: {self._held_reason} (the job "
                        f"asks for more cores, memory or time than the partition allows: compare the cluster's "
                        f"cores, memory and walltime with `scontrol show partition`)")
        elif states is not None and not alive and now - max(self._last_worker, self._last_job) > w.stall_timeout:
            why = (f"the last submission failed: {self._submit_error}" if self._submit_error
                   else f"the worker jobs ended ({logs})")
            self._stall(f"no worker and no worker job pending or running for {w.stall_timeout:g} s "
                        f"(schlieren.stall-timeout): {why}")
        elif w.wait_timeout and self._ever_worker and now - self._last_worker > w.wait_timeout:
            self._stall(f"no worker for {w.wait_timeout:g} s (schlieren.wait-timeout) after the workers left: "
                        f"{self.jobs_summary(states)}")

    def jobs_summary(self, states: Mapping[str, str] | None = None) -> str:
        """The jobs the cluster holds, in words (``"1 worker job pending in the batch queue"``)."""
        kind = self.watch_settings.kind
        if states is None:
            return f"{len(self.workers)} worker job(s) submitted"
        pending = running = 0
        for proc in self.workers.values():
            state = states.get(_job_key(kind, getattr(proc, "job_id", None) or ""))
            pending += state in _PENDING.get(kind, ())
            running += is_alive(kind, state) and state not in _PENDING.get(kind, ())
        if not pending and not running:
            return "no worker job pending or running"
        parts = [f"{n} worker job(s) {what}" for n, what in ((pending, "pending in the batch queue"),
                                                              (running, "running")) if n]
        return ", ".join(parts)

    async def jobs_summary_now(self) -> str:
        return self.jobs_summary(await batch_states(self.watch_settings.kind))

    def _stall(self, reason: str) -> None:
        if self.stalled is not None:
            return
        self.stalled = reason
        callback = self.on_stall
        if callback is not None:
            callback(reason)

    def _drop_job(self, job: str, proc: Any, why: str) -> None:
        """Forget ``job`` (cancelling it: harmless when it already ended) and submit a
        replacement under a new name, unless the cluster is closing or no longer wants it."""
        if self.workers.get(job) is not proc:
            return
        del self.workers[job]
        self._futures.add(asyncio.ensure_future(proc.close()))
        if getattr(proc, "job_id", None) and job not in self._joined:
            self._silent_ends += 1
        spec = self.worker_spec.pop(job, None)
        replace = spec is not None and not self._jobs_closing and self.status == Status.running
        log.info("worker job %s (batch id %s) %s%s", job, getattr(proc, "job_id", None), why,
                 "; submitting a replacement" if replace else "")
        if replace:
            self.replaced += 1
            self.worker_spec.update(self.new_worker_spec())
            self._correct_state()

    # -- closing ------------------------------------------------------------------------------

    async def _close(self) -> None:
        if self.status == Status.running and not self._jobs_closing:
            self._jobs_closing = True
            self._look_now()
            with contextlib.suppress(Exception):
                await self._close_workers_first()
        await super()._close()

    async def _close_workers_first(self, timeout: float = 30.0) -> None:
        """Ask every worker to close and give the jobs a moment to end by themselves, so that
        the scheduler's shutdown and ``scancel`` find nothing to interrupt."""
        adaptive = getattr(self, "_adaptive", None)
        if adaptive is not None:
            adaptive.stop(reason="cluster-closing")
        scheduler = getattr(self, "scheduler", None)
        workers = getattr(scheduler, "workers", None)
        if not workers:
            return
        for address in list(workers):
            scheduler.close_worker(address)
        deadline = time.monotonic() + timeout
        while scheduler.workers and time.monotonic() < deadline:
            await asyncio.sleep(0.2)
        kind = self.watch_settings.kind
        joined = [p for j, p in self.workers.items() if j in self._joined and getattr(p, "job_id", None)]
        deadline = time.monotonic() + 10.0
        while joined and time.monotonic() < deadline:
            states = await batch_states(kind)
            if states is None or not any(is_alive(kind, states.get(_job_key(kind, p.job_id))) for p in joined):
                return
            await asyncio.sleep(1.0)


@contextlib.contextmanager
def stop_on_stall(cluster: Any) -> Iterator[None]:
    """Within this block, a stall of ``cluster`` (:class:`WatchedJobs`) stops the main
    thread wherever it waits (for workers, in the run's loop) and is raised as
    :class:`ClusterStalled` with its one line. A cluster without a watch: nothing happens.

    The cluster's event loop thread signals the main thread (``SIGUSR1``, its handler
    installed here and restored on exit), which interrupts a sleep or a wait at once.
    """
    if not isinstance(cluster, WatchedJobs) or threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        if cluster.stalled is not None:
            raise _Stalled()

    previous = signal.signal(signal.SIGUSR1, _raise)
    main = threading.main_thread().ident
    cluster.on_stall = lambda reason: signal.pthread_kill(main, signal.SIGUSR1)  # type: ignore[arg-type]
    try:
        if cluster.stalled is not None:
            raise _Stalled()
        yield
    except _Stalled:
        raise ClusterStalled(cluster.stalled) from None
    finally:
        cluster.on_stall = None
        signal.signal(signal.SIGUSR1, previous)


class _Stalled(BaseException):
    """Raised in the main thread by :func:`stop_on_stall`'s signal handler (a BaseException,
    so that no ``except Exception`` on the way swallows it)."""
