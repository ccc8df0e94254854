"""deploy/ recipes read by the tools that drive them, with those tools' own code and schemas.

* DaskCluster manifests: the Dask Kubernetes operator's CRD (``openAPIV3Schema`` shipped in
  the dask-kubernetes package, made strict like ``kubectl apply --validate=strict``), the
  operator's own pod builders (labels, ``DASK_WORKER_NAME``) and ``KubeCluster``'s signature.
* Helm values: rendered by Helm's template engine (helm-python-sdk binds Helm's Go SDK) with
  the dask chart release 2024.1.1 (tests/workers/data, see README.md there).
* Plain Kubernetes objects (NetworkPolicy, Job, the chart's Deployments and Services):
  Kubernetes' API schemas, strict (kubernetes-validate).
* Every command line a recipe passes to ``dask scheduler`` / ``dask worker`` / ``schlieren``:
  parsed by distributed 2026.8's click commands / schlieren's argparse, after the shell or
  Kubernetes expanded it.
* Every mounted secret readable by the pod's user; the "restricted" Pod Security Standard.
"""

from __future__ import annotations

import copy
import hashlib
import importlib.resources
import inspect
import json
import os
import re
import shlex
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from schlieren.workers.cluster import (
    IMAGE_UID,
    THREAD_ENV,
    TOMO,
    daskcluster_manifest,
    job_script,
    jobqueue_cluster,
    jobqueue_kwargs,
    make_batch_cluster,
    schlieren_section,
    unique_cluster_config,
)
from schlieren.workers.cluster.scheduler import _VERSION_PACKAGES
from schlieren.workers.commands.submit import load_submit_config

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
K8S = DEPLOY / "kubernetes"
DATA = Path(__file__).resolve().parent / "data"
CHART = DATA / "dask-2024.1.1.tgz"
#: sha256 of dask-2024.1.1.tgz as published in the chart repository's index.yaml
CHART_DIGEST = "33b5ef503c6cc08a8c6f641d605ff4b993ff25f7b1aa113200f7f73cdc28581e"
KUBE_VERSION = "1.30"  # oldest Kubernetes the recipes target (fsGroupChangePolicy, seccompProfile)


def _docs(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def _k8s_config(**overrides: Any) -> dict:
    cfg = load_submit_config(K8S / "schlieren.yaml")
    cfg["kubernetes"].update(overrides)
    return cfg


# ----------------------------------------------------------------------------------------
# the operator's CRD


def _strict(schema: Any) -> Any:
    """The CRD schema with unknown fields refused (the API server's strict field validation)."""
    if isinstance(schema, dict):
        out = {k: _strict(v) for k, v in schema.items()}
        if (
            "properties" in out
            and "additionalProperties" not in out
            and not out.get("x-kubernetes-preserve-unknown-fields")
        ):
            out["additionalProperties"] = False
        return out
    if isinstance(schema, list):
        return [_strict(v) for v in schema]
    return schema


@pytest.fixture(scope="module")
def daskcluster_validator() -> jsonschema.Draft7Validator:
    crd_file = importlib.resources.files("dask_kubernetes") / (
        "operator/deployment/helm/dask-kubernetes-operator/crds/daskcluster.yaml"
    )
    crd = yaml.safe_load(crd_file.read_text())
    assert crd["spec"]["names"]["kind"] == "DaskCluster"
    (version,) = [v for v in crd["spec"]["versions"] if v["name"] == "v1"]
    schema = _strict(copy.deepcopy(version["schema"]["openAPIV3Schema"]))
    # every object also has apiVersion, kind and metadata (not part of a CRD's schema)
    schema["properties"].update(apiVersion={"type": "string"}, kind={"type": "string"}, metadata={"type": "object"})
    return jsonschema.Draft7Validator(schema)


def _crd_errors(validator: jsonschema.Draft7Validator, manifest: dict) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(manifest)]


def test_shipped_daskcluster_manifests_validate_against_the_operator_crd(daskcluster_validator):
    for name in ("daskcluster.yaml", "daskcluster-tls.yaml"):
        (manifest,) = _docs(K8S / name)
        assert manifest["apiVersion"] == "kubernetes.dask.org/v1" and manifest["kind"] == "DaskCluster"
        assert _crd_errors(daskcluster_validator, manifest) == [], name
    # what `schlieren submit` creates, with every kind of volume a lab may use
    cfg = unique_cluster_config(_k8s_config(volumes=[
        {"name": "data", "mount-path": "/data", "persistentVolumeClaim": {"claimName": "lab"}},
        {"name": "nfs", "mount-path": "/nfs", "read-only": True, "nfs": {"server": "nas", "path": "/export"}},
        {"name": "creds", "mount-path": "/etc/creds", "secret": {"secretName": "s3", "defaultMode": 0o440}},
        {"name": "scratch", "mount-path": "/scratch", "sub-path": "dask", "emptyDir": {"sizeLimit": "20Gi"}},
    ], **{"service-account": "schlieren"}))
    assert _crd_errors(daskcluster_validator, daskcluster_manifest(cfg)) == []


def test_the_strict_crd_refuses_what_the_operator_would_drop(daskcluster_validator):
    """The validation can fail: a misspelt field, a wrong type, a missing worker spec."""
    (manifest,) = _docs(K8S / "daskcluster.yaml")
    typo = copy.deepcopy(manifest)
    typo["spec"]["worker"]["spec"]["containers"][0]["volumeMount"] = []
    assert any("volumeMount" in e for e in _crd_errors(daskcluster_validator, typo))
    wrong = copy.deepcopy(manifest)
    wrong["spec"]["worker"]["replicas"] = "4"
    assert any("replicas" in e for e in _crd_errors(daskcluster_validator, wrong))
    missing = copy.deepcopy(manifest)
    del missing["spec"]["worker"]
    assert any("'worker' is a required property" in e for e in _crd_errors(daskcluster_validator, missing))


