"""deploy/kubernetes/objstore.yaml: a cluster with no shared volume, reading and writing a bucket.

Validated like the other recipes (tests/workers/test_deploy_recipes.py, whose checks are
reused): the DaskCluster against the operator's CRD, every pod and the Job against
Kubernetes' API schemas and the "restricted" Pod Security Standard, the command lines with
the tools they run (``dask worker`` / ``dask scheduler`` and schlieren's own parser), and
networkpolicy.yaml must let exactly this cluster and its run reach the scheduler. And what
the recipe promises: no pod mounts anything but a scratch emptyDir, every pod that touches
the bucket gets the credentials Secret as environment variables (the recipe holds no key),
the workers get the thread caps, and the image has s3fs.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from test_deploy_recipes import (  # noqa: F401 - daskcluster_validator is a fixture
    _admits,
    _crd_errors,
    _docs,
    _k8s_validate,
    _operator_pods,
    _restricted_violations,
    daskcluster_validator,
)

REPO = Path(__file__).resolve().parents[2]
K8S = REPO / "deploy" / "kubernetes"
RECIPE = K8S / "objstore.yaml"
SECRET = "schlieren-bucket"


@pytest.fixture(scope="module")
def docs() -> dict[str, dict]:
    return {d["kind"]: d for d in yaml.safe_load_all(RECIPE.read_text())}


def _pods(docs) -> dict[str, dict]:
    pods = {role: t["spec"] for role, t in _operator_pods(docs["DaskCluster"]).items()}
    return {**pods, "run": docs["Job"]["spec"]["template"]["spec"]}


def test_the_recipe_is_a_valid_cluster_and_job(docs, daskcluster_validator):
    assert set(docs) == {"DaskCluster", "Job"}
    assert {d["metadata"]["namespace"] for d in docs.values()} == {"schlieren"}
    assert _crd_errors(daskcluster_validator, docs["DaskCluster"]) == []
    _k8s_validate(docs["Job"])
    for role, template in _operator_pods(docs["DaskCluster"]).items():
        _k8s_validate({"apiVersion": "v1", "kind": "Pod", "metadata": template["metadata"], "spec": template["spec"]})
    for role, pod in _pods(docs).items():
        assert _restricted_violations(pod) == [], role


def test_no_pod_mounts_shared_storage_and_the_bucket_readers_get_the_secret(docs):
    for role, pod in _pods(docs).items():
        for vol in pod.get("volumes", []):
            assert set(vol) == {"name", "emptyDir"}, f"{role} mounts {vol}"
        (c,) = pod["containers"]
        assert {m["name"] for m in c.get("volumeMounts", [])} <= {v["name"] for v in pod.get("volumes", [])}
        secrets = [e["secretRef"]["name"] for e in c.get("envFrom", [])]
        env = {e["name"]: e.get("value") for e in c.get("env", [])}
        assert not any(k.startswith("AWS_") for k in env)  # no credentials in the recipe itself
        if role == "scheduler":
            assert not secrets  # it never touches the data
            continue
        assert secrets == [SECRET]
        scratch = next(m["mountPath"] for m in c["volumeMounts"] if m["name"] == "scratch")
        assert env["SCHLIEREN_CACHE_DIR"].startswith(scratch + "/")


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
    params = dask_worker.make_context("dask worker", list(w["args"][2:])).params
    assert params["nthreads"] == 1 and params["resources"] == "TOMO=1"
    (s,) = pods["scheduler"]["containers"]
    assert s["args"][:2] == ["dask", "scheduler"]
    dask_scheduler.make_context("dask scheduler", list(s["args"][2:]))

    (run,) = pods["run"]["containers"]
    assert run["args"][0] == "schlieren"
    args = build_parser().parse_args(run["args"][1:])
    assert args.func.__module__ == "schlieren.workers.commands.run"
    assert location.is_url(args.session) and location.is_url(args.out)
    assert args.scheduler == f"tcp://{docs['DaskCluster']['metadata']['name']}-scheduler:8786"


def test_the_network_policies_admit_this_cluster_and_its_run_only(docs):
    policies = _docs(K8S / "networkpolicy.yaml")

    def pod(labels, ns="schlieren"):
        return {"ns": ns, "ns_labels": {"kubernetes.io/metadata.name": ns}, "labels": labels}

    cluster = {role: pod(t["metadata"]["labels"]) for role, t in _operator_pods(docs["DaskCluster"]).items()}
    run = pod(docs["Job"]["spec"]["template"]["metadata"]["labels"])
    stranger = pod({"app": "notebook"})
    assert _admits(policies, cluster["scheduler"], run, 8786)
    assert _admits(policies, cluster["scheduler"], cluster["worker"], 8786)
    assert _admits(policies, cluster["worker"], cluster["scheduler"], 40123)
    assert not _admits(policies, cluster["scheduler"], stranger, 8786)
    assert not _admits(policies, cluster["worker"], run, 40123)


def test_the_image_installs_the_s3_extra():
    text = (REPO / "deploy" / "Containerfile").read_text()
    install = next(line for line in text.splitlines() if line.startswith("RUN pip install"))
    extras = install.split("[", 1)[1].split("]", 1)[0].split(",")
    assert "s3" in extras
