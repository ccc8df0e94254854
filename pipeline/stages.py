"""The declared stages of a reconstruction run, and the run configuration.

Each :class:`Stage` names its pure kernel (in ``pipeline/``), the :class:`RunConfig` field
holding its frozen params dataclass, the store arrays it reads and writes, the dims it
maps over (one task per index of those dims) and the stages it waits for. The executors
in ``workers/`` (a plain loop in ``workers/serial.py``, a Dask graph in
``workers/graph.py``) compile this same table; ``workers/tasks/`` holds the per-stage
glue that reads the inputs of one index, calls the kernel and writes whole chunks.

Dependencies are declared per index:

* ``same``: the task at the same index of that stage (matching the dims they share),
* ``all``: every task of that stage,
* ``window``: the tasks of that stage within ``frame_halo`` frames, same camera,
* ``neighbours``: the tasks of that stage within the run's space-time window
  (:func:`~schlieren.pipeline.spacetime.window_frames`: up to ``spacetime.window`` frames
  either side).

The ``spacetime`` stage (:data:`SPACETIME_STAGE`) is in a run only when
``spacetime.window > 0`` (:func:`run_stages`); a dependency on a stage that is not in the
run is dropped.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable

from schlieren.pipeline import capture as _capture
from schlieren.pipeline import flow as _flow
from schlieren.pipeline import hull as _hull
from schlieren.pipeline import masks as _masks
from schlieren.pipeline import poisson as _poisson
from schlieren.pipeline import spacetime as _spacetime
from schlieren.pipeline import sync as _sync
from schlieren.pipeline import tomography as _tomo
from schlieren.pipeline import uncertainty as _unc
from schlieren.pipeline.params import ParamsError, param, parameters
from schlieren.pipeline.params import validate as _validate

__all__ = ["Stage", "RunConfig", "STAGES", "SPACETIME_STAGE", "OPTIONAL_STAGES", "run_stages", "stages_with",
           "stage", "middle_frame", "config_from_dict", "config_to_dict", "check_config", "bind_medium",
           "bind_flow_factor"]


@parameters
class RunConfig:
    """Every parameter of a run, one frozen params class per stage (saved in the store)."""

    flow: _flow.FlowParams = field(default_factory=_flow.FlowParams)
    flash: _sync.FlashParams = field(default_factory=_sync.FlashParams)
    resample: _sync.ResampleParams = field(default_factory=_sync.ResampleParams)
    masks: _masks.MaskParams = field(default_factory=_masks.MaskParams)
    hull: _hull.HullParams = field(default_factory=_hull.HullParams)
    tomography: _tomo.TomoParams = field(default_factory=_tomo.TomoParams)
    poisson: _poisson.PoissonParams = field(default_factory=_poisson.PoissonParams)
    reconstruction: str = param(
        "two-step", choices=("two-step", "direct"),
        help="`two-step`: the paper's gradient tomography (`tomography`) followed by the anisotropic Poisson "
             "integration (`poisson`); `direct`: refractivity solved directly from the deflections "
             "(`direct`, beyond the paper).")
    warm_start_block: int = param(
        4, unit="frames", ge=1, le=10000,
        help="Frames solved in sequence, each tomography solve warm-started from the previous frame's; "
             "blocks are independent, so more blocks give more parallel work.")
    direct: _tomo.RefractivityParams = field(default_factory=_tomo.RefractivityParams)
    spacetime: _spacetime.SpaceTimeParams = field(default_factory=_spacetime.SpaceTimeParams)
    uncertainty: _unc.UncertaintyParams = field(default_factory=_unc.UncertaintyParams)
    capture: _capture.CaptureParams = field(default_factory=_capture.CaptureParams)
    refine: _flow.RefineParams = field(default_factory=_flow.RefineParams)

    @property
    def flow_factor(self) -> int:
        """Downsampling factor from image pixels to the flow grid."""
        return self.flow.factor


def bind_flow_factor(cfg: RunConfig, cameras, grid) -> RunConfig:
    """The configuration with the flow grid's factor a run on ``cameras`` and ``grid`` takes:
    with ``flow.auto_factor``, :func:`~schlieren.pipeline.tomography.binning.auto_flow_factor`
    up to ``flow.factor``; otherwise ``cfg`` unchanged. Binding twice gives the same factor."""
    if not cfg.flow.auto_factor:
        return cfg
    from schlieren.pipeline.tomography.binning import auto_flow_factor

    f = auto_flow_factor(cameras, grid, cfg.flow.factor)
    return cfg if f == cfg.flow.factor else dataclasses.replace(cfg, flow=dataclasses.replace(cfg.flow, factor=f))


def bind_medium(cfg: RunConfig, n_ambient: float) -> RunConfig:
    """The configuration with every ``n_ambient`` parameter set to the session's medium."""
    out = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value) and any(g.name == "n_ambient" for g in dataclasses.fields(value)):
            out[f.name] = dataclasses.replace(value, n_ambient=float(n_ambient))
    return dataclasses.replace(cfg, **out)


