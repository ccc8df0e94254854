"""Shared fixtures: a tiny synthetic capture (rendered once per test session) and its serial reconstruction."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

TINY = dict(cameras=4, ring="half", phantom="blob", frames=3, size=(192, 144), seed=3,
            recon_voxel=0.005, supersample=2)


@pytest.fixture(scope="session")
def tiny_spec():
    """The tiny session's synthesis parameters (``TINY``), for tests that vary them (``from
    conftest import`` names another conftest module in a full run)."""
    return dict(TINY)


@pytest.fixture(scope="session")
def tiny_session(tmp_path_factory):
    from schlieren.workers.synth import synthesize

    out = tmp_path_factory.mktemp("tiny") / "session"
    res = synthesize(out, **TINY)
    return res


@pytest.fixture(scope="session")
def serial_run(tiny_session, tmp_path_factory):
    """The tiny session reconstructed by the serial reference executor: ``store`` (its path),
    ``reads`` (the params fields the run's code read, tests/params_reads.py) and ``log`` (the
    run's log messages)."""
    import logging
    from types import SimpleNamespace

    from params_reads import recording_reads

    from schlieren.workers.run import run_session

    out = tmp_path_factory.mktemp("serial") / "store.zarr"
    lines: list[str] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda record: lines.append(record.getMessage())
    logger = logging.getLogger("schlieren")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        with recording_reads() as reads:
            summary = run_session(tiny_session.session, out, serial=True)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert summary.ok, summary.failures
    return SimpleNamespace(store=out, reads=frozenset(reads), log=lines)


@pytest.fixture(scope="session")
def serial_store(serial_run):
    """The tiny session reconstructed by the serial reference executor."""
    return serial_run.store


def pytest_configure(config):
    # tests/ holds shared helpers (store_compare.py) importable from every test folder
    import sys
    from pathlib import Path

    here = str(Path(__file__).parent)
    if here not in sys.path:
        sys.path.insert(0, here)


# --------------------------------------------------------------------------------------
# a real S3-compatible server on 127.0.0.1 for the object-store tests
# --------------------------------------------------------------------------------------
S3_ENV = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
          "AWS_DEFAULT_REGION": "us-east-1"}


class S3Server:
    """moto's S3 server (from the test extra) in a subprocess; ``bucket()`` makes a fresh bucket."""

    def __init__(self, endpoint: str, proc):
        self.endpoint = endpoint
        self.proc = proc
        self._n = 0

    def bucket(self, prefix: str = "t") -> str:
        """A new empty bucket's URL, ``s3://<name>``."""
        import fsspec

        self._n += 1
        name = f"{prefix}-{self._n:04d}"
        fsspec.filesystem("s3", endpoint_url=self.endpoint).mkdir(name)
        return f"s3://{name}"

    def upload(self, folder, url: str) -> str:
        """Copy a local folder's files below ``url``; returns ``url``."""
        import fsspec

        fs = fsspec.filesystem("s3", endpoint_url=self.endpoint)
        fs.put(f"{folder}/", url.removeprefix("s3://") + "/", recursive=True)
        return url


@pytest.fixture(scope="session")
def s3_server():
    """Start moto's S3 server on a free 127.0.0.1 port with test credentials in the environment.

    The environment (AWS_ENDPOINT_URL, keys, region) is set for this process and inherited
    by the CLI subprocesses and Dask workers the tests start, as a deployment's would be.
    Skipped, saying why, when moto[server] or s3fs is not installed.
    """
    import socket
    import subprocess
    import sys
    import time
    import urllib.request

    for mod, what in (("moto.server", "moto[server]"), ("s3fs", "s3fs")):
        try:
            __import__(mod)
        except ImportError as exc:
            pytest.skip(f"object-store tests need {what} (pip install -e '.[test]'): {exc}")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while True:
        try:
            with urllib.request.urlopen(f"{endpoint}/moto-api/", timeout=2):
                break
        except OSError:
            if proc.poll() is not None or time.time() > deadline:
                proc.kill()
                pytest.fail(f"moto's S3 server did not start on {endpoint}")
            time.sleep(0.2)
    try:
        with pytest.MonkeyPatch.context() as mp:
            for k, v in {**S3_ENV, "AWS_ENDPOINT_URL": endpoint}.items():
                mp.setenv(k, v)
            yield S3Server(endpoint, proc)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


# --------------------------------------------------------------------------------------
# test tiers: fast (pure Python, the edit-test loop) and system (daemons and tools)
# --------------------------------------------------------------------------------------
#: Fixtures that start something beyond Python: a test using one is in the system tier.
SYSTEM_FIXTURES = {"s3_server", "external_cluster_factory", "external_scheduler", "slurm"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if SYSTEM_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.system)


def _starts_a_service(args) -> str | None:
    """What a command line starts that belongs to the system tier, or None."""
    words = [str(a) for a in (args if isinstance(args, (list, tuple)) else str(args).split())]
    joined = " ".join(words)
    if "--dry-run" in words or "--help" in words:
        return None
    for i, w in enumerate(words):
        if w == "--workers" and i + 1 < len(words) and words[i + 1] not in ("0", "1"):
            return f"a local Dask cluster ({joined[:120]})"
        if w.startswith("--workers=") and w.split("=", 1)[1] not in ("0", "1"):
            return f"a local Dask cluster ({joined[:120]})"
    for needle, what in (("--scheduler", "a Dask client of a scheduler"), (" submit ", "a batch cluster"),
                         ("moto.server", "an S3 server"), ("chromium", "a browser"),
                         ("dask scheduler", "a Dask scheduler"), ("dask worker", "Dask workers"),
                         ("slurm.sh", "SLURM")):
        if needle in f" {joined} ":
            return f"{what} ({joined[:120]})"
    return None


@pytest.fixture(autouse=True)
def _fast_tier_starts_no_services(request, monkeypatch):
    """In a run that deselects the system tier, a test that starts a Dask cluster, a
    server, a browser or SLURM without the `system` marker fails and says so: the fast
    tier stays fast because nothing can slip into it unmarked."""
    markexpr = request.config.getoption("-m") or ""
    if "not system" not in markexpr or request.node.get_closest_marker("system"):
        return
    import subprocess

    import distributed.deploy.spec as spec

    def refuse(what):
        pytest.fail(f"this test starts {what}: mark it @pytest.mark.system (tests/conftest.py)", pytrace=False)

    real_popen_init = subprocess.Popen.__init__

    def popen_init(self, args, *a, **kw):
        what = _starts_a_service(args)
        if what:
            refuse(what)
        real_popen_init(self, args, *a, **kw)

    real_spec_init = spec.SpecCluster.__init__

    def spec_init(self, *a, **kw):
        refuse("a Dask cluster in this process")
        real_spec_init(self, *a, **kw)

    monkeypatch.setattr(subprocess.Popen, "__init__", popen_init)
    monkeypatch.setattr(spec.SpecCluster, "__init__", spec_init)
