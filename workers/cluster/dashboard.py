"""The scheduler dashboard: its link, and a loopback address with a free port for a local one.

The dashboard shows code and data, so a cluster started here binds it to loopback only
(reach it from elsewhere through an SSH tunnel; DASK-ZARR.md recommendation 10 and
pitfall 20: distributed's default binds all interfaces, and a taken port falls back to a
random one).
"""

from __future__ import annotations

import logging
import socket

from distributed import Client

log = logging.getLogger(__name__)

DEFAULT_DASHBOARD = "127.0.0.1:8787"
_LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


def dashboard_link(client: Client) -> str | None:
    """URL of the scheduler dashboard's status page, or None when the scheduler runs none.

    Formatted with the ``distributed.dashboard.link`` template. For a remote scheduler the
    host is the scheduler's own host name: open an SSH tunnel to reach it.
    """
    try:
        services = client.scheduler_info(n_workers=0).get("services", {})
    except TypeError:  # older distributed without n_workers
        services = client.scheduler_info().get("services", {})
    if "dashboard" not in services:
        return None
    return client.dashboard_link


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _port_is_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
        return True


def loopback_dashboard_address(address: str | None) -> str:
    """Normalise a dashboard ``host:port`` to a loopback host and a free port.

    ``":8787"`` and ``"8787"`` become ``"127.0.0.1:8787"``; a non-loopback host raises
    ``ValueError`` (the dashboard shows code and data: reach it through an SSH tunnel);
    a taken port is replaced by a free one.
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
    if port == 0 or not _port_is_free(host, port):
        new = _free_port(host)
        if port:
            log.info("dashboard port %d is taken; using %d", port, new)
        port = new
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