@dataclass(frozen=True)
class Stage:
    """One declared stage.

    Attributes
    ----------
    name : str
    kernel : callable
        The pure kernel this stage wraps.
    params : str or None
        Name of the :class:`RunConfig` field holding the kernel's parameters.
    inputs, outputs : tuple of str
        Store arrays read and written (``images`` = the session's frames).
    over : tuple of str
        Dims mapped over: ``("camera", "frame")``, ``("frame",)``, ``("camera",)`` or ``()``.
    after : tuple of (str, str)
        ``(stage, how)`` dependencies, ``how`` in ``{"same", "all", "window", "neighbours", "chain",
        "block", "middle", "margin"}`` (``block``: every frame of the task's warm-start block;
        ``middle``: the dependency's indices at the middle frame, :func:`middle_frame`;
        ``margin``: all of the dependency's indices, for tasks at raw frames outside the
        output range only).
    frame_halo : int
        Frames either side read by ``window`` dependencies.
    resources : dict
        Worker resources each task needs (e.g. ``{"TOMO": 1}`` for memory-heavy solves).
    batch : bool
        A cheap per-camera-frame stage: a task may compute several consecutive frames
        of one camera (``frames_per_task`` of :func:`~schlieren.workers.plan.make_plan`).
    grid : {"image", "flow"}
        What a batched stage's work scales with: the camera images or the (downsampled)
        flow grid (:func:`~schlieren.workers.run.default_frames_per_task`).
    enabled_by : str or None
        An optional stage (:data:`OPTIONAL_STAGES`): the :class:`RunConfig` switch that adds
        it to a run when true (``"uncertainty.enabled"``; ``"spacetime.window"``: when > 0);
        None for the stages every run has.
    cost : float
        Rough seconds per task, used only to order the work (``workers/plan.py``,
        :func:`~schlieren.workers.plan.critical_path_priorities`): the serial in-task
        times of benchmarks/scaling.py's session (8 cameras x 16 frames, 480x360 images,
        a 60x60x120 grid). Only their ratios along a path matter.
    """

    name: str
    kernel: Callable
    params: str | None
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    over: tuple[str, ...]
    after: tuple[tuple[str, str], ...] = ()
    frame_halo: int = 0
    resources: dict = field(default_factory=dict)
    batch: bool = False
    cost: float = 0.01
    grid: str = "image"
    enabled_by: str | None = None

    def enabled(self, cfg: RunConfig) -> bool:
        """Whether a run of ``cfg`` has this stage."""
        if self.enabled_by is None:
            return True
        group, name = self.enabled_by.split(".")
        return bool(getattr(getattr(cfg, group), name))


def middle_frame(n_frames: int) -> int:
    """The output frame the ``regularisation`` stage chooses the weight on (and a ``middle``
    dependency points at)."""
    return int(n_frames) // 2


