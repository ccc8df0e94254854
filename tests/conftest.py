"""Shared fixtures: a tiny synthetic capture (rendered once per test session) and its serial reconstruction."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

TINY = dict(cameras=4, ring="half", phantom="blob", frames=3, size=(192, 144), seed=3,
            recon_voxel=0.005, supersample=2)


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
