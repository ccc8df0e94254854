"""deploy/: files parse, dask-jobqueue renders our job scripts, manifests match their config.

No batch system or Kubernetes cluster is reachable here, so the SLURM job script is also
*executed* with bash against a scheduler on 127.0.0.1: its ``#SBATCH`` lines are comments,
the rest starts real workers, which must join with our resources, thread caps and TLS.
"""

from __future__ import annotations

import copy
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import dask.config
import pytest
import yaml

from schlieren.workers.cli import main as cli_main
from schlieren.workers.cluster import (
    DASK_SETTINGS,
    THREAD_ENV,
    TOMO,
    ClusterOptions,
    daskcluster_manifest,
    job_script,
    jobqueue_cluster,
    jobqueue_kwargs,
    make_batch_cluster,
    open_client,
    schlieren_section,
    worker_thread_report,
)
from schlieren.workers.commands.submit import load_submit_config, render
from schlieren.workers.security import make_certificates

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten(v, key))
        else:
            out[key] = v
    return out


def test_every_yaml_in_deploy_parses():
    files = sorted(DEPLOY.rglob("*.yaml"))
    assert {f.relative_to(DEPLOY).as_posix() for f in files} >= {
        "config/bos.yaml",
        "slurm/jobqueue.yaml",
        "kubernetes/schlieren.yaml",
        "kubernetes/daskcluster.yaml",
        "kubernetes/daskcluster-tls.yaml",
        "kubernetes/helm-values.yaml",
        "kubernetes/networkpolicy.yaml",
        "kubernetes/run-job.yaml",
    }
    for f in files:
        docs = list(yaml.safe_load_all(f.read_text()))
        assert docs and all(isinstance(d, dict) for d in docs), f


def test_bos_yaml_equals_the_settings_the_code_applies():
    cfg = yaml.safe_load((DEPLOY / "config/bos.yaml").read_text())
    flat = {k: str(v) for k, v in _flatten(cfg).items()}
    assert flat == {k: str(v) for k, v in DASK_SETTINGS.items()}
    # and Dask reads it as such (what DASK_CONFIG=deploy/config does on every machine)
    loaded = dask.config.collect(paths=[str(DEPLOY / "config")], env={})
    assert dask.config.get("distributed.nanny.pre-spawn-environ.OPENCV_FOR_THREADS_NUM", config=loaded) == "1"
    assert dask.config.get("distributed.worker.memory.recent-to-old-time", config=loaded) == "120s"


def test_containerfile_sets_thread_caps_and_a_non_root_user():
    text = (DEPLOY / "Containerfile").read_text()
    assert re.search(r"^FROM python:3\.11\.\d+-slim", text, re.M)
    for var, value in THREAD_ENV.items():
        assert re.search(rf"\b{var}={value}\b", text), var
    assert "DASK_CONFIG=/opt/schlieren/deploy/config" in text and "COPY deploy/config" in text
    users = re.findall(r"^USER\s+(\S+)", text, re.M)
    assert users and users[-1] not in ("root", "0")
    assert re.search(r'pip install --constraint deploy/constraints\.txt "\.\[cluster,s3\]"', text)
    # everything the image copies exists in the repository
    for src in re.findall(r"^COPY\s+(.+?)\s+\S+$", text, re.M):
        for part in src.split():
            assert (REPO / part).exists(), part


def test_shell_scripts_are_valid_bash():
    for script in (DEPLOY / "tls/make-certs.sh", DEPLOY / "slurm/schlieren.sbatch"):
        subprocess.run(["bash", "-n", str(script)], check=True, timeout=30)
    sbatch = (DEPLOY / "slurm/schlieren.sbatch").read_text()
    assert "--resources TOMO=1" in sbatch and "--nthreads 1" in sbatch
    assert "--protocol tls" in sbatch and "--dashboard-address 127.0.0.1:8787" in sbatch
    for var in ("OMP_NUM_THREADS", "OPENCV_FOR_THREADS_NUM", "NUMBA_NUM_THREADS"):
        assert f"{var}=1" in sbatch