STAGES: tuple[Stage, ...] = (
    Stage("sync", _sync.offset_from_flash, None, ("images",), ("time_offset", "flash_frames"), ("camera",),
          cost=0.011),
    Stage("clock", _sync.output_times, None, ("time_offset",), ("time",), (),
          after=(("sync", "all"),), cost=0.001),
    # a raw frame of the rolling-shutter margins is processed only if an output instant
    # needs it, which the clock decides (docs/tuning.md, "Frame quality")
    # defective pixels from the reference frames and a sample of the capture frames (issue 33),
    # and the flow's pre-smoothing from the reference's sharpness (pipeline/flow/focus.py)
    Stage("capture", _capture.find_defective_pixels, "capture", ("images",),
          ("defective_pixels", "presmooth", "reference_topup", "reference", "reference_count"),
          ("camera",), cost=0.05),
    # the flow of each raw frame with the camera's motion, the lighting's change and the
    # defective pixels removed (pipeline/capture/correction.py; params "flow" and "capture")
    Stage("deflection", _capture.corrected_deflection, "flow", ("images", "defective_pixels"),
          ("flow_raw", "frame_quality", "background_motion", "photometric", "capture_fit"),
          ("camera", "raw_frame"), after=(("clock", "margin"), ("capture", "same")), batch=True, cost=0.014),
    Stage("resample", _sync.resample_flow, "resample", ("flow_raw", "time_offset", "time"),
          ("flow",), ("camera", "frame"), after=(("clock", "all"), ("deflection", "window")),
          frame_halo=2, batch=True, cost=0.02, grid="flow"),
    Stage("potential", _masks.flow_potential, "masks", ("flow",), ("potential", "potential_summary"),
          ("camera", "frame"), after=(("resample", "same"),), batch=True, cost=0.004, grid="flow"),
    Stage("threshold", _masks.threshold_from_summaries, "masks", ("potential_summary",),
          ("mask_threshold",), (), after=(("potential", "all"),), cost=0.02),
    # the potential edges are implied by the threshold's, but without them Dask counts
    # masks as root tasks (one small dependency group) and holds them in its scheduler
    # queue until a worker runs out of hull and solve tasks (docs/tuning.md, "Scheduling")
    Stage("mask", _masks.make_mask, "masks", ("potential", "mask_threshold"), ("mask",),
          ("camera", "frame"), after=(("threshold", "all"), ("potential", "window")), frame_halo=1,
          batch=True, cost=0.003, grid="flow"),
    Stage("geometry", _tomo.build_geometry, "tomography", (), ("geometry",), (), cost=1.35),
    Stage("hull", _hull.visual_hull, "hull", ("mask",), ("hull",), ("frame",),
          after=(("mask", "same"),), cost=0.36),
    # the regularisation weight, from the noise measured outside the masks (discrepancy
    # principle on the middle frame; with reg_choice "fixed" it only records reg_weight).
    # It reads the middle frame's masks only, so the solves need not wait for every mask
    # (docs/tuning.md, "Tomography weight")
    Stage("regularisation", _tomo.choose_reg_weight, "tomography", ("flow", "mask", "geometry"),
          ("reg_weight", "rhs_noise"), (), after=(("mask", "middle"), ("geometry", "all")),
          resources={"TOMO": 1}, cost=2.5),
    Stage("tomography", _tomo.solve_gradient, "tomography", ("flow", "hull", "geometry", "reg_weight"),
          ("gradient",), ("frame",),
          after=(("hull", "block"), ("resample", "same"), ("geometry", "all"), ("regularisation", "all"),
                 ("tomography", "chain")),
          resources={"TOMO": 1}, cost=0.71),
    Stage("integrate", _poisson.integrate, "poisson", ("gradient", "hull"),
          ("refractivity", "density", "temperature"), ("frame",),
          after=(("tomography", "same"), ("spacetime", "same")), resources={"TOMO": 1}, cost=0.23),
)

