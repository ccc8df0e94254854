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