def _jobqueue_config(tls_dir: Path | None = None, **slurm_overrides) -> dict:
    cfg = load_submit_config(DEPLOY / "slurm/jobqueue.yaml")
    if tls_dir is None:
        cfg["schlieren"].pop("tls", None)
    else:
        cfg["schlieren"]["tls"] = {"dir": str(tls_dir)}
    cfg["jobqueue"]["slurm"].update(slurm_overrides)
    return cfg


@pytest.mark.parametrize("kind", ["slurm", "pbs"])
def test_jobqueue_renders_our_job_script(kind, tmp_path):
    certs = make_certificates(tmp_path / "tls")
    cfg = _jobqueue_config(certs.directory)
    script = job_script(kind, cfg)
    directive = "#SBATCH" if kind == "slurm" else "#PBS"
    assert directive in script
    if kind == "slurm":
        assert "#SBATCH -p compute" in script and "#SBATCH --cpus-per-task=8" in script
        assert "#SBATCH -J schlieren-worker" in script and "#SBATCH --exclusive" in script
    else:
        assert "#PBS -l select=1:ncpus=8:mem=64GB" in script and "#PBS -q workq" in script
    lines = script.splitlines()
    worker_line = next(ln for ln in lines if "distributed.cli.dask_worker" in ln)
    # thread caps are exported before the worker command
    for var in THREAD_ENV:
        exports = [i for i, ln in enumerate(lines) if ln.strip() == f"export {var}={THREAD_ENV[var]}"]
        assert exports and exports[0] < lines.index(worker_line), var
    args = shlex.split(worker_line)
    assert args[args.index("--resources") + 1] == f"{TOMO}=1"
    assert args[args.index("--nthreads") + 1] == "1" and args[args.index("--nworkers") + 1] == "8"
    assert args[args.index("--interface") + 1] == "ib0"
    assert args[args.index("--tls-ca-file") + 1] == str(certs.ca_file)
    assert args[args.index("--tls-cert") + 1] == str(certs.directory / "worker.pem")
    assert args[args.index("--tls-key") + 1] == str(certs.directory / "worker-key.pem")
    assert any(a.startswith("tls://") for a in args)
    # without TLS: no TLS flags, tcp://
    plain = job_script(kind, _jobqueue_config(None))
    assert "--tls-cert" not in plain and "tcp://" in plain and "tls://" not in plain


def test_jobqueue_kwargs_respect_user_resources_and_validate():
    cfg = _jobqueue_config(None, worker_extra_args=["--resources", "TOMO=2", "--lifetime", "1h"])
    job_kw, cluster_kw = jobqueue_kwargs("slurm", cfg)
    assert job_kw["worker_extra_args"].count("--resources") == 1
    assert cluster_kw["scheduler_options"]["dashboard_address"] == "127.0.0.1:8787"
    bad = _jobqueue_config(None, cores=8, processes=3)
    with pytest.raises(ValueError, match="multiple of processes"):
        jobqueue_kwargs("slurm", bad)
    no_mem = copy.deepcopy(cfg)
    del no_mem["jobqueue"]["slurm"]["memory"]
    with pytest.raises(ValueError, match="memory is required"):
        jobqueue_kwargs("slurm", no_mem)
    with pytest.raises(ValueError, match="no 'jobqueue: pbs:'"):
        jobqueue_kwargs("pbs", {"jobqueue": {"slurm": {}}})
    with pytest.raises(ValueError, match="unknown key"):
        schlieren_section({"schlieren": {"scael": 3}})
    with pytest.raises(ValueError, match="unknown cluster kind"):
        make_batch_cluster("sge", cfg)