def test_manifest_is_the_operator_template_plus_ours():
    """daskcluster_manifest starts from dask-kubernetes' make_cluster_spec: what the template
    gives (ports, probes, service, the worker's operator-set name and dashboard) is kept."""
    from dask_kubernetes.operator import make_cluster_spec

    cfg = _k8s_config()
    m = daskcluster_manifest(cfg)
    t = make_cluster_spec("schlieren", image=cfg["kubernetes"]["image"], n_workers=4, idle_timeout=3600)
    assert m["spec"]["scheduler"]["service"] == t["spec"]["scheduler"]["service"]
    assert (m["spec"]["idleTimeout"], m["spec"]["worker"]["replicas"]) == (3600, 4)
    for role in ("worker", "scheduler"):
        (mc,), (tc,) = m["spec"][role]["spec"]["containers"], t["spec"][role]["spec"]["containers"]
        for key in ("name", "image", "ports", "readinessProbe", "livenessProbe"):
            assert mc.get(key) == tc.get(key), (role, key)
    (mw,), (tw,) = m["spec"]["worker"]["spec"]["containers"], t["spec"]["worker"]["spec"]["containers"]
    assert mw["args"][-5:] == tw["args"][-5:] == ["--name", "$(DASK_WORKER_NAME)", "--dashboard", "--dashboard-address", "8788"]
    # no idle-timeout: the CRD's default, 0 (never)
    cfg["kubernetes"].pop("idle-timeout")
    assert daskcluster_manifest(cfg)["spec"]["idleTimeout"] == 0


def test_kubernetes_volumes_are_mounted_in_every_worker():
    m = daskcluster_manifest(_k8s_config())
    wpod, spod = m["spec"]["worker"]["spec"], m["spec"]["scheduler"]["spec"]
    assert wpod["volumes"] == [{"name": "data", "persistentVolumeClaim": {"claimName": "schlieren-data"}}]
    assert wpod["containers"][0]["volumeMounts"] == [{"name": "data", "mountPath": "/data"}]
    assert "volumes" not in spod  # the scheduler reads no data
    tls = daskcluster_manifest(_k8s_config(**{"tls-secret": "schlieren-tls"}))
    wpod, spod = tls["spec"]["worker"]["spec"], tls["spec"]["scheduler"]["spec"]
    assert [v["name"] for v in wpod["volumes"]] == ["tls", "data"] and [v["name"] for v in spod["volumes"]] == ["tls"]
    assert {x["mountPath"] for x in wpod["containers"][0]["volumeMounts"]} == {"/etc/schlieren/tls", "/data"}

    bad = [
        ([{"name": "data", "persistentVolumeClaim": {"claimName": "x"}}], r"volumes\[0\]\.mount-path"),
        ([{"name": "Data", "mount-path": "/d", "emptyDir": {}}], r"volumes\[0\]\.name"),
        ([{"name": "tls", "mount-path": "/d", "emptyDir": {}}], r"volumes\[0\]\.name"),
        ([{"name": "a", "mount-path": "/d", "emptyDir": {}, "nfs": {"server": "s", "path": "/"}}], "exactly one"),
        ([{"name": "a", "mount-path": "/d"}], "exactly one"),
        ([{"name": "a", "mount-path": "/d", "emptyDir": {}}, {"name": "b", "mount-path": "/d", "emptyDir": {}}],
         r"volumes\[1\]\.mount-path: /d is already mounted"),
        ({"name": "a"}, "must be a list"),
    ]
    for volumes, message in bad:
        with pytest.raises(ValueError, match=message):
            daskcluster_manifest(_k8s_config(volumes=volumes))


# ----------------------------------------------------------------------------------------
# pods as the operator builds them


def _operator_pods(manifest: dict) -> dict[str, dict]:
    """Scheduler and worker pod templates exactly as the operator's controller builds them."""
    from dask_kubernetes.operator.controller import controller

    name = manifest["metadata"]["name"]
    ns = manifest["metadata"].get("namespace", "default")
    sched = controller.build_scheduler_deployment_spec(name, manifest["spec"]["scheduler"]["spec"], {}, {})
    worker = controller.build_worker_deployment_spec(
        f"{name}-default", ns, name, "abc123", manifest["spec"]["worker"]["spec"], {}, {}
    )
    return {"scheduler": sched["spec"]["template"], "worker": worker["spec"]["template"]}


