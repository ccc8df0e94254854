"""The Python API: docs/api.md's example executed as written, a user's own Dask client,
progress output, refusals before anything exists."""

from __future__ import annotations

import io
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def python_blocks(md: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", md.read_text(), flags=re.S)


def test_import_schlieren_is_cheap_and_versioned():
    code = ("import sys, schlieren\n"
            "print(schlieren.__version__)\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed', 'zarr'}))\n"
            "print(callable(schlieren.run) and callable(schlieren.open))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    from importlib.metadata import version

    assert out[0] == version("schlieren") and out[1] == "[]" and out[2] == "True"


def test_the_documented_example_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (example,) = python_blocks(REPO / "docs" / "api.md")[:1]
    exec(compile(example, "docs/api.md", "exec"), {})
    out = capsys.readouterr().out
    psnr = float(re.search(r"PSNR ([\d.]+) dB", out).group(1))
    assert psnr > 30.0, out
    assert (tmp_path / "api-demo" / "run_report" / "index.html").is_file()
    assert list((tmp_path / "api-demo" / "run_nrrd").glob("temperature_*.nrrd"))


@pytest.mark.system
def test_a_users_client_gets_the_worker_setup_and_the_tomo_resource(tiny_session, serial_store, tmp_path):
    """A LocalCluster the user started without the TOMO resource: tomography tasks would wait
    forever on it; schlieren.run(client=...) adds the resource and the thread caps."""
    from distributed import Client, LocalCluster

    import schlieren

    # worker processes: the setup plugin caps threads through the environment of the process it runs in
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        assert not any(w["resources"] for w in client.scheduler_info()["workers"].values())
        ds = schlieren.run(tiny_session.session, tmp_path / "c.zarr", client=client, progress=False)
        assert all(w["resources"].get("TOMO") == 1 for w in client.scheduler_info()["workers"].values())
        plugins = client.run(lambda dask_worker: sorted(dask_worker.plugins))
        assert all("schlieren-worker-setup" in p for p in plugins.values())
    ref = schlieren.open(serial_store)
    np.testing.assert_array_equal(ds["refractivity"].values, ref["refractivity"].values)  # bit-identical


def test_progress_goes_to_the_given_console(tiny_session, serial_store, tmp_path):
    import shutil

    from rich.console import Console

    import schlieren

    store = tmp_path / "p.zarr"
    shutil.copytree(serial_store, store)
    from schlieren.storage.store import ResultStore

    st = ResultStore.open(store)
    for k in range(st.done("integrate").size):
        st.unmark("integrate", k)  # leave the last stage to do
    buf = io.StringIO()
    schlieren.run(tiny_session.session, store, progress=Console(file=buf, force_terminal=True, width=100))
    text = buf.getvalue()
    assert "integrate" in text and f"{st.done('integrate').size}/{st.done('integrate').size}" in text


def test_bad_params_and_sessions_are_refused_before_anything_exists(tiny_session, tmp_path):
    import schlieren
    from schlieren.storage.errors import SchlierenInputError

    with pytest.raises(ValueError, match=r"tomography.max_iter: must be an integer in \[1, 10000\]"):
        schlieren.run(tiny_session.session, tmp_path / "a.zarr", params={"tomography": {"max_iter": -5}})
    with pytest.raises(SchlierenInputError, match="session manifest not found"):
        schlieren.run(tmp_path / "nowhere.yaml", tmp_path / "b.zarr")
    assert not (tmp_path / "a.zarr").exists() and not (tmp_path / "b.zarr").exists()
    with pytest.raises(SchlierenInputError, match="no result store"):
        schlieren.open(tmp_path / "a.zarr")


def test_progress_goes_to_the_notebook_under_jupyter(monkeypatch):
    import types

    from schlieren.workers import api

    assert not api._progress_console(True).is_jupyter  # a terminal or a script: stderr
    shell = type("ZMQInteractiveShell", (), {})()
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    console = api._progress_console(True)
    assert console.is_jupyter and not console.stderr
