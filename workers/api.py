"""The Python API: ``import schlieren`` (re-exported by the top-level package).

Everything the command line does, as functions that take and return Python objects::

    import schlieren

    res = schlieren.synth("capture", cameras=8, frames=4, size=(480, 360))
    ds = schlieren.run(res.session, "capture.zarr", workers=2)     # -> xarray.Dataset
    ds.temperature.sel(frame=ds.frame[0]).max()
    table = schlieren.evaluate("capture.zarr", res.truth)
    page = schlieren.report("capture.zarr")
    files = schlieren.export("capture.zarr", format="vti", quantity="temperature")

This module lives in ``workers/`` because running a session needs Dask; the store,
session and report code it calls are the same as the CLI's.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from pathlib import Path
from typing import Any

__all__ = ["run", "open", "synth", "evaluate", "report", "export", "RunFailed", "load_params"]

log = logging.getLogger(__name__)

_open = open  # the builtin, before this module's open() shadows it


class RunFailed(RuntimeError):
    """Some tasks of :func:`run` failed; every completed chunk is kept (run again to resume).

    Attributes
    ----------
    summary : RunSummary
        Counts, timings and ``failures`` (task key -> one-line message).
    """

    def __init__(self, summary):
        roots = summary.root_failures()
        lines = [f"{len(roots)} task(s) of the run on {summary.store} failed "
                 f"({len(summary.failures) - len(roots)} more not run because of them); "
                 "completed chunks are kept, run again to resume:"]
        lines += [f"  - {m}" for m in list(roots.values())[:10]]
        super().__init__("\n".join(lines))
        self.summary = summary


def load_params(params) -> Any:
    """A checked :class:`~schlieren.pipeline.stages.RunConfig` from None, a RunConfig, a
    nested dict (``{"tomography": {"max_iter": 40}}``) or the path of a YAML file.

    Raises
    ------
    schlieren.pipeline.params.ParamsError
        A ``ValueError`` naming the parameter and its valid values.
    """
    from schlieren.pipeline.params import ParamsError
    from schlieren.pipeline.stages import RunConfig, check_config, config_from_dict

    if params is None:
        return RunConfig()
    if isinstance(params, RunConfig):
        return check_config(params)
    if isinstance(params, (str, os.PathLike)):
        from schlieren.storage.params_io import read_params

        try:
            return config_from_dict(read_params(params))
        except ParamsError as exc:
            raise ParamsError(f"file {os.fspath(params)}: {exc.message}", exc.field) from None
    if isinstance(params, dict):
        return config_from_dict(params)
    raise TypeError(f"params must be None, a RunConfig, a dict or a YAML file path, not {type(params).__name__}")


def _in_notebook() -> bool:
    ip = sys.modules.get("IPython")
    shell = ip.get_ipython() if ip is not None and hasattr(ip, "get_ipython") else None
    return shell is not None and type(shell).__name__ == "ZMQInteractiveShell"


def _progress_console(progress):
    """The rich console progress bars go to: the notebook's output cell, else stderr."""
    from rich.console import Console

    if progress is True or progress is None:
        return Console(force_jupyter=True) if _in_notebook() else Console(stderr=True)
    return progress  # a rich Console given by the caller


@contextlib.contextmanager
def _client(workers, client, scheduler, tls):
    """The Dask client to use, and whether this call owns it."""
    if client is not None:
        from schlieren.workers.cluster import adopt_client

        adopt_client(client)
        yield client
        return
    if scheduler is None and (workers is None or workers <= 1):
        yield None  # the serial reference loop in this process
        return
    from schlieren.workers.cluster import ClusterOptions, open_client

    opts = ClusterOptions(workers=None if scheduler else int(workers), scheduler=scheduler, tls_dir=tls)
    with open_client(opts) as (c, _info):
        yield c