@pytest.mark.system
@pytest.mark.timeout(60)
def test_jobqueue_cluster_object_renders_the_same_script(tmp_path):
    certs = make_certificates(tmp_path / "tls")
    cfg = _jobqueue_config(certs.directory, interface="lo", local_directory=str(tmp_path), log_directory=None,
                           **{"scheduler-options": {"interface": "lo", "dashboard_address": "127.0.0.1:0"}})
    cluster = jobqueue_cluster("slurm", cfg)  # starts the scheduler here; submits nothing
    try:
        assert cluster.scheduler_address.startswith("tls://127.0.0.1:")
        assert cluster.job_script() == job_script("slurm", cfg, scheduler_address=cluster.scheduler_address)
    finally:
        cluster.close()


@pytest.mark.timeout(120)
def test_rendered_slurm_script_starts_workers_that_join_over_tls(tmp_path, external_cluster_factory):
    """Run the job script's body with bash: the workers it starts join our TLS scheduler."""
    certs = make_certificates(tmp_path / "tls")
    cluster = external_cluster_factory(n_workers=0, tls_dir=certs.directory)
    cfg = _jobqueue_config(
        certs.directory, cores=1, processes=1, memory="1GiB", interface="lo", job_script_prologue=[],
        local_directory=str(tmp_path / "scratch"), log_directory=None, python=sys.executable, death_timeout=30,
    )
    script = job_script("slurm", cfg, scheduler_address=cluster.address)
    path = tmp_path / "job.sh"
    path.write_text(script)
    # no DASK_CONFIG and no thread variables inherited: only the job script's exports cap threads
    env = {k: v for k, v in os.environ.items() if k not in THREAD_ENV and not k.startswith("DASK_")}
    cluster.spawn(["bash", str(path)], "job", env=env)  # stopped at teardown with the cluster
    with open_client(ClusterOptions(scheduler=cluster.address, tls_dir=str(certs.directory), connect_timeout=60)) as (
        client,
        info,
    ):
        assert info.n_workers == 1 and info.tomo_slots == 1
        (addr, w), = client.scheduler_info(n_workers=-1)["workers"].items()
        assert addr.startswith("tls://127.0.0.1:") and w["nthreads"] == 1 and w["resources"] == {TOMO: 1}
        (rep,) = client.run(worker_thread_report).values()
        assert rep["cv2_threads"] == 1
        started_with = dict(
            item.split("=", 1) for item in open(f"/proc/{rep['pid']}/environ").read().split("\0") if "=" in item
        )
        assert all(started_with.get(v) == THREAD_ENV[v] for v in THREAD_ENV)
        assert client.submit(pow, 2, 10, key="tomography-job-000000", resources={TOMO: 1}).result(timeout=30) == 1024


def test_kubernetes_manifests_match_their_config():
    cfg = load_submit_config(DEPLOY / "kubernetes/schlieren.yaml")
    assert yaml.safe_load((DEPLOY / "kubernetes/daskcluster.yaml").read_text()) == daskcluster_manifest(cfg)
    tls_cfg = copy.deepcopy(cfg)
    tls_cfg["kubernetes"]["tls-secret"] = "schlieren-tls"
    assert yaml.safe_load((DEPLOY / "kubernetes/daskcluster-tls.yaml").read_text()) == daskcluster_manifest(tls_cfg)
    assert render("kubernetes", cfg).startswith("apiVersion: kubernetes.dask.org/v1")


