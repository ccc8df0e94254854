"""Dashboard and performance report of a separately started scheduler, on 127.0.0.1."""

from __future__ import annotations

import json
import time
import urllib.request

import pytest
from bokeh.client import pull_session

from schlieren.workers.cluster import TOMO, ClusterOptions, open_client
from schlieren.workers.monitoring import performance_report_cm


def _get(url: str) -> tuple[int, str]:
    with urllib.request.urlopen(url, timeout=20) as resp:
        return resp.status, resp.read().decode("utf-8", errors="replace")


def _status_page_task_names(url: str) -> set[str]:
    """Task-prefix names shown by the status page's "progress" plot (its Bokeh document)."""
    names: set[str] = set()
    with pull_session(url=url) as session:
        for model in session.document.models:
            data = getattr(model, "data", None)
            if type(model).__name__ == "ColumnDataSource" and "name" in data and "all" in data:
                names |= {str(n) for n in data["name"]}
    return names


@pytest.mark.timeout(120)
def test_dashboard_status_page_lists_our_tasks(external_scheduler, tmp_path):
    cluster = external_scheduler
    with open_client(ClusterOptions(scheduler=cluster.address, connect_timeout=30)) as (client, info):
        link = info.dashboard_link
        assert link == f"http://127.0.0.1:{cluster.dashboard_port}/status"
        assert _get(link.replace("/status", "/health")) == (200, "ok")

        report = tmp_path / "reports" / "session-report.html"
        with performance_report_cm(report) as path:
            flows = client.map(lambda i: i + 1, range(6), key=[f"deflection-sess-cam0-{i:06d}" for i in range(6)])
            vols = client.map(
                lambda i: 2 * i, range(3), key=[f"tomography-sess-{i:06d}" for i in range(3)], resources={TOMO: 1}
            )
            assert client.gather(flows) == [1, 2, 3, 4, 5, 6] and client.gather(vols) == [0, 2, 4]
        assert path == report

        status, html = _get(link)
        assert status == 200 and "<title>Dask" in html and "bokeh" in html.lower()
        # the progress plot of the status page names our stages (futures are still held)
        names = _status_page_task_names(link)
        assert any(n.startswith("deflection") for n in names), names
        assert any(n.startswith("tomography") for n in names), names
        assert not any(n.startswith("integrate") for n in names)  # control: no such task was run

        counts = json.loads(_get(link.replace("/status", "/json/counts.json"))[1])
        assert counts["workers"] == 2 and counts["tasks"] >= 9
        status, workers_html = _get(link.replace("/status", "/info/main/workers.html"))
        assert status == 200 and "127.0.0.1" in workers_html

    html = report.read_text()
    assert html.lstrip().lower().startswith("<!doctype html") or "<html" in html[:2000].lower()
    assert "deflection-sess" in html and "tomography-sess" in html


def test_performance_report_none_is_a_no_op():
    t0 = time.perf_counter()
    with performance_report_cm(None) as path:
        assert path is None
    assert time.perf_counter() - t0 < 5


def _health(link: str) -> tuple[int, str]:
    return _get(link.replace("/status", "/health"))


@pytest.mark.system
@pytest.mark.timeout(120)
def test_a_taken_dashboard_port_is_named_in_the_dashboard_line():
    """8787 taken (another run, a notebook's cluster): the run still starts, on another port,
    and the line it prints says which port was taken; the link is the one that answers."""
    import socket

    from schlieren.workers.cluster import dashboard_line

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        taken = s.getsockname()[1]
        opts = ClusterOptions(workers=1, memory_limit="1GiB", dashboard_address=f"127.0.0.1:{taken}")
        with open_client(opts) as (client, info):
            line = dashboard_line(client)
            assert line == f"dashboard: {info.dashboard_link} (port {taken} is taken, by another run or program; " \
                           f"this run's is {info.dashboard_link.split(':')[2].split('/')[0]})", line
            assert f":{taken}/" not in info.dashboard_link
            assert _health(info.dashboard_link) == (200, "ok")


@pytest.mark.system
@pytest.mark.timeout(120)
def test_a_batch_clusters_dashboard_link_names_where_it_listens():
    """The submit scheduler listens on all interfaces (host None: the compute nodes reach it)
    but its dashboard on loopback only: the link names 127.0.0.1, not the host's address."""
    from pathlib import Path

    from distributed import Client

    from schlieren.workers.cluster import dashboard_line, dashboard_link, make_batch_cluster
    from schlieren.workers.commands.submit import load_submit_config

    cfg = load_submit_config(Path(__file__).resolve().parents[2] / "deploy/slurm/jobqueue.yaml")
    cfg["schlieren"].pop("tls", None)
    cfg["schlieren"]["adapt"] = {"minimum": 0, "maximum": 1}  # submits nothing
    cfg["jobqueue"]["slurm"]["scheduler-options"] = {"dashboard_address": "127.0.0.1:0"}
    cluster = make_batch_cluster("slurm", cfg)
    try:
        with Client(cluster) as client:
            link = dashboard_link(client)
            assert link.startswith("http://127.0.0.1:"), (link, cluster.scheduler_address)
            assert _health(link) == (200, "ok")
            assert dashboard_line(client) == f"dashboard: {link}"
    finally:
        cluster.close()