def run(session, out, *, workers: int | None = None, client=None, scheduler: str | None = None,
        params=None, frames: tuple[int, int] | None = None, progress=True, tls: str | None = None,
        report: str | None = None, frames_per_task: int | None = None, overwrite: bool = False):
    """Process a capture session into a result store and open it.

    Parameters
    ----------
    session : path
        The session folder or its ``session.yaml`` (docs/session.md).
    out : path
        The result store (a Zarr v3 folder). An existing store of the same session and
        parameters is resumed; one of another configuration is refused (naming the
        fields that differ).
    workers : int, optional
        Start a local cluster of this many single-threaded worker processes; ``None`` or
        1 runs the serial reference loop in this process (bit-identical results).
    client : distributed.Client, optional
        Your own cluster. Its workers get the thread caps and the ``TOMO`` resource that
        tomography tasks request automatically (a worker plugin).
    scheduler : str, optional
        Address of a running scheduler (``tcp://host:8786``, or ``tls://`` with ``tls``).
    params : RunConfig, dict or path, optional
        Run parameters (docs/parameters.md); checked before anything is created.
    frames : (int, int), optional
        Half-open range of capture frames, overriding the manifest's ``frames``.
    progress : bool or rich.console.Console
        Progress bars per stage: in the notebook's output cell under Jupyter, on
        stderr otherwise; False for none.
    tls : str, optional
        Certificate folder for a ``tls://`` scheduler (``schlieren tls init``).
    report : str, optional
        Path of a Dask performance report (HTML).
    frames_per_task : int, optional
        Frames of one camera per task in the cheap per-image stages.
    overwrite : bool
        Replace a store of another configuration at ``out`` (a store of this same run
        is resumed either way).

    Returns
    -------
    xarray.Dataset
        :func:`open` of the finished store.

    Raises
    ------
    schlieren.storage.errors.SchlierenInputError
        Bad session or store, one line naming the file, camera and field (nothing done).
    schlieren.pipeline.params.ParamsError
        A bad parameter (nothing done).
    RunFailed
        Some tasks failed; completed chunks are kept and a second call resumes.
    """
    from schlieren.storage.session import load_session
    from schlieren.workers.progress import StageProgress
    from schlieren.workers.run import run_session

    cfg = load_params(params)
    loaded = load_session(session, frames=frames)  # bad input stops here, before any cluster
    console = _progress_console(progress) if progress else None
    with _client(workers, client, scheduler, tls) as c, \
            StageProgress(enabled=bool(progress), console=console) as bars:
        summary = run_session(loaded, out, client=c, frames=frames, serial=c is None, config=cfg,
                              report=report, on_receipt=bars.receipt, on_failure=bars.failure,
                              on_plan=bars.plan, frames_per_task=frames_per_task, overwrite=overwrite)
    if not summary.ok:
        raise RunFailed(summary)
    return open(out)


def open(store):
    """Open a result store as an ``xarray.Dataset`` (lazy, dask-backed arrays).

    Reads are checked chunk by chunk (``storage/integrity.py``). Dims, coordinates
    (capture ``frame`` index, ``time``, ``camera``, ``x/y/z`` in metres,
    ``u/v`` in image pixels) and CF attributes are described in docs/store.md. Nested
    root attributes (``session``, ``params``...) are JSON text; :func:`json.loads` them.
    """
    from schlieren.storage import location
    from schlieren.storage.integrity import open_dataset
    from schlieren.storage.store import ResultStore

    ResultStore.open(store, mode="r")  # not a result store: a one-line StoreError naming the path
    # every chunk read is checked: a corrupt one, or one lost under a set completion marker,
    # raises ChunkError naming the array and the chunk instead of returning data (a store at
    # a URL: credentials and endpoint from the environment, as for runs)
    return open_dataset(location.normalize(store), consolidated=None)


def synth(out_dir, **kwargs):
    """Render a synthetic session with its ground truth (``schlieren synth``).

    Keyword arguments are those of :func:`schlieren.workers.synth.synthesize`
    (``cameras=16, ring="half", phantom="plume", frames=8, size=(1440, 1080)``, ...).

    Returns
    -------
    SynthResult
        ``.session`` (the session.yaml) and ``.truth`` (truth.zarr) among others.
    """
    from schlieren.workers.synth import synthesize

    return synthesize(out_dir, **kwargs)


def evaluate(store, truth) -> dict:
    """Accuracy of a store against synthetic ground truth (``schlieren evaluate``).

    Returns
    -------
    dict
        ``frames``: one row per store frame (``frame`` = capture index, ``time``, ``rms``,
        ``psnr``...); ``overall``: the averages (docs/store.md, "Accuracy metric").
    """
    from schlieren.workers.evaluate import evaluate as _evaluate

    return _evaluate(store, truth)


def report(store, out=None, *, truth=None, frames: tuple[int, int] | None = None,
           cameras: int | None = None) -> Path:
    """Write the HTML report of a store (``schlieren report``); returns ``index.html``.

    ``truth`` (a ``truth.zarr``) adds the accuracy table of :func:`evaluate`.
    """
    from schlieren.workers.report import make_report

    evaluation = evaluate(store, truth) if truth is not None else None
    return make_report(store, out, evaluation=evaluation, frames=frames, max_cameras=cameras)


def export(store, out=None, *, format: str = "vti", quantity: str = "refractivity",
           frames: tuple[int, int] | None = None) -> list[Path]:
    """Export one volume quantity per frame (``schlieren export``); returns the files to open
    (the ``.pvd`` of vti, the ``.mhd`` headers of raw, the ``.nrrd`` files)."""
    from schlieren.workers.report import generate_export

    return list(generate_export(store, out, format=format, quantity=quantity, frames=frames).entry_points)