def test_daskcluster_manifest_structure():
    cfg = load_submit_config(DEPLOY / "kubernetes/schlieren.yaml", scale=3)
    m = daskcluster_manifest(cfg)
    assert (m["apiVersion"], m["kind"], m["metadata"]["name"]) == ("kubernetes.dask.org/v1", "DaskCluster", "schlieren")
    worker = m["spec"]["worker"]
    assert worker["replicas"] == 3
    (wc,) = worker["spec"]["containers"]
    args = wc["args"]
    assert args[:2] == ["dask", "worker"] and args[args.index("--resources") + 1] == "TOMO=1"
    assert args[args.index("--nthreads") + 1] == "1" and args[args.index("--memory-limit") + 1] == "8GiB"
    assert wc["resources"]["limits"] == wc["resources"]["requests"] == {"cpu": "1", "memory": "8Gi"}
    env = {e["name"]: e["value"] for e in wc["env"]}
    assert all(env[k] == THREAD_ENV[k] for k in THREAD_ENV) and env["DASK_CONFIG"] == "/opt/schlieren/deploy/config"
    assert wc["securityContext"]["runAsNonRoot"] is True
    sched = m["spec"]["scheduler"]
    assert sched["service"]["type"] == "ClusterIP"
    ports = {p["name"]: p["port"] for p in sched["service"]["ports"]}
    assert ports == {"tcp-comm": 8786, "http-dashboard": 8787}
    assert [v["name"] for v in worker["spec"]["volumes"]] == ["data"] and "--tls-cert" not in args

    cfg["kubernetes"]["tls-secret"] = "schlieren-tls"
    t = daskcluster_manifest(cfg)
    (wc,) = t["spec"]["worker"]["spec"]["containers"]
    (sc,) = t["spec"]["scheduler"]["spec"]["containers"]
    assert "tls://schlieren-scheduler:8786" in wc["args"]
    assert wc["args"][wc["args"].index("--tls-cert") + 1] == "/etc/schlieren/tls/worker.pem"
    assert sc["args"][sc["args"].index("--tls-cert") + 1] == "/etc/schlieren/tls/scheduler.pem"
    assert sc["args"][sc["args"].index("--protocol") + 1] == "tls"
    for pod in (t["spec"]["worker"]["spec"], t["spec"]["scheduler"]["spec"]):
        assert pod["volumes"][0] == {"name": "tls", "secret": {"secretName": "schlieren-tls", "defaultMode": 0o440}}
        assert pod["containers"][0]["volumeMounts"][0]["readOnly"] is True
        assert pod["securityContext"]["fsGroup"] == 10001  # the secret's group: readable by the pods' user
    with pytest.raises(ValueError, match="cannot talk TLS"):
        make_batch_cluster("kubernetes", cfg)
    with pytest.raises(ValueError, match="image"):
        daskcluster_manifest({"kubernetes": {"name": "x"}})


def test_helm_values_cap_threads_and_advertise_tomo():
    values = yaml.safe_load((DEPLOY / "kubernetes/helm-values.yaml").read_text())
    w = values["worker"]
    args = w["extraArgs"]
    assert args[args.index("--resources") + 1] == "TOMO=1" and w["threads_per_worker"] == 1
    env = {e["name"]: e["value"] for e in w["env"]}
    assert env["OPENCV_FOR_THREADS_NUM"] == "1" and env["OMP_NUM_THREADS"] == "1"
    assert w["resources"]["limits"]["memory"] == w["resources"]["requests"]["memory"]
    assert values["scheduler"]["serviceType"] == "ClusterIP" and values["jupyter"]["enabled"] is False


