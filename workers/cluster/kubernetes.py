"""Kubernetes through the Dask operator: the ``DaskCluster`` resource of a submit config
(``deploy/kubernetes/schlieren.yaml``) and the ``KubeCluster`` that creates it.
"""

from __future__ import annotations

import copy
import json
import re
import secrets
from collections.abc import Mapping
from typing import Any

from schlieren.workers.cluster.options import schlieren_section, underscore_keys
from schlieren.workers.cluster.settings import THREAD_ENV, TOMO

#: uid/gid of the ``schlieren`` user in the image (deploy/Containerfile); pods run as it.
IMAGE_UID = 10001
#: where a ``tls-secret`` is mounted in the pods
TLS_MOUNT = "/etc/schlieren/tls"
#: Kubernetes names: RFC 1123 labels (DaskCluster names become Service names)
_K8S_NAME = re.compile(r"^[a-z]([-a-z0-9]*[a-z0-9])?$")
#: longest ``kubernetes.name``: it gets a ``-xxxxxx`` suffix per submit, and the operator
#: names worker deployments ``<name>-default-worker-<10 chars>`` (63 at most)
_MAX_NAME = 32
_NOT_INSTALLED = "dask-kubernetes is not installed: pip install dask-kubernetes"


def _volumes(raw: Any) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``kubernetes.volumes`` as (pod volumes, container volumeMounts).

    Each entry is a Kubernetes volume (``name`` and one source such as
    ``persistentVolumeClaim``, ``nfs``, ``secret``, ``csi``) plus ``mount-path`` (required),
    ``read-only`` and ``sub-path``.
    """
    if raw is None:
        return [], []
    if not isinstance(raw, list):
        raise ValueError("kubernetes.volumes must be a list of volumes (name, mount-path and one volume source)")
    volumes, mounts, paths = [], [], set()
    for i, item in enumerate(raw):
        where = f"kubernetes.volumes[{i}]"
        if not isinstance(item, Mapping):
            raise ValueError(f"{where}: expected a mapping with name, mount-path and a volume source")
        entry = {str(k): v for k, v in item.items()}
        name = str(entry.pop("name", ""))
        mount_path = entry.pop("mount-path", entry.pop("mountPath", None))
        read_only = entry.pop("read-only", entry.pop("readOnly", False))
        sub_path = entry.pop("sub-path", entry.pop("subPath", None))
        if not _K8S_NAME.match(name) or name == "tls":
            raise ValueError(f"{where}.name: {name!r} is not a volume name (lowercase letters, digits, '-'; not 'tls')")
        if not isinstance(mount_path, str) or not mount_path.startswith("/"):
            raise ValueError(f"{where}.mount-path: expected an absolute path inside the pods, got {mount_path!r}")
        if mount_path in paths or mount_path.rstrip("/") == TLS_MOUNT:
            raise ValueError(f"{where}.mount-path: {mount_path} is already mounted")
        paths.add(mount_path)
        if len(entry) != 1:
            raise ValueError(
                f"{where}: expected exactly one volume source (persistentVolumeClaim, nfs, secret, ...), "
                f"got {', '.join(sorted(entry)) or 'none'}"
            )
        volumes.append({"name": name, **entry})
        mount: dict[str, Any] = {"name": name, "mountPath": mount_path}
        if read_only:
            mount["readOnly"] = True
        if sub_path:
            mount["subPath"] = str(sub_path)
        mounts.append(mount)
    return volumes, mounts


def daskcluster_manifest(config: Mapping[str, Any]) -> dict[str, Any]:
    """A ``DaskCluster`` resource (Dask Kubernetes operator, ``kubernetes.dask.org/v1``).

    From ``config["kubernetes"]``: ``name``, ``image``, ``workers`` (replicas, overridden
    by ``schlieren.scale``), ``worker-memory`` / ``worker-cpu`` (requests = limits),
    ``scheduler-memory`` / ``scheduler-cpu``, ``env`` (mapping), ``volumes`` (see
    :func:`_volumes`: the session and store, mounted in every worker), ``tls-secret``
    (name of a Secret holding the files of ``schlieren tls init``; with it scheduler and
    workers talk ``tls://`` and mount it read-only at ``/etc/schlieren/tls``),
    ``image-pull-policy``, ``service-account``, ``namespace``, ``idle-timeout`` (seconds
    after which the operator deletes an idle cluster; 0: never), ``run-as-user`` (the
    image's uid, 10001).

    Pods run as that uid and gid with it as ``fsGroup`` (mounted secrets are group-readable,
    mode 0440), ``seccompProfile: RuntimeDefault``, every capability dropped and no
    privilege escalation (the "restricted" Pod Security Standard). Workers run one thread,
    advertise ``TOMO=<tomo-slots>``, get the thread caps as environment variables and a
    memory limit equal to their request.
    """
    k8s = config.get("kubernetes")
    if not isinstance(k8s, Mapping):
        raise ValueError("the config has no 'kubernetes:' section")
    kc = underscore_keys(k8s)
    known = {
        "name", "image", "workers", "worker_memory", "worker_cpu", "scheduler_memory", "scheduler_cpu",
        "env", "tls_secret", "image_pull_policy", "service_account", "namespace", "volumes", "idle_timeout",
        "run_as_user",
    }
    unknown = set(kc) - known
    if unknown:
        raise ValueError(f"unknown key(s) in the 'kubernetes' section: {', '.join(sorted(unknown))}")
    sec = schlieren_section(config)
    name = str(kc.get("name", "schlieren"))
    if not _K8S_NAME.match(name) or len(name) > _MAX_NAME + 7:
        raise ValueError(
            f"kubernetes.name {name!r}: lowercase letters, digits and '-', starting with a letter, at most {_MAX_NAME}"
        )
    image = kc.get("image")
    if not image:
        raise ValueError("kubernetes.image is required (the image built from deploy/Containerfile)")
    raw_sec = underscore_keys(config.get("schlieren") or {})
    replicas = int(raw_sec.get("scale", kc.get("workers", 2)))
    wmem = str(kc.get("worker_memory", "4Gi"))
    wcpu = str(kc.get("worker_cpu", "1"))
    smem = str(kc.get("scheduler_memory", "2Gi"))
    scpu = str(kc.get("scheduler_cpu", "1"))
    env = {**THREAD_ENV, **{str(k): str(v) for k, v in (kc.get("env") or {}).items()}}
    env_list = [{"name": k, "value": v} for k, v in env.items()]
    tls_secret = kc.get("tls_secret")
    pull = str(kc.get("image_pull_policy", "IfNotPresent"))
    uid = int(kc.get("run_as_user", IMAGE_UID))
    if uid < 1:
        raise ValueError("kubernetes.run-as-user must be a non-root uid (the image's is 10001)")
    data_volumes, data_mounts = _volumes(kc.get("volumes"))

    def tls_args(role: str) -> list[str]:
        if not tls_secret:
            return []
        return [
            "--tls-ca-file", f"{TLS_MOUNT}/ca.pem",
            "--tls-cert", f"{TLS_MOUNT}/{role}.pem",
            "--tls-key", f"{TLS_MOUNT}/{role}-key.pem",
        ]

    # 0440 + fsGroup: the kubelet makes the files root:<uid>, readable by the pod's group only
    tls_volumes = [{"name": "tls", "secret": {"secretName": str(tls_secret), "defaultMode": 0o440}}] if tls_secret else []
    tls_mounts = [{"name": "tls", "mountPath": TLS_MOUNT, "readOnly": True}] if tls_secret else []
    pod_security = {
        "runAsNonRoot": True,
        "runAsUser": uid,
        "runAsGroup": uid,
        "fsGroup": uid,
        # chown a volume only when its root is not yet ours: a store holds millions of chunk files
        "fsGroupChangePolicy": "OnRootMismatch",
        "seccompProfile": {"type": "RuntimeDefault"},
    }
    container_security = {
        "runAsNonRoot": True,
        "allowPrivilegeEscalation": False,
        "capabilities": {"drop": ["ALL"]},
    }

    worker_args = ["dask", "worker"]
    if tls_secret:
        # the operator's DASK_SCHEDULER_ADDRESS is tcp://; name the tls:// service address instead
        worker_args.append(f"tls://{name}-scheduler:8786")
    worker_args += [
        "--name", "$(DASK_WORKER_NAME)",
        "--nthreads", "1",
        "--memory-limit", wmem.replace("Gi", "GiB").replace("Mi", "MiB"),
        "--resources", f"{TOMO}={sec['tomo_slots']}",
        "--dashboard-address", "8788",
        *tls_args("worker"),
    ]
    scheduler_args = ["dask", "scheduler", "--host", "0.0.0.0", "--dashboard-address", ":8787"]
    if tls_secret:
        scheduler_args += ["--protocol", "tls", *tls_args("scheduler")]

    def pod(container: dict[str, Any], volumes: list[dict[str, Any]]) -> dict[str, Any]:
        spec: dict[str, Any] = {"securityContext": pod_security, "containers": [container]}
        if volumes:
            spec["volumes"] = volumes
        if kc.get("service_account"):
            spec["serviceAccountName"] = str(kc["service_account"])
        return spec

    worker = {
        "name": "worker",
        "image": image,
        "imagePullPolicy": pull,
        "args": worker_args,
        "env": env_list,
        "resources": {"requests": {"cpu": wcpu, "memory": wmem}, "limits": {"cpu": wcpu, "memory": wmem}},
        "ports": [{"name": "http-dashboard", "containerPort": 8788, "protocol": "TCP"}],
        "securityContext": container_security,
    }
    scheduler = {
        "name": "scheduler",
        "image": image,
        "imagePullPolicy": pull,
        "args": scheduler_args,
        "env": env_list,
        "resources": {"requests": {"cpu": scpu, "memory": smem}, "limits": {"cpu": scpu, "memory": smem}},
        "ports": [
            {"name": "tcp-comm", "containerPort": 8786, "protocol": "TCP"},
            {"name": "http-dashboard", "containerPort": 8787, "protocol": "TCP"},
        ],
        "readinessProbe": {
            "httpGet": {"port": "http-dashboard", "path": "/health"},
            "initialDelaySeconds": 0,
            "periodSeconds": 1,
            "timeoutSeconds": 300,
        },
        "livenessProbe": {"httpGet": {"port": "http-dashboard", "path": "/health"}, "initialDelaySeconds": 15, "periodSeconds": 20},
        "securityContext": container_security,
    }
    if tls_mounts or data_mounts:
        worker["volumeMounts"] = tls_mounts + data_mounts
    if tls_mounts:
        scheduler["volumeMounts"] = tls_mounts
    spec: dict[str, Any] = {}
    if kc.get("idle_timeout") is not None:
        spec["idleTimeout"] = int(kc["idle_timeout"])
    spec["worker"] = {"replicas": replicas, "spec": pod(worker, tls_volumes + data_volumes)}
    spec["scheduler"] = {
        "spec": pod(scheduler, tls_volumes),
        "service": {
            "type": "ClusterIP",
            "selector": {"dask.org/cluster-name": name, "dask.org/component": "scheduler"},
            "ports": [
                {"name": "tcp-comm", "protocol": "TCP", "port": 8786, "targetPort": "tcp-comm"},
                {"name": "http-dashboard", "protocol": "TCP", "port": 8787, "targetPort": "http-dashboard"},
            ],
        },
    }
    manifest: dict[str, Any] = {
        "apiVersion": "kubernetes.dask.org/v1",
        "kind": "DaskCluster",
        "metadata": {"name": name},
        "spec": spec,
    }
    if kc.get("namespace"):
        manifest["metadata"]["namespace"] = str(kc["namespace"])
    return json.loads(json.dumps(manifest))  # no shared sub-objects (YAML anchors when dumped)


def unique_cluster_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """``config`` with ``kubernetes.name`` made unique for one submit (``<name>-<6 hex>``).

    ``schlieren submit`` creates a fresh DaskCluster each time instead of connecting to a
    leftover one of the same name (whose workers may run other code or versions).
    """
    out = copy.deepcopy(dict(config))
    k8s = out.get("kubernetes")
    if not isinstance(k8s, dict):
        raise ValueError("the config has no 'kubernetes:' section")
    base = str(k8s.get("name", "schlieren"))
    if not _K8S_NAME.match(base) or len(base) > _MAX_NAME:
        raise ValueError(
            f"kubernetes.name {base!r}: lowercase letters, digits and '-', starting with a letter, at most {_MAX_NAME}"
        )
    k8s["name"] = f"{base}-{secrets.token_hex(3)}"
    return out


def kube_cluster(config: Mapping[str, Any]) -> Any:
    """A ``dask_kubernetes.operator.KubeCluster`` with :func:`daskcluster_manifest` under a
    name unique to this call (:func:`unique_cluster_config`).

    Created only (never connected to a leftover) and deleted when the cluster object
    closes; adaptive between ``schlieren.adapt``'s bounds when given. A ``tls-secret``
    manifest is refused: the operator's client side speaks plain ``tcp://``.
    """
    sec = schlieren_section(config)
    manifest = daskcluster_manifest(unique_cluster_config(config))
    if underscore_keys(config["kubernetes"]).get("tls_secret"):
        raise ValueError(
            "KubeCluster cannot talk TLS to the scheduler: apply the manifest with kubectl and use "
            "`schlieren run --scheduler tls://...` (deploy/GUIDE.md)"
        )
    try:
        from dask_kubernetes.operator import KubeCluster
        from dask_kubernetes.operator.kubecluster.kubecluster import CreateMode
    except ImportError as exc:
        raise RuntimeError(_NOT_INSTALLED) from exc
    namespace = underscore_keys(config["kubernetes"]).get("namespace")
    # a new cluster every time (never a leftover of the same name), deleted when closed
    cluster = KubeCluster(
        custom_cluster_spec=manifest,
        namespace=namespace,
        create_mode=CreateMode.CREATE_ONLY,
        shutdown_on_close=True,
    )
    if sec["adapt"] is not None:
        cluster.adapt(minimum=sec["adapt"][0], maximum=sec["adapt"][1])
    return cluster
