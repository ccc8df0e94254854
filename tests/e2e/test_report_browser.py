"""The report page as a browser shows it: headless Chromium screenshot of index.html served
over HTTP from 127.0.0.1.

System tier. Without Chromium the test is skipped with a one-line reason; `.ci/run`
installs it (Debian's package) so CI always runs it. ``SCHLIEREN_REQUIRE_BROWSER=1`` turns
the skip into a failure (for a machine that must have it).
"""

from __future__ import annotations

import functools
import http.server
import importlib.util
import os
import shutil
import subprocess
import threading
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from schlieren.workers.report import make_report

pytestmark = pytest.mark.system

WIDTH, HEIGHT = 1280, 2000
BROWSERS = ("chromium", "chromium-browser", "chromium-headless-shell", "google-chrome", "/usr/bin/chromium")


def _fixture_module():
    path = Path(__file__).parents[1] / "storage" / "test_report.py"
    spec = importlib.util.spec_from_file_location("_schlieren_report_store_fixture_e2e", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _browser() -> str:
    for name in BROWSERS:
        found = shutil.which(name)
        if found:
            return found
    msg = "headless Chromium not found (`apt-get install -y chromium`; .ci/run installs it)"
    if os.environ.get("SCHLIEREN_REQUIRE_BROWSER") == "1":
        pytest.fail(msg)
    pytest.skip(msg)


class _Handler(http.server.SimpleHTTPRequestHandler):
    requested: list[str] = []

    def log_message(self, fmt, *args):  # keep the test output clean, remember what was fetched
        type(self).requested.append(self.path)


def test_report_page_screenshot(tmp_path):
    browser = _browser()
    fx = _fixture_module()
    store = fx.make_store(tmp_path)
    index = make_report(store, tmp_path / "report")

    handler = type("H", (_Handler,), {"requested": []})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             functools.partial(handler, directory=str(index.parent)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    shot = tmp_path / "screenshot.png"
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/index.html"
        cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               "--disable-dev-shm-usage", "--hide-scrollbars", f"--user-data-dir={tmp_path / 'profile'}",
               f"--screenshot={shot}", f"--window-size={WIDTH},{HEIGHT}", url]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    finally:
        server.shutdown()
        server.server_close()
    assert shot.exists(), f"no screenshot; chromium exited {proc.returncode}: {proc.stderr[-2000:]}"

    img = iio.imread(shot)[..., :3].astype(np.float64)
    assert img.shape == (HEIGHT, WIDTH, 3)
    assert img.std() > 20  # not a blank page
    # the page fetched its figures through the relative links
    fetched = set(handler.requested)
    assert any("deflection_cam00.png" in r for r in fetched), fetched
    # the figures are drawn: the deflection colour coding gives strongly saturated pixels
    # (hue = direction), which plain text and tables never have
    mx, mn = img.max(axis=-1), img.min(axis=-1)
    saturated = (mx - mn) / np.maximum(mx, 1.0) > 0.6
    assert saturated.sum() > 2000, saturated.sum()
    # several distinct hues appear (red, green, blue regions of the colour wheel)
    dominant = np.argmax(img[saturated], axis=-1)
    assert all(np.sum(dominant == k) > 100 for k in range(3)), np.bincount(dominant, minlength=3)