#: The space-time stage (beyond the paper; in a run when ``spacetime.window > 0``): frame
#: ``k``'s gradient from the per-frame solutions of frames ``k - W .. k + W`` (``gradient_frame``,
#: which the tomography stage then writes instead of ``gradient``) moved onto frame ``k``
#: along their motion and averaged.
SPACETIME_STAGE = Stage("spacetime", _spacetime.motion_compensated_mean, "spacetime",
                        ("gradient_frame", "hull"), ("gradient",), ("frame",),
                        after=(("tomography", "neighbours"), ("hull", "same")), resources={"TOMO": 1}, cost=0.3,
                        enabled_by="spacetime.window")

#: Stages a run has only when its configuration asks for them (``Stage.enabled_by``): a
#: run without them keeps the plan, the markers and the store of :data:`STAGES` alone.
OPTIONAL_STAGES: tuple[Stage, ...] = (
    SPACETIME_STAGE,
    # the standard errors per voxel: the frame's noise through its own solve and integration
    # (a few solves per frame, so a stage of its own: its tasks run beside the next frames'
    # solves, and the per-frame tomography is left as it is)
    Stage("uncertainty", _unc.frame_uncertainty, "uncertainty",
          ("flow", "mask", "hull", "gradient", "refractivity", "geometry", "reg_weight", "flow_window"),
          ("refractivity_sigma", "density_sigma", "temperature_sigma"), ("frame",),
          after=(("integrate", "same"), ("geometry", "all"), ("regularisation", "all")),
          resources={"TOMO": 1}, cost=5.0, enabled_by="uncertainty.enabled"),
)


def stages_with(names) -> tuple[Stage, ...]:
    """:data:`STAGES` and the optional stages named in ``names``, each placed before the
    first stage that waits for it (the space-time stage before the integration), the
    others at the end."""
    out = list(STAGES)
    for s in OPTIONAL_STAGES:
        if s.name in names:
            out.insert(next((i for i, t in enumerate(out) if any(d == s.name for d, _ in t.after)), len(out)), s)
    return tuple(out)


def run_stages(cfg: RunConfig) -> tuple[Stage, ...]:
    """The stages of a run of ``cfg``: :data:`STAGES` and the optional ones it enables."""
    return stages_with({s.name for s in OPTIONAL_STAGES if s.enabled(cfg)})


_BY_NAME = {s.name: s for s in STAGES + OPTIONAL_STAGES}


def stage(name: str) -> Stage:
    """Look a stage up by name."""
    return _BY_NAME[name]


def config_to_dict(cfg: RunConfig) -> dict:
    """Plain nested dict of every parameter (for the store attributes)."""
    return dataclasses.asdict(cfg)


def config_from_dict(d: dict | None) -> RunConfig:
    """Build a :class:`RunConfig` from a nested mapping (a ``--params`` file, the store attrs).

    Every value is checked against the parameter schema (:mod:`schlieren.pipeline.params`):
    strict types, finite numbers, ranges, choices; unknown names are refused.

    Raises
    ------
    schlieren.pipeline.params.ParamsError
        A ``ValueError`` naming the parameter (``tomography.max_iter``) and its valid values;
        also ``spacetime.window > 0`` or ``refine.passes > 0`` with the ``direct``
        reconstruction (it has no per-frame gradient stage to average or predict from).
    """
    cfg = _validate(RunConfig, d)
    if cfg.reconstruction == "direct" and cfg.spacetime.window > 0:
        raise ParamsError("> 0 needs reconstruction 'two-step' (the direct solve has no per-frame gradient stage "
                          "to average)", "spacetime.window")
    if cfg.reconstruction == "direct" and cfg.refine.passes > 0:
        raise ParamsError("> 0 needs reconstruction 'two-step' (the refinement predicts from the gradient "
                          "solve)", "refine.passes")
    return cfg


def check_config(cfg: RunConfig) -> RunConfig:
    """``cfg`` checked against the schema like a ``--params`` file (for configurations built in Python)."""
    return config_from_dict(config_to_dict(cfg))
