"""The scheduler dashboard: its link, and a loopback address for a local one.

The dashboard shows code and data, so a cluster started here binds it to loopback only
(reach it from elsewhere through an SSH tunnel; DASK-ZARR.md recommendation 10 and
pitfall 20: distributed's default binds all interfaces, and a taken port falls back to a
random one). The link names the address the dashboard really listens on (for a scheduler
in this process, its HTTP server's own socket), and the line printed with it says when
the port asked for was taken.
"""

from __future__ import annotations

import contextlib
import logging
import re
import socket
import warnings
from collections.abc import Iterator
from typing import Any

from distributed import Client
from distributed.utils import format_dashboard_link

log = logging.getLogger(__name__)

DEFAULT_DASHBOARD = "127.0.0.1:8787"
_LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})
_ANY_HOSTS = frozenset({"", "0.0.0.0", "::"})
_PORT_IN_USE = r"Port \d+ is already in use"


def _bound_dashboard(client: Client) -> tuple[str, int] | None:
    """``(host, port)`` the dashboard of a scheduler running in this process listens on."""
    server = getattr(getattr(getattr(client, "cluster", None), "scheduler", None), "http_server", None)
    port = getattr(server, "port", None)
    if not port:
        return None
    return str(getattr(server, "address", "") or ""), int(port)


def _requested_port(cluster: Any) -> int | None:
    """The dashboard port a cluster object asked its scheduler for (None: unknown or any)."""
    spec = getattr(cluster, "scheduler_spec", None) or {}
    address = (spec.get("options") or {}).get("dashboard_address") if isinstance(spec, dict) else None
    if address is None:
        return None
    try:
        port = int(str(address).rpartition(":")[2])
    except ValueError:
        return None
    return port or None


def dashboard_link(client: Client) -> str | None:
    """URL of the scheduler dashboard's status page, or None when the scheduler runs none.

    Formatted with the ``distributed.dashboard.link`` template. For a scheduler in this
    process the host is the one its dashboard listens on (``127.0.0.1`` for ours, whatever
    address the scheduler itself has); for a remote scheduler it is the scheduler's own
    host name: open an SSH tunnel to reach it.
    """
    try:
        services = client.scheduler_info(n_workers=0).get("services", {})
    except TypeError:  # older distributed without n_workers
        services = client.scheduler_info().get("services", {})
    if "dashboard" not in services:
        return None
    bound = _bound_dashboard(client)
    if bound is not None and bound[0] not in _ANY_HOSTS:
        host, port = bound
        return format_dashboard_link(f"[{host}]" if ":" in host else host, port)
    return client.dashboard_link


def dashboard_line(client: Client) -> str | None:
    """What a run prints about its dashboard: ``dashboard: URL``, and when the port asked
    for was taken (another run, a notebook's cluster) ``(port 8787 is taken; ...)``."""
    link = dashboard_link(client)
    if not link:
        return None
    asked, bound = _requested_port(getattr(client, "cluster", None)), _bound_dashboard(client)
    if asked and bound is not None and bound[1] != asked:
        return f"dashboard: {link} (port {asked} is taken, by another run or program; this run's is {bound[1]})"
    return f"dashboard: {link}"


@contextlib.contextmanager
def port_warnings_logged() -> Iterator[None]:
    """Starting a scheduler whose dashboard port is taken: distributed picks a free one and
    says so as a multi-line UserWarning on stderr; here it becomes a log line (the run's
    ``dashboard:`` line names the port taken). Other warnings pass through."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.filterwarnings("always", message=_PORT_IN_USE, category=UserWarning)
        yield
    for w in caught:
        if re.search(_PORT_IN_USE, str(w.message)):
            log.info("dashboard: %s", " ".join(str(w.message).split()))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback_dashboard_address(address: str | None) -> str:
    """Normalise a dashboard ``host:port`` to a loopback host.

    ``":8787"`` and ``"8787"`` become ``"127.0.0.1:8787"``; a non-loopback host raises
    ``ValueError`` (the dashboard shows code and data: reach it through an SSH tunnel).
    Port 0 becomes a free port. A taken port is kept: the scheduler then binds another and
    :func:`dashboard_line` says which port was taken.
    """
    address = (address or DEFAULT_DASHBOARD).strip()
    if "://" in address:
        address = address.split("://", 1)[1]
    host, sep, port_s = address.rpartition(":")
    if not sep:
        host, port_s = "", address
    host = host.strip("[]") or "127.0.0.1"
    if host not in _LOOPBACK_HOSTS:
        raise ValueError(
            f"the local dashboard binds loopback only, got host {host!r}; use an SSH tunnel to view it remotely"
        )
    if host == "localhost":
        host = "127.0.0.1"
    try:
        port = int(port_s)
    except ValueError as exc:
        raise ValueError(f"bad dashboard address {address!r}: expected HOST:PORT") from exc
    if port == 0:
        port = _free_port(host)
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
