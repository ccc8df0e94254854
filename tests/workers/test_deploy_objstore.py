"""deploy/kubernetes/objstore.yaml: a cluster with no shared volume, reading and writing a bucket.

Checked against the tools that run it: the Job's command line parses with schlieren's own
CLI parser, the worker and scheduler command lines with distributed's ``dask worker`` /
``dask scheduler`` commands; and against what the recipe promises: no pod mounts anything
but a scratch emptyDir, every pod that touches the bucket gets the credentials Secret as
environment variables, the thread caps are the ones the renderer gives other recipes, the
scheduler is reachable only from its own pods and the run, and the image has s3fs.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "deploy" / "kubernetes" / "objstore.yaml"
SECRET = "schlieren-bucket"


@pytest.fixture(scope="module")
def docs() -> dict[str, dict]:
    return {d["kind"]: d for d in yaml.safe_load_all(RECIPE.read_text())}


def _pods(docs) -> dict[str, dict]:
    spec = docs["DaskCluster"]["spec"]
    return {"worker": spec["worker"]["spec"], "scheduler": spec["scheduler"]["spec"],
            "run": docs["Job"]["spec"]["template"]["spec"]}


def test_the_recipe_holds_a_cluster_its_run_and_a_network_policy(docs):
    assert set(docs) == {"DaskCluster", "Job", "NetworkPolicy"}
    assert docs["DaskCluster"]["apiVersion"] == "kubernetes.dask.org/v1"
    assert {d["metadata"]["namespace"] for d in docs.values()} == {"schlieren"}


def test_no_pod_mounts_shared_storage_and_the_bucket_readers_get_the_secret(docs):
    for role, pod in _pods(docs).items():
        for vol in pod.get("volumes", []):
            assert set(vol) == {"name", "emptyDir"}, f"{role} mounts {vol}"
        (c,) = pod["containers"]
        mounted = {m["name"] for m in c.get("volumeMounts", [])}
        assert mounted <= {v["name"] for v in pod.get("volumes", [])}
        secrets = [e["secretRef"]["name"] for e in c.get("envFrom", [])]
        env = {e["name"]: e.get("value") for e in c.get("env", [])}
        if role == "scheduler":
            assert not secrets  # it never touches the data
        else:
            assert secrets == [SECRET]
            assert env["SCHLIEREN_CACHE_DIR"].startswith(
                next(m["mountPath"] for m in c["volumeMounts"] if m["name"] == "scratch"))
        # no credentials written into the recipe itself
        assert not any(k.startswith("AWS_") for k in env)
        sc = c["securityContext"]
        assert sc["runAsNonRoot"] and not sc["allowPrivilegeEscalation"] and sc["capabilities"]["drop"] == ["ALL"]


def test_workers_get_the_thread_caps_of_the_other_recipes(docs):
    from schlieren.workers.cluster import THREAD_ENV

    (c,) = _pods(docs)["worker"]["containers"]
    env = {e["name"]: e["value"] for e in c["env"]}
    assert {k: env.get(k) for k in THREAD_ENV} == dict(THREAD_ENV)


def test_command_lines_parse_with_the_tools_they_run(docs):
    from distributed.cli.dask_scheduler import main as dask_scheduler
    from distributed.cli.dask_worker import main as dask_worker

    from schlieren.storage import location
    from schlieren.workers.cli import build_parser

    pods = _pods(docs)
    (w,) = pods["worker"]["containers"]
    assert w["args"][:2] == ["dask", "worker"]
    ctx = dask_worker.make_context("dask worker", list(w["args"][2:]))
    assert ctx.params["nthreads"] == 1 and ctx.params["resources"] == "TOMO=1"
    (s,) = pods["scheduler"]["containers"]
    assert s["args"][:2] == ["dask", "scheduler"]
    dask_scheduler.make_context("dask scheduler", list(s["args"][2:]))

    (run,) = pods["run"]["containers"]
    assert run["args"][0] == "schlieren"
    args = build_parser().parse_args(run["args"][1:])
    assert args.func.__module__ == "schlieren.workers.commands.run"
    assert location.is_url(args.session) and location.is_url(args.out)
    name = docs["DaskCluster"]["metadata"]["name"]
    assert args.scheduler == f"tcp://{name}-scheduler:8786"
    assert args.log.startswith("/scratch/")


def test_only_the_cluster_and_its_run_reach_the_scheduler(docs):
    pol = docs["NetworkPolicy"]["spec"]
    name = docs["DaskCluster"]["metadata"]["name"]
    sched_labels = docs["DaskCluster"]["spec"]["scheduler"]["service"]["selector"]
    assert pol["podSelector"]["matchLabels"] == sched_labels
    sources = [f["podSelector"]["matchLabels"] for f in pol["ingress"][0]["from"]]
    job_labels = docs["Job"]["spec"]["template"]["metadata"]["labels"]
    assert sources == [{"dask.org/cluster-name": name}, job_labels]
    assert [p["port"] for p in pol["ingress"][0]["ports"]] == [8786]


def test_the_image_installs_the_s3_extra():
    text = (REPO / "deploy" / "Containerfile").read_text()
    install = next(line for line in text.splitlines() if line.startswith("RUN pip install"))
    extras = install.split("[", 1)[1].split("]", 1)[0].split(",")
    assert "s3" in extras