def test_submit_dry_run_and_config_errors(tmp_path, capsys):
    assert cli_main(["submit", "S", "--out", "O", "--cluster", "kubernetes",
                     "--config", str(DEPLOY / "kubernetes/schlieren.yaml"), "--scale", "5", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert yaml.safe_load(out)["spec"]["worker"]["replicas"] == 5

    cfg = _jobqueue_config(None)
    cfg_path = tmp_path / "jq.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg))
    assert cli_main(["submit", "S", "--out", "O", "--cluster", "pbs", "--config", str(cfg_path), "--dry-run"]) == 0
    assert "#PBS -N schlieren-worker" in capsys.readouterr().out

    bad = tmp_path / "bad.yaml"
    bad.write_text("jobqueue: [unclosed\n")
    assert cli_main(["submit", "S", "--out", "O", "--cluster", "slurm", "--config", str(bad), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.yaml line" in err[0]

    evil = tmp_path / "evil.yaml"
    evil.write_text("schlieren: !!python/object/apply:os.system ['echo pwned']\n")
    assert cli_main(["submit", "S", "--out", "O", "--cluster", "slurm", "--config", str(evil), "--dry-run"]) == 2
    assert "evil.yaml" in capsys.readouterr().err

    assert cli_main(["submit", "S", "--out", "O", "--cluster", "slurm", "--config", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml" in capsys.readouterr().err
    k8s_only = tmp_path / "k.yaml"
    k8s_only.write_text("kubernetes: {image: x}\n")
    assert cli_main(["submit", "S", "--out", "O", "--cluster", "slurm", "--config", str(k8s_only), "--dry-run"]) == 2
    assert "no 'jobqueue: slurm:' section" in capsys.readouterr().err
    assert os.environ.get("SCHLIEREN_PWNED") is None


def test_kubernetes_dry_run_without_dask_kubernetes_says_what_to_install(monkeypatch, capsys):
    """The manifest comes from dask-kubernetes' template: without the package, one line."""
    monkeypatch.setitem(sys.modules, "dask_kubernetes.operator", None)  # its import fails
    assert cli_main(["submit", "S", "--out", "O", "--cluster", "kubernetes",
                     "--config", str(DEPLOY / "kubernetes/schlieren.yaml"), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dask-kubernetes is not installed: pip install dask-kubernetes" in err[0]


@pytest.mark.system
@pytest.mark.timeout(120)
def test_submit_runs_the_session_on_the_cluster_it_creates(tiny_session, tmp_path, monkeypatch, capsys):
    """The submit glue: config -> cluster -> client (plugin, TOMO) -> run_session -> exit code.

    A LocalCluster on 127.0.0.1 stands in for the batch system, which is not reachable here.
    """
    from distributed import LocalCluster

    import schlieren.workers.cluster as cluster_mod
    import schlieren.workers.run as run_mod

    made: dict = {}

    def local_batch_cluster(kind, config):
        made.update(kind=kind, scale=schlieren_section(config)["scale"])
        made["cluster"] = LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0",
            resources={TOMO: 1}, memory_limit="1GiB",
        )
        return made["cluster"]

    calls: list = []

    def run_session(session, out, *, client, config, report, on_receipt, **callbacks):
        calls.append((session.name, out, session.frames, callbacks["verify"], callbacks["overwrite"]))
        threads = client.run(worker_thread_report)  # the worker setup plugin was registered
        assert {r["cv2_threads"] for r in threads.values()} == {1}
        value = client.submit(sum, [1, 2, 3], key="tomography-submit-000000", resources={TOMO: 1}).result(timeout=30)
        failures = {} if value == 6 else {"tomography-submit-000000": "wrong"}
        on_receipt({"stage": "tomography", "index": [0], "frame": 2, "seconds": 0.5, "iterations": 7})
        return run_mod.RunSummary(store=str(out), executor="dask", tasks=1, failures=failures)

    monkeypatch.setattr(cluster_mod, "make_batch_cluster", local_batch_cluster)
    monkeypatch.setattr(run_mod, "run_session", run_session)
    cfg = _jobqueue_config(None)
    cfg["schlieren"]["wait-timeout"] = 60
    cfg_path = tmp_path / "jq.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg))
    saved = {k: os.environ.get(k) for k in THREAD_ENV}  # in-process nannies export them here
    try:
        code = cli_main(["submit", str(tiny_session.session), "--out", str(tmp_path / "store"), "--cluster", "slurm",
                         "--config", str(cfg_path), "--scale", "3", "--frames", "5:7", "--no-progress",
                         "--log", str(tmp_path / "run.jsonl"), "--verify"])
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    assert code == 0
    assert made["kind"] == "slurm" and made["scale"] == 3
    name = yaml.safe_load(Path(tiny_session.session).read_text())["name"]
    assert calls == [(name, str(tmp_path / "store"), (5, 7), True, False)]  # --verify reaches the run
    lines = [json.loads(x) for x in (tmp_path / "run.jsonl").read_text().splitlines()]
    assert [x["message"] for x in lines] == ["task receipt", "run finished"]
    assert lines[0]["session"] == name and lines[0]["iterations"] == 7 and lines[0]["frame"] == 2
    assert lines[1]["tasks"] == 1 and lines[1]["failed"] == 0 and lines[1]["executor"] == "dask"
    assert made["cluster"].status.name == "closed"  # submit shuts the cluster down
    err = capsys.readouterr().err
    assert "dashboard: http://127.0.0.1:" in err


# ----------------------------------------------------------------------------------------
# the job watch of SLURM / PBS clusters (its runs against a real SLURM: tests/e2e/test_slurm.py)


def test_batch_job_states_are_read_from_squeue_and_qstat():
    from schlieren.workers.cluster.jobwatch import (NEVER_CLEARS, is_alive, parse_qstat, parse_squeue,
                                                    parse_squeue_reasons, submit_error_line)

    assert parse_squeue("12 RUNNING\n13 PENDING\n14 CANCELLED\n\n") == {"12": "RUNNING", "13": "PENDING",
                                                                       "14": "CANCELLED"}
    listing = "12 RUNNING None\n13 PENDING PartitionConfig\n14 PENDING ReqNodeNotAvail, UnavailableNodes:vm\n"
    assert parse_squeue(listing) == {"12": "RUNNING", "13": "PENDING", "14": "PENDING"}
    assert parse_squeue_reasons(listing) == {"12": "None", "13": "PartitionConfig",
                                             "14": "ReqNodeNotAvail, UnavailableNodes:vm"}
    assert "PartitionConfig" in NEVER_CLEARS and "Resources" not in NEVER_CLEARS and "Priority" not in NEVER_CLEARS
    qstat = ("Job id            Name             User              Time Use S Queue\n"
             "----------------  ---------------- ----------------  -------- - -----\n"
             "1234.pbs01        schlieren-worker alice             00:00:03 R workq\n"
             "1235.pbs01        schlieren-worker alice                    0 Q workq\n")
    assert parse_qstat(qstat) == {"1234": "R", "1235": "Q"}
    assert is_alive("slurm", "RUNNING") and is_alive("slurm", "PENDING")
    assert not any(is_alive("slurm", s) for s in ("COMPLETING", "CANCELLED", "FAILED", "NODE_FAIL", None))
    assert is_alive("pbs", "Q") and not is_alive("pbs", "F") and not is_alive("pbs", "E")
    refused = RuntimeError("Command exited with non-zero exit code.\nExit code: 1\nCommand:\nsbatch /tmp/x.sh\n"
                           "stdout:\n\nstderr:\nsbatch: error: invalid partition specified: compute\n\n")
    assert submit_error_line(refused) == "sbatch: error: invalid partition specified: compute"


def test_workers_are_mapped_to_their_multi_process_job():
    """``<job>-<i>`` names the i-th worker process of job ``<job>`` (dask-jobqueue issue 611)."""
    from schlieren.workers.cluster.jobwatch import WatchedJobs

    cluster = WatchedJobs.__new__(WatchedJobs)
    group = {"group": ["-0", "-1"]}
    cluster.worker_spec = {"SLURMCluster-1": group, "SLURMCluster-10": group}
    cluster.workers = {"SLURMCluster-1": object(), "SLURMCluster-10": object(), "SLURMCluster-2": object()}
    assert cluster.job_of("SLURMCluster-1-1") == "SLURMCluster-1"
    assert cluster.job_of("SLURMCluster-10-0") == "SLURMCluster-10"
    assert cluster.job_of("SLURMCluster-2-0") == "SLURMCluster-2"  # dropped from the plan, still held
    assert cluster.job_of("SLURMCluster-1") is None and cluster.job_of("SLURMCluster-3-0") is None
