"""The local mode: a ``LocalCluster`` of worker processes on ``127.0.0.1`` only (scheduler,
workers, nannies, dashboards), with the ``TOMO`` resource and the thread caps, optionally
talking ``tls://`` with the certificates of ``schlieren tls init``
(DASK-ZARR.md recommendation 8). Its worker processes are spawned and import the
``__main__`` script again: a script that starts one outside ``if __name__ == "__main__":``
is refused with one line (DASK-ZARR.md pitfall 10).
"""

from __future__ import annotations

import ast
import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from distributed import Client

from schlieren.workers.cluster.dashboard import loopback_dashboard_address, port_warnings_logged
from schlieren.workers.cluster.interrupts import LocalInterrupts
from schlieren.workers.cluster.options import ClusterInfo, ClusterOptions
from schlieren.workers.cluster.scheduler import prepare_client
from schlieren.workers.cluster.settings import THREAD_ENV, TOMO
from schlieren.workers.security import cluster_security

log = logging.getLogger(__name__)


class MissingMainGuard(SystemExit):
    """A script starts a local cluster at its top level, outside ``if __name__ == "__main__":``.

    Worker processes are spawned: each imports the script again (as ``__mp_main__``) and
    would start a cluster of its own, which fails in hundreds of lines of worker
    tracebacks ending in "Nanny failed to start". A ``SystemExit`` carrying the one line
    that says so: the script stops with that line, no traceback.
    """


def _is_main_guard(test: ast.expr) -> bool:
    """``__name__ == "__main__"`` (either side)."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = [test.left, test.comparators[0]]
    return (any(isinstance(x, ast.Name) and x.id == "__name__" for x in sides)
            and any(isinstance(x, ast.Constant) and x.value == "__main__" for x in sides))


def unguarded_main_statement() -> tuple[str, int] | None:
    """``(file, line)`` of the top-level statement of the ``__main__`` script that is running
    now (and led to this call) when it is not under ``if __name__ == "__main__":``; None
    when guarded, or when ``__main__`` is no file (a notebook, ``python -c``, a REPL)."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if main is None or not path:
        return None
    frame, line = sys._getframe(), None
    while frame is not None:  # the outermost frame running the script's top level
        if frame.f_globals is vars(main) and frame.f_code.co_name == "<module>":
            line = frame.f_lineno
        frame = frame.f_back
    if line is None:
        return None
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"), filename=str(path))
    except (OSError, SyntaxError, ValueError):
        return None
    for node in tree.body:
        if node.lineno <= line <= (node.end_lineno or node.lineno):
            guarded = isinstance(node, ast.If) and _is_main_guard(node.test) and any(
                b.lineno <= line <= (b.end_lineno or b.lineno) for b in node.body)
            return None if guarded else (str(path), node.lineno)
    return None


def check_main_guard(n_workers: int) -> None:
    """Refuse, with one line, to start local worker processes from an unguarded script
    (raises :class:`MissingMainGuard`), before anything starts."""
    main = sys.modules.get("__main__")
    if getattr(main, "__name__", "__main__") == "__mp_main__":  # a worker re-importing such a script
        raise MissingMainGuard("schlieren: a worker process imported the script that started it and would "
                               "start a cluster too: put the run under `if __name__ == \"__main__\":`")
    where = unguarded_main_statement()
    if where is not None:
        path, line = where
        raise MissingMainGuard(
            f"schlieren: {Path(path).name}, line {line}, starts {n_workers} local worker processes at the top "
            "level of the script; each imports the script again and would start its own: put the call under "
            "`if __name__ == \"__main__\":` (docs/api.md)")


def _start_local_cluster(opts: ClusterOptions, n_workers: int) -> Any:
    """The ``LocalCluster`` of ``opts``, started; a taken dashboard port is logged, not warned
    (distributed binds another; :func:`dashboard_line` names the port taken)."""
    from distributed import LocalCluster

    kwargs: dict[str, Any] = {}
    if opts.tls_dir:
        kwargs["security"] = cluster_security(opts.tls_dir)
        kwargs["protocol"] = "tls://"
    elif opts.tls_cert:
        raise ValueError("a local TLS cluster needs a certificate directory (--tls DIR) with scheduler, worker and client certificates")
    with port_warnings_logged():  # a taken dashboard port: one log line, and the run's "dashboard:" line
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=opts.threads_per_worker,
            processes=True,
            host="127.0.0.1",
            dashboard_address=loopback_dashboard_address(opts.dashboard_address),
            memory_limit=opts.memory_limit,
            resources={TOMO: opts.tomo_slots},
            local_directory=opts.local_directory,
            silence_logs=logging.WARNING,
            **kwargs,
        )
    return cluster


@contextlib.contextmanager
def local_client(opts: ClusterOptions) -> Iterator[tuple[Client, ClusterInfo]]:
    """Start the local cluster of ``opts`` and yield ``(client, info)``; close both on exit."""
    n_workers = opts.workers or max(1, os.cpu_count() or 1)
    check_main_guard(n_workers)  # spawned workers import an unguarded script again
    # the nannies run in this process and export pre-spawn-environ into os.environ before
    # spawning each worker; put this process's own environment back when done
    saved_env = {k: os.environ.get(k) for k in THREAD_ENV}
    cluster = _start_local_cluster(opts, n_workers)
    try:
        client = Client(cluster, set_as_default=True)
        try:
            client.wait_for_workers(n_workers, timeout=opts.connect_timeout)
            client.register_plugin(LocalInterrupts())
            info = prepare_client(client, opts, "local")
            log.info("local cluster with %d worker(s), dashboard %s", info.n_workers, info.dashboard_link)
            yield client, info
        finally:
            client.close()
    finally:
        cluster.close()
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