def _expand_k8s(args: list[str], env: list[dict]) -> list[str]:
    """Kubernetes' ``$(VAR)`` expansion of container args from the container's env."""
    values = {e["name"]: e["value"] for e in env if "value" in e}
    return [re.sub(r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)", lambda m: values.get(m.group(1), m.group(0)), a) for a in args]


# ----------------------------------------------------------------------------------------
# distributed's CLI


def _parse_dask(role: str, args: list[str]) -> dict[str, Any]:
    """Parse ``dask <role> ARGS`` with distributed's own click command; return its parameters."""
    import click

    if role == "scheduler":
        from distributed.cli.dask_scheduler import main
    else:
        from distributed.cli.dask_worker import main
    try:
        ctx = main.make_context(f"dask {role}", list(args))
    except click.ClickException as exc:
        raise AssertionError(f"dask {role} {shlex.join(args)}: {exc.format_message()}") from None
    params = dict(ctx.params)
    if role == "worker":
        from dask.utils import parse_bytes, parse_timedelta

        if params.get("memory_limit") not in (None, "auto"):
            assert parse_bytes(params["memory_limit"]) > 2**30, params["memory_limit"]
        for key in ("lifetime", "lifetime_stagger"):
            if params.get(key):
                parse_timedelta(params[key])
    return params


def _resources(params: dict) -> dict[str, float]:
    text = params.get("resources") or ""
    return {k: float(v) for k, v in (item.split("=") for item in text.replace(",", " ").split())}


def _in_secret(args: list[str], mount: str, secret_dir: Path) -> list[str]:
    """Paths below the secret's mount point, read from the files the secret is made of.

    (click checks that TLS files exist.) Every file an argument names must be in the secret.
    """
    out = []
    for a in args:
        if a.startswith(mount + "/"):
            local = secret_dir / a[len(mount) + 1:]
            assert local.is_file(), f"{a} is not in the secret made from {sorted(os.listdir(secret_dir))}"
            a = str(local)
        out.append(a)
    return out


def test_operator_pods_start_valid_dask_commands(tmp_path):
    from schlieren.workers.security import make_certificates

    # the secret: what `schlieren tls init` writes, without the CA key (GUIDE.md section 5)
    certs = make_certificates(tmp_path / "certs").directory
    (certs / "ca-key.pem").unlink()
    for name in ("daskcluster.yaml", "daskcluster-tls.yaml"):
        (manifest,) = _docs(K8S / name)
        pods = _operator_pods(manifest)
        for template in pods.values():
            for c in template["spec"]["containers"]:
                c["args"] = _in_secret(c["args"], "/etc/schlieren/tls", certs)
        (w,) = pods["worker"]["spec"]["containers"]
        args = _expand_k8s(w["args"], w["env"])
        assert args[:2] == ["dask", "worker"]
        p = _parse_dask("worker", args[2:])
        assert p["name"].startswith("schlieren-default-worker-") and p["nthreads"] == 1
        assert _resources(p) == {TOMO: 1.0}
        # no address on the command line: the operator's DASK_SCHEDULER_ADDRESS (click envvar)
        env = {e["name"]: e["value"] for e in w["env"]}
        if "tls" in name:
            assert p["scheduler"] == "tls://schlieren-scheduler:8786" and p["tls_key"].endswith("worker-key.pem")
        else:
            assert p["scheduler"] is None and env["DASK_SCHEDULER_ADDRESS"].startswith("tcp://schlieren-scheduler.")
        (s,) = pods["scheduler"]["spec"]["containers"]
        assert s["args"][:2] == ["dask", "scheduler"]
        sp = _parse_dask("scheduler", s["args"][2:])
        assert sp["dashboard_address"] == ":8787"
        assert sp["protocol"] == ("tls" if "tls" in name else None)


def test_dask_cli_parser_refuses_unknown_flags():
    with pytest.raises(AssertionError, match="No such option"):
        _parse_dask("worker", ["tcp://x:8786", "--nprocs", "2"])
    with pytest.raises(AssertionError, match="No such option"):
        _parse_dask("scheduler", ["--bokeh-port", "8787"])


# ----------------------------------------------------------------------------------------
# security: secrets readable by the pod's user, the restricted Pod Security Standard


def _image_user() -> tuple[int, int]:
    """uid and primary gid of the image's user (deploy/Containerfile: useradd --uid N, USER N)."""
    text = (DEPLOY / "Containerfile").read_text()
    uid = int(re.search(r"useradd[^\n]*--uid (\d+)", text).group(1))
    assert re.findall(r"^USER\s+(\S+)", text, re.M)[-1] == str(uid)
    return uid, uid  # useradd makes a group of the same id


def _process_ids(pod: dict, container: dict) -> tuple[int, set[int]]:
    """uid and groups of the container's process, as the kubelet starts it."""
    img_uid, img_gid = _image_user()
    psc, csc = pod.get("securityContext") or {}, container.get("securityContext") or {}
    uid = csc.get("runAsUser", psc.get("runAsUser", img_uid))
    gid = csc.get("runAsGroup", psc.get("runAsGroup", img_gid if uid == img_uid else 0))
    groups = {gid, *psc.get("supplementalGroups", [])}
    if psc.get("fsGroup") is not None:
        groups.add(psc["fsGroup"])
    return uid, groups


def _secret_files(pod: dict, container: dict) -> list[tuple[str, int, int, int]]:
    """(path, owner uid, group, mode) of every file of every secret volume the container mounts.

    The kubelet writes them root-owned with ``items[].mode`` or ``defaultMode`` (0644 when
    unset); with an ``fsGroup`` it then changes their group to it and adds 0440 (read-only
    volumes: ``SetVolumeOwnership``).
    """
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    out = []
    fs_group = (pod.get("securityContext") or {}).get("fsGroup")
    for mount in container.get("volumeMounts", []):
        vol = volumes[mount["name"]]
        sources = [vol["secret"]] if "secret" in vol else [
            s["secret"] for s in vol.get("projected", {}).get("sources", []) if "secret" in s
        ]
        for src in sources:
            default = src.get("defaultMode", vol.get("projected", {}).get("defaultMode", 0o644))
            items = src.get("items") or [{"path": "*"}]
            for item in items:
                mode, group = item.get("mode", default), 0
                if fs_group is not None:
                    mode, group = mode | 0o440, fs_group
                out.append((f"{mount['mountPath']}/{item['path']}", 0, group, mode))
    return out


def _unreadable_secrets(pod: dict) -> list[str]:
    bad = []
    for c in pod["containers"]:
        uid, groups = _process_ids(pod, c)
        for path, owner, group, mode in _secret_files(pod, c):
            readable = (uid == owner and mode & stat.S_IRUSR) or (group in groups and mode & stat.S_IRGRP) or (
                mode & stat.S_IROTH
            ) or uid == 0
            if not readable:
                bad.append(f"{c['name']}: {path} mode {mode:04o} owner {owner}:{group}, process {uid}:{sorted(groups)}")
    return bad


def _restricted_violations(pod: dict) -> list[str]:
    """Checks of the "restricted" Pod Security Standard (Kubernetes 1.30) that pod specs control."""
    psc = pod.get("securityContext") or {}
    out = []
    allowed_volumes = {"configMap", "csi", "downwardAPI", "emptyDir", "ephemeral", "persistentVolumeClaim",
                       "projected", "secret"}
    for v in pod.get("volumes", []):
        kinds = set(v) - {"name"}
        if not kinds <= allowed_volumes:
            out.append(f"volume {v['name']}: {', '.join(sorted(kinds - allowed_volumes))} not allowed")
    for c in pod["containers"]:
        csc = c.get("securityContext") or {}
        if not csc.get("runAsNonRoot", psc.get("runAsNonRoot")):
            out.append(f"{c['name']}: runAsNonRoot is not true")
        if csc.get("runAsUser", psc.get("runAsUser")) == 0:
            out.append(f"{c['name']}: runs as uid 0")
        if csc.get("allowPrivilegeEscalation") is not False:
            out.append(f"{c['name']}: allowPrivilegeEscalation is not false")
        caps = csc.get("capabilities") or {}
        if "ALL" not in caps.get("drop", []):
            out.append(f"{c['name']}: capabilities.drop lacks ALL")
        if set(caps.get("add", [])) - {"NET_BIND_SERVICE"}:
            out.append(f"{c['name']}: adds capabilities")
        seccomp = (csc.get("seccompProfile") or psc.get("seccompProfile") or {}).get("type")
        if seccomp not in ("RuntimeDefault", "Localhost"):
            out.append(f"{c['name']}: seccompProfile is {seccomp}")
    return out


def test_every_operator_pod_reads_its_secrets_and_is_restricted():
    for name in ("daskcluster.yaml", "daskcluster-tls.yaml"):
        (manifest,) = _docs(K8S / name)
        for role, template in _operator_pods(manifest).items():
            pod = template["spec"]
            assert _unreadable_secrets(pod) == [], (name, role)
            assert _restricted_violations(pod) == [], (name, role)
            assert pod["securityContext"]["runAsUser"] == IMAGE_UID == _image_user()[0]
    (tls,) = _docs(K8S / "daskcluster-tls.yaml")
    files = _secret_files(tls["spec"]["worker"]["spec"], tls["spec"]["worker"]["spec"]["containers"][0])
    assert files == [("/etc/schlieren/tls/*", 0, IMAGE_UID, 0o440)]  # group-readable, not world-readable


def test_secret_and_restricted_checks_catch_the_old_manifest():
    """Mode 0400 root-owned without fsGroup (the manifest before this fix): no pod reads its key."""
    (tls,) = _docs(K8S / "daskcluster-tls.yaml")
    pod = copy.deepcopy(tls["spec"]["worker"]["spec"])
    pod["volumes"][0]["secret"]["defaultMode"] = 0o400
    pod["securityContext"] = {"runAsNonRoot": True}
    pod["containers"][0]["securityContext"] = {"runAsNonRoot": True, "allowPrivilegeEscalation": False}
    assert _unreadable_secrets(pod) == [
        f"worker: /etc/schlieren/tls/* mode 0400 owner 0:0, process {IMAGE_UID}:[{IMAGE_UID}]"
    ]
    assert _restricted_violations(pod) == ["worker: capabilities.drop lacks ALL", "worker: seccompProfile is None"]
    pod["securityContext"]["fsGroup"] = IMAGE_UID  # what the fix relies on: fsGroup makes it 0440 root:10001
    assert _unreadable_secrets(pod) == []
    pod["volumes"].append({"name": "host", "hostPath": {"path": "/"}})
    assert "volume host: hostPath not allowed" in _restricted_violations(pod)


# ----------------------------------------------------------------------------------------
# Kubernetes' own schemas


def _k8s_validate(obj: dict) -> None:
    import kubernetes_validate

    try:
        kubernetes_validate.validate(obj, KUBE_VERSION, strict=True)
    except kubernetes_validate.ValidationError as exc:
        raise AssertionError(f"{obj['kind']} {obj['metadata'].get('name')}: {exc.message} at {list(exc.path)}") from None


def test_plain_kubernetes_objects_validate_against_the_api_schemas():
    docs = _docs(K8S / "networkpolicy.yaml") + _docs(K8S / "run-job.yaml")
    assert {d["kind"] for d in docs} == {"NetworkPolicy", "Job"}
    for d in docs:
        _k8s_validate(d)
    # the DaskCluster pod specs are core PodSpecs too
    for name in ("daskcluster.yaml", "daskcluster-tls.yaml"):
        (manifest,) = _docs(K8S / name)
        for role, template in _operator_pods(manifest).items():
            _k8s_validate({"apiVersion": "v1", "kind": "Pod", "metadata": template["metadata"], "spec": template["spec"]})
    # and the strict schema does refuse a misspelt field
    (job,) = _docs(K8S / "run-job.yaml")
    job["spec"]["template"]["spec"]["securityContext"]["fsGroupPolicy"] = "x"
    with pytest.raises(AssertionError, match="fsGroupPolicy"):
        _k8s_validate(job)


def test_run_job_is_a_valid_schlieren_run_in_a_restricted_pod():
    from schlieren.workers.cli import build_parser

    (job,) = _docs(K8S / "run-job.yaml")
    pod = job["spec"]["template"]["spec"]
    (c,) = pod["containers"]
    assert _restricted_violations(pod) == [] and _unreadable_secrets(pod) == []
    args = _expand_k8s(c["args"], c["env"])
    assert args[0] == "schlieren"
    ns = build_parser().parse_args(args[1:])
    assert (ns.session, ns.out, ns.scheduler) == ("/data/session", "/data/session.zarr", "tcp://schlieren-dask-scheduler:8786")
    assert ns.report == "/data/session.zarr.report.html"
    assert job["spec"]["template"]["metadata"]["labels"]["schlieren.io/client"] == "true"
    assert {m["mountPath"] for m in c["volumeMounts"]} == {"/data"}


# ----------------------------------------------------------------------------------------
# the Helm chart


@pytest.fixture(scope="module")
def helm_rendered() -> dict[str, list[dict]]:
    """deploy/kubernetes/helm-values.yaml rendered by Helm (release `schlieren`, namespace `schlieren`)."""
    helm = pytest.importorskip("helm_python", reason="helm-python-sdk (Helm's engine) has wheels for Linux x86_64 only")
    assert hashlib.sha256(CHART.read_bytes()).hexdigest() == CHART_DIGEST  # the published release, unaltered
    values = yaml.safe_load((K8S / "helm-values.yaml").read_text())
    with helm.Chart.load(str(CHART)) as chart:
        assert (chart.name, chart.version) == ("dask", "2024.1.1")
        files = chart.render(values, name="schlieren", namespace="schlieren")
    out: dict[str, list[dict]] = {}
    for path, text in files.items():
        if path.endswith(".yaml"):
            for doc in yaml.safe_load_all(text):
                if doc:
                    out.setdefault(doc["kind"], []).append(doc)
        else:
            out.setdefault("NOTES", []).append({"text": text})
    return out


def _shim_target(command: str) -> list[str]:
    """What the image's ``dask-scheduler`` / ``dask-worker`` wrapper runs (deploy/bin)."""
    text = (DEPLOY / "bin" / command).read_text()
    (line,) = [ln for ln in text.splitlines() if ln.startswith("exec ")]
    words = shlex.split(line)
    assert words[-1] == "$@"
    return words[1:-1]


def test_helm_chart_renders_our_values_into_valid_objects(helm_rendered):
    kinds = {k: [d["metadata"]["name"] for d in v] for k, v in helm_rendered.items() if k != "NOTES"}
    assert kinds == {
        "Deployment": ["schlieren-dask-scheduler", "schlieren-dask-worker"],
        "Service": ["schlieren-dask-scheduler"],
    }
    for docs in (helm_rendered["Deployment"], helm_rendered["Service"]):
        for d in docs:
            _k8s_validate(d)


def test_helm_pods_run_dask_commands_of_distributed_2026(helm_rendered):
    deps = {d["metadata"]["labels"]["component"]: d for d in helm_rendered["Deployment"]}
    (s,) = deps["scheduler"]["spec"]["template"]["spec"]["containers"]
    (w,) = deps["worker"]["spec"]["template"]["spec"]["containers"]
    # the chart release calls the removed scripts; the image's wrappers turn them into `dask ...`
    assert s["args"][0] == "dask-scheduler" and w["args"][0] == "dask-worker"
    assert _shim_target("dask-scheduler") == ["dask", "scheduler"] and _shim_target("dask-worker") == ["dask", "worker"]
    sp = _parse_dask("scheduler", s["args"][1:])
    assert sp["port"] == "8786" and sp["dashboard_address"] == ":8787"
    wp = _parse_dask("worker", _expand_k8s(w["args"][1:], w.get("env", [])))
    assert wp["scheduler"] == "schlieren-dask-scheduler:8786" and wp["nthreads"] == 1
    assert _resources(wp) == {TOMO: 1.0}
    from dask.utils import parse_bytes

    assert parse_bytes(wp["memory_limit"]) == parse_bytes(w["resources"]["limits"]["memory"]) == 8 * 2**30
    env = {e["name"]: e["value"] for e in w["env"]}
    assert all(env[k] == v for k, v in THREAD_ENV.items()) and env["DASK_CONFIG"] == "/opt/schlieren/deploy/config"
    # the session and store volume
    wpod = deps["worker"]["spec"]["template"]["spec"]
    assert wpod["volumes"][0]["persistentVolumeClaim"]["claimName"] == "schlieren-data"
    assert w["volumeMounts"] == [{"mountPath": "/data", "name": "data"}]


def test_helm_wrappers_run_the_dask_cli(tmp_path):
    """deploy/bin/dask-scheduler and dask-worker, executed, reach distributed's commands."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    for role in ("scheduler", "worker"):
        script = DEPLOY / "bin" / f"dask-{role}"
        assert os.access(script, os.X_OK), script
        out = subprocess.run([str(script), "--help"], env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert "--dashboard-address" in out.stdout and "--tls-key" in out.stdout


def test_helm_pods_are_non_root_with_group_and_seccomp(helm_rendered):
    """The chart has no container securityContext: pod-level settings only ("baseline", not "restricted")."""
    for d in helm_rendered["Deployment"]:
        pod = d["spec"]["template"]["spec"]
        psc = pod["securityContext"]
        assert psc["runAsNonRoot"] is True and psc["runAsUser"] == psc["fsGroup"] == IMAGE_UID
        assert psc["seccompProfile"] == {"type": "RuntimeDefault"}
        assert _unreadable_secrets(pod) == []
        assert all("securityContext" not in c for c in pod["containers"])  # as GUIDE/values say


def test_port_forward_lines_name_a_rendered_service_and_its_ports(helm_rendered):
    """Every `kubectl port-forward svc/...` line of the recipes and GUIDE.md names a real service port."""
    (svc,) = helm_rendered["Service"]
    services = {svc["metadata"]["name"]: {p["port"] for p in svc["spec"]["ports"]}}
    assert services == {"schlieren-dask-scheduler": {8786, 8787}}
    for name in ("daskcluster.yaml", "daskcluster-tls.yaml"):
        (m,) = _docs(K8S / name)
        services[f"{m['metadata']['name']}-scheduler"] = {p["port"] for p in m["spec"]["scheduler"]["service"]["ports"]}
    files = [K8S / "helm-values.yaml", K8S / "schlieren.yaml", DEPLOY / "GUIDE.md"]
    commands = [m.group(0) for f in files for m in re.finditer(r"kubectl[^`\n#]*port-forward[^`\n#]*", f.read_text())]
    assert any("svc/schlieren-dask-scheduler" in c for c in commands)
    for command in commands:
        words = shlex.split(command)
        target = next(w for w in words if w.startswith("svc/"))
        assert target[4:] in services, command
        forwarded = [w for w in words[words.index(target) + 1:] if re.fullmatch(r"\d+(:\d+)?", w)]
        assert forwarded and all(int(w.split(":")[-1]) in services[target[4:]] for w in forwarded), command
    # the chart's own notes agree
    notes = helm_rendered["NOTES"][0]["text"]
    assert "svc/schlieren-dask-scheduler $DASK_SCHEDULER_UI_PORT:8787" in notes


# ----------------------------------------------------------------------------------------
# NetworkPolicy, evaluated on the pods of both recipes


def _matches(selector: dict, labels: dict) -> bool:
    return all(labels.get(k) == v for k, v in (selector.get("matchLabels") or {}).items())


def _admits(policies: list[dict], dest: dict, src: dict, port: int) -> bool:
    """Whether NetworkPolicy ingress rules let ``src`` reach ``dest`` on TCP ``port``.

    Pods are ``{"ns": ..., "ns_labels": ..., "labels": ...}``.
    """
    selecting = [p for p in policies if p["metadata"]["namespace"] == dest["ns"]
                 and "Ingress" in p["spec"].get("policyTypes", ["Ingress"]) and _matches(p["spec"]["podSelector"], dest["labels"])]
    if not selecting:
        return True
    for p in selecting:
        for rule in p["spec"].get("ingress", []):
            if rule.get("ports") and not any(x.get("port") == port for x in rule["ports"]):
                continue
            for peer in rule.get("from") or [{}]:
                if not peer:
                    return True
                ns_ok = _matches(peer["namespaceSelector"], src["ns_labels"]) if "namespaceSelector" in peer else (
                    src["ns"] == p["metadata"]["namespace"]
                )
                pod_ok = _matches(peer["podSelector"], src["labels"]) if "podSelector" in peer else True
                if ns_ok and pod_ok:
                    return True
    return False


def test_network_policies_admit_only_the_cluster_its_clients_and_the_operator(helm_rendered):
    policies = _docs(K8S / "networkpolicy.yaml")

    def pod(labels, ns="schlieren"):
        return {"ns": ns, "ns_labels": {"kubernetes.io/metadata.name": ns}, "labels": labels}

    (manifest,) = _docs(K8S / "daskcluster.yaml")
    op = {role: pod(t["metadata"]["labels"]) for role, t in _operator_pods(manifest).items()}
    deps = {d["metadata"]["labels"]["component"]: d for d in helm_rendered["Deployment"]}
    hl = {role: pod(d["spec"]["template"]["metadata"]["labels"]) for role, d in deps.items()}
    (job,) = _docs(K8S / "run-job.yaml")
    client = pod(job["spec"]["template"]["metadata"]["labels"])
    stranger = pod({"app": "notebook"})
    operator = pod({"app.kubernetes.io/name": "dask-kubernetes-operator"}, ns="dask-operator")
    elsewhere = pod({"dask.org/component": "worker"}, ns="other-lab")

    for cluster in (op, hl):
        for port in (8786, 8787):
            assert _admits(policies, cluster["scheduler"], cluster["worker"], port)
            assert _admits(policies, cluster["scheduler"], client, port)
            assert not _admits(policies, cluster["scheduler"], stranger, port)
            assert not _admits(policies, cluster["scheduler"], elsewhere, port)
        assert not _admits(policies, cluster["scheduler"], cluster["worker"], 22)
        for src, ok in ((cluster["scheduler"], True), (cluster["worker"], True), (client, False), (stranger, False)):
            assert _admits(policies, cluster["worker"], src, 40123) is ok
    assert _admits(policies, op["scheduler"], operator, 8787) and _admits(policies, op["scheduler"], operator, 8786)
    assert not _admits(policies, op["worker"], operator, 40123)
    assert not _admits(policies, client, stranger, 8080)  # default deny covers everything else
    # no policy: everything admitted (what the recipes had before)
    assert _admits([], op["scheduler"], stranger, 8786)


# ----------------------------------------------------------------------------------------
# `schlieren submit --cluster kubernetes`: a new cluster each time, deleted at close


def test_kubecluster_is_created_fresh_and_shut_down(monkeypatch, daskcluster_validator):
    from dask_kubernetes.operator import kubecluster as kc_pkg
    from dask_kubernetes.operator.kubecluster.kubecluster import CreateMode, KubeCluster
    from dask_kubernetes.operator.validation import validate_cluster_name

    import dask_kubernetes.operator as operator_pkg

    made: list[dict] = []

    class Recorder:
        def __init__(self, **kwargs):
            inspect.signature(KubeCluster).bind(**kwargs)  # the real constructor accepts them
            made.append(kwargs)
            self.adapted = None

        def adapt(self, **kw):
            inspect.signature(KubeCluster.adapt).bind(self, **kw)
            self.adapted = kw

    monkeypatch.setattr(operator_pkg, "KubeCluster", Recorder)
    monkeypatch.setattr(kc_pkg, "KubeCluster", Recorder)
    cfg = _k8s_config()
    a = make_batch_cluster("kubernetes", cfg)
    b = make_batch_cluster("kubernetes", cfg)
    names = [m["custom_cluster_spec"]["metadata"]["name"] for m in made]
    assert names[0] != names[1] and all(re.fullmatch(r"schlieren-[0-9a-f]{6}", n) for n in names)
    for kwargs in made:
        validate_cluster_name(kwargs["custom_cluster_spec"]["metadata"]["name"])
        assert kwargs["create_mode"] is CreateMode.CREATE_ONLY and kwargs["shutdown_on_close"] is True
        assert kwargs["namespace"] == "schlieren"
        spec = kwargs["custom_cluster_spec"]
        assert _crd_errors(daskcluster_validator, spec) == []
        assert spec["spec"]["scheduler"]["service"]["selector"]["dask.org/cluster-name"] == spec["metadata"]["name"]
    assert a.adapted is None and b.adapted is None
    cfg["schlieren"]["adapt"] = {"minimum": 1, "maximum": 6}
    assert make_batch_cluster("kubernetes", cfg).adapted == {"minimum": 1, "maximum": 6}
    with pytest.raises(ValueError, match="at most 32"):
        unique_cluster_config(_k8s_config(name="a-very-long-cluster-name-for-a-lab-x"))


# ----------------------------------------------------------------------------------------
# SLURM / PBS: walltime, adapt, interface, $TMPDIR, python


def _jq(kind: str = "slurm", **overrides) -> dict:
    cfg = load_submit_config(DEPLOY / "slurm/jobqueue.yaml")
    cfg["schlieren"].pop("tls", None)
    cfg["jobqueue"][kind].update(overrides)
    return cfg


def test_walltime_needs_a_lifetime_that_ends_before_it():
    for kind in ("slurm", "pbs"):
        job_kw, _ = jobqueue_kwargs(kind, _jq(kind))
        args = job_kw["worker_extra_args"]
        assert args[args.index("--lifetime") + 1] == "110m" and args[args.index("--lifetime-stagger") + 1] == "5m"
    with pytest.raises(ValueError, match=r"jobqueue.slurm.walltime is 02:00:00 but worker-extra-args has no --lifetime"):
        jobqueue_kwargs("slurm", _jq(worker_extra_args=[]))
    with pytest.raises(ValueError, match="must end before the walltime 01:00:00"):
        jobqueue_kwargs("slurm", _jq(walltime="01:00:00"))
    # the batch systems' walltime formats
    ok = {"slurm": ["1-00", "0-02:00", "2:00:00", "150", "1-0:0:0"], "pbs": ["02:00:00", "7200"]}
    bad = {"slurm": ["115", "1:55:00", "0-01"], "pbs": ["6900", "01:55:00", "115:00"]}
    for kind in ok:
        for w in ok[kind]:
            jobqueue_kwargs(kind, _jq(kind, walltime=w))
        for w in bad[kind]:
            with pytest.raises(ValueError, match="must end before"):
                jobqueue_kwargs(kind, _jq(kind, walltime=w))
    jobqueue_kwargs("slurm", _jq(walltime=None, worker_extra_args=[]))  # no walltime: nothing to leave before


def test_adapt_bounds_and_scale_override():
    assert schlieren_section(_jq())["adapt"] == (1, 4)
    assert schlieren_section({"schlieren": {"adapt": {"maximum": 3}}})["adapt"] == (0, 3)
    for bad in ({"minimum": 3, "maximum": 2}, {"maximum": 0}, {"minimum": 1}, {"max": 3}, [1, 2]):
        with pytest.raises(ValueError, match="adapt"):
            schlieren_section({"schlieren": {"adapt": bad}})
    cfg = load_submit_config(DEPLOY / "slurm/jobqueue.yaml", scale=3)
    assert "adapt" not in cfg["schlieren"] and schlieren_section(cfg)["scale"] == 3


@pytest.mark.system
@pytest.mark.timeout(60)
def test_login_node_scheduler_does_not_take_the_workers_interface():
    """interface: ib0 (absent here) is for the workers; the login-node scheduler starts anyway."""
    import psutil

    assert "ib0" not in psutil.net_if_addrs()
    _, cluster_kw = jobqueue_kwargs("slurm", _jq())
    assert cluster_kw["scheduler_options"]["host"] is None and "interface" not in cluster_kw["scheduler_options"]
    # an explicit scheduler interface is kept (here loopback, so the test listens nowhere else)
    cfg = _jq(**{"scheduler-options": {"interface": "lo", "dashboard_address": "127.0.0.1:0"}})
    cfg["schlieren"]["adapt"] = {"minimum": 0, "maximum": 3}
    cluster = make_batch_cluster("slurm", cfg)  # submits nothing: adaptive minimum 0, no tasks
    try:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        assert "--interface ib0" in cluster.job_script()
        adaptive = cluster._adaptive
        assert (adaptive.minimum, adaptive.maximum) == (0, 3 * 8)  # jobs x worker processes per job
    finally:
        cluster.close()
    with pytest.raises(RuntimeError, match="'ib0' is not a valid network interface"):
        # what the recipe did before: the login-node scheduler on the workers' ib0
        jobqueue_cluster("slurm", _jq(**{"scheduler-options": {"interface": "ib0"}})).close()


def _fake_python(bin_dir: Path) -> None:
    """A ``python`` that records its argv (one JSON line per call) instead of starting a worker."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    fake = bin_dir / "python"
    fake.write_text(f"#!{sys.executable}\nimport json, os, sys\n"
                    "open(os.environ['ARGV_LOG'], 'a').write(json.dumps(sys.argv[1:]) + '\\n')\n")
    fake.chmod(0o755)


@pytest.mark.parametrize("kind", ["slurm", "pbs"])
def test_job_script_runs_the_venv_python_with_a_valid_worker_command(kind, tmp_path):
    """The rendered job script, run by bash: activated venv's python, $TMPDIR expanded on the node."""
    home = tmp_path / "home dir"
    venv_bin = home / "schlieren/.venv/bin"
    _fake_python(venv_bin)
    (venv_bin / "activate").write_text(f'export PATH="{venv_bin}:$PATH"\n')  # what `source activate` does
    script = tmp_path / "job.sh"
    script.write_text(job_script(kind, _jq(kind), scheduler_address="tcp://login01:8786"))
    assert re.search(r"^python -m distributed\.cli\.dask_worker ", script.read_text(), re.M)
    log = tmp_path / "argv.jsonl"
    runs = {"set": str(tmp_path / "node scratch"), "empty": "", "unset": None}
    for case, tmpdir in runs.items():
        env = {"HOME": str(home), "PATH": "/usr/bin:/bin", "ARGV_LOG": str(log)}
        if tmpdir is not None:
            env["TMPDIR"] = tmpdir
        done = subprocess.run(["bash", str(script)], env=env, check=True, timeout=60, capture_output=True, text=True)
        # a site without environment modules: the recipe's `module load` line stays quiet
        assert done.stderr == "", done.stderr
    calls = [json.loads(x) for x in log.read_text().splitlines()]
    assert len(calls) == 3 and all(c[:2] == ["-m", "distributed.cli.dask_worker"] for c in calls)
    dirs = []
    for argv in calls:
        p = _parse_dask("worker", argv[2:])
        assert p["scheduler"] == "tcp://login01:8786" and p["nthreads"] == 1 and p["n_workers"] == "8"
        assert p["interface"] == "ib0" and _resources(p) == {TOMO: 1.0} and p["death_timeout"] == "120"
        dirs.append(p["local_directory"])
    assert dirs == [runs["set"], "/tmp", "/tmp"]
    with pytest.raises(ValueError, match=f"jobqueue.{kind}.local-directory: cannot quote"):
        jobqueue_kwargs(kind, _jq(kind, local_directory='$HOME/"x"'))


def test_sbatch_script_runs_valid_commands(tmp_path):
    """deploy/slurm/schlieren.sbatch, executed by bash with stand-ins for dask, srun and schlieren."""
    home = tmp_path / "home"
    venv_bin = home / "schlieren/.venv/bin"
    venv_bin.mkdir(parents=True)
    log = tmp_path / "argv.jsonl"
    recorder = (f"#!{sys.executable}\nimport json, os, sys\n"
                "argv = [os.path.basename(sys.argv[0])] + sys.argv[1:]\n"
                "open(os.environ['ARGV_LOG'], 'a').write(json.dumps(argv) + '\\n')\n"
                "if argv[:2] == ['dask', 'scheduler']:\n"
                "    f = argv[argv.index('--scheduler-file') + 1]\n"
                "    open(f, 'w').write(json.dumps({'address': 'tls://node01:41234'}))\n"
                "if argv[0] == 'schlieren':  # the script stops the (background) workers after the run\n"
                "    import time\n"
                "    for _ in range(200):\n"
                "        if '\"worker\"' in open(os.environ['ARGV_LOG']).read():\n"
                "            break\n"
                "        time.sleep(0.05)\n")
    for name in ("dask", "schlieren"):
        (venv_bin / name).write_text(recorder)
        (venv_bin / name).chmod(0o755)
    (venv_bin / "srun").write_text('#!/bin/sh\nwhile [ "${1#--}" != "$1" ]; do shift; done\nexec "$@"\n')
    (venv_bin / "srun").chmod(0o755)
    (venv_bin / "activate").write_text(f'export PATH="{venv_bin}:{Path(sys.executable).parent}:$PATH"\n')
    tls = tmp_path / "tls"
    tls.mkdir()
    for f in ("ca.pem", "scheduler.pem", "scheduler-key.pem", "worker.pem", "worker-key.pem", "client.pem", "client-key.pem"):
        (tls / f).write_text("x")
    env = {"HOME": str(home), "PATH": "/usr/bin:/bin", "ARGV_LOG": str(log), "SLURM_JOB_ID": "77",
           "SLURM_SUBMIT_DIR": str(tmp_path), "SLURM_MEM_PER_NODE": "65536", "SLURM_NTASKS_PER_NODE": "8"}
    subprocess.run(["bash", str(DEPLOY / "slurm/schlieren.sbatch"), "/lab/s1", "/lab/s1.zarr", str(tls)],
                   env=env, check=True, timeout=60, capture_output=True)
    calls = {tuple(c[:2]): c for c in map(json.loads, log.read_text().splitlines())}
    sp = _parse_dask("scheduler", calls["dask", "scheduler"][2:])
    assert sp["protocol"] == "tls" and sp["dashboard_address"] == "127.0.0.1:8787" and sp["port"] == "0"
    wp = _parse_dask("worker", calls["dask", "worker"][2:])
    assert wp["nthreads"] == 1 and _resources(wp) == {TOMO: 1.0} and wp["tls_key"] == str(tls / "worker-key.pem")
    assert wp["memory_limit"] == f"{65536 * 9 // 10 // 8}MiB" and wp["local_directory"] == "/tmp/dask-77"
    from schlieren.workers.cli import build_parser

    ns = build_parser().parse_args(calls["schlieren", "run"][1:])
    assert (ns.session, ns.out, ns.scheduler, ns.tls) == ("/lab/s1", "/lab/s1.zarr", "tls://node01:41234", str(tls))


def test_guide_dask_commands_parse():
    """Every `dask scheduler` / `dask worker` line of deploy/GUIDE.md is a valid distributed 2026.8 command."""
    found = 0
    for line in (DEPLOY / "GUIDE.md").read_text().splitlines():
        line = line.split("#", 1)[0].strip().strip("`")
        m = re.match(r"dask (scheduler|worker)\b(.*)", line)
        if m:
            _parse_dask(m.group(1), shlex.split(m.group(2)))
            found += 1
    assert found >= 2


# ----------------------------------------------------------------------------------------
# the image: pinned base, pinned packages


def _closure(root: str, extras: set[str]) -> set[str]:
    """Canonical names of ``root[extras]`` and everything it needs, from the installed metadata."""
    from importlib.metadata import PackageNotFoundError, distribution

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    seen: set[str] = set()
    todo = [(root, frozenset(extras))]
    while todo:
        name, ex = todo.pop()
        key = canonicalize_name(name)
        try:
            dist = distribution(name)
        except PackageNotFoundError:
            continue
        if key in seen and not ex:
            continue
        seen.add(key)
        for raw in dist.requires or []:
            req = Requirement(raw)
            envs = [{"extra": e} for e in ex] or [{"extra": ""}]
            if req.marker is None or any(req.marker.evaluate(e) for e in envs):
                todo.append((req.name, frozenset(req.extras)))
    return seen


def _pins(path) -> dict[str, str]:
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins: dict[str, str] = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            req = Requirement(line)
            (spec,) = req.specifier
            assert spec.operator == "==", line
            pins[canonicalize_name(req.name)] = spec.version
    return pins


def test_image_pins_its_base_and_every_package():
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name
    from distributed.versions import required_packages

    text = (DEPLOY / "Containerfile").read_text()
    base = re.search(r"^FROM (\S+)", text, re.M).group(1)
    assert re.fullmatch(r"python:3\.11\.\d+-slim-(bookworm|trixie)(@sha256:[0-9a-f]{64})?", base), base
    assert re.search(r'^RUN pip install --constraint deploy/constraints\.txt "\.\[cluster,s3\]"$', text, re.M)
    assert "COPY deploy/constraints.txt ./deploy/constraints.txt" in text
    assert re.search(r"^COPY deploy/bin/dask-scheduler deploy/bin/dask-worker /usr/local/bin/$", text, re.M)

    pins = _pins(DEPLOY / "constraints.txt")
    # every package of the install is pinned (names from the installed metadata of schlieren[cluster,s3])
    needed = _closure("schlieren", {"cluster", "s3"}) - {"schlieren"}
    assert needed - set(pins) == set(), "regenerate deploy/constraints.txt (see its header)"
    # the version checks' packages in particular, and the pins satisfy pyproject's requirements
    checked = {canonicalize_name(p) for p in [*_VERSION_PACKAGES, *required_packages]} - {"schlieren"}
    assert checked <= set(pins)
    import tomllib

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    for raw in project["dependencies"] + project["optional-dependencies"]["cluster"] + \
            project["optional-dependencies"]["s3"]:
        req = Requirement(raw)
        assert req.specifier.contains(pins[canonicalize_name(req.name)], prereleases=True), raw


def test_dev_pins_cover_the_test_environment_and_agree_with_the_image():
    """deploy/constraints-dev.txt (dev.py's pins) holds every package of
    schlieren[test,cluster,bench], satisfies pyproject's requirements, and pins each package
    the image also pins to the same version (client and workers must match)."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    dev = _pins(DEPLOY / "constraints-dev.txt")
    image = _pins(DEPLOY / "constraints.txt")
    needed = _closure("schlieren", {"test", "cluster", "bench"}) - {"schlieren"}
    assert needed - set(dev) == set(), "regenerate deploy/constraints-dev.txt (see its header)"
    assert {n: (v, dev[n]) for n, v in image.items() if n in dev and dev[n] != v} == {}
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    for raw in project["dependencies"] + extras["test"] + extras["cluster"] + extras["bench"]:
        req = Requirement(raw)
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        assert req.specifier.contains(dev[canonicalize_name(req.name)], prereleases=True), raw


# ----------------------------------------------------------------------------------------
# the local SLURM script and the guide's SLURM section


@pytest.mark.system  # runs deploy/slurm/local/slurm.sh start (it ends at once here, but it is SLURM's script)
@pytest.mark.skipif(os.name != "posix", reason="a bash script")
def test_local_slurm_script_says_in_one_line_why_it_cannot_start(tmp_path):
    """Where SLURM cannot be started (here: not root) slurm.sh exits 3 with one line, which
    tests/e2e/test_slurm.py skips with and .ci/run reports; nothing is started."""
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "id").write_text("#!/bin/sh\necho 1000\n")  # `id -u`: not root
    (fake / "id").chmod(0o755)
    env = dict(os.environ, PATH=f"{fake}:{os.environ.get('PATH', '/usr/bin:/bin')}",
               SCHLIEREN_SLURM_DIR=str(tmp_path / "slurm"))
    p = subprocess.run([str(DEPLOY / "slurm/local/slurm.sh"), "start"], env=env, capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 3, p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and "needs root" in p.stderr, p.stderr
    assert not (tmp_path / "slurm" / "slurm.conf").exists()


def test_guide_names_what_a_slurm_site_edits_and_needs_first():
    guide = (DEPLOY / "GUIDE.md").read_text()
    slurm = guide[guide.index("## 3. SLURM"):guide.index("## 4. PBS")]
    for needed in ("schlieren tls init", "DASK_CONFIG", "`--exclusive`", "one job per node",
                   "deploy/slurm/local/slurm.sh start", "SLURM_CONF", "wait-timeout", "stall-timeout"):
        assert needed in slurm, needed
    assert slurm.index("schlieren tls init") < slurm.index("schlieren submit SESSION"), "certificates first"
