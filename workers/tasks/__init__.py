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

Modules: :mod:`.run_context` (the run's per-process context, :class:`TaskFailed`),
:mod:`.runner` (running a task: marker, receipt, failure text), and one module per
stage's task: :mod:`.sync` (``sync``, ``clock``), :mod:`.deflection`, :mod:`.resample`,
:mod:`.masks` (``potential``, ``threshold``, ``mask``), :mod:`.geometry`, :mod:`.hull`,
:mod:`.regularisation`, :mod:`.tomography`, :mod:`.integrate` (refractivity and the
derived density and temperature) and the optional :mod:`.uncertainty` (their standard errors).
"""

from schlieren.workers.tasks.deflection import flow_params, frame_flags, raw_frame_needed
from schlieren.workers.tasks.hull import HULL_PROJECTION_BYTES
from schlieren.workers.tasks.regularisation import choose_flow_window
from schlieren.workers.tasks.resample import bad_frames
from schlieren.workers.tasks.run_context import RunContext, TaskFailed, adopt_session, context
from schlieren.workers.tasks.runner import STAGE_TASKS, flush_writes, run_task, run_tasks
from schlieren.workers.tasks.tomography import flow_blur, tomo_params

__all__ = ["run_task", "run_tasks", "flush_writes", "TaskFailed", "RunContext", "context", "adopt_session",
           "STAGE_TASKS", "flow_params", "frame_flags", "raw_frame_needed", "bad_frames", "choose_flow_window",
           "flow_blur", "tomo_params", "HULL_PROJECTION_BYTES"]
