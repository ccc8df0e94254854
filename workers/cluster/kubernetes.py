"""Kubernetes through the Dask operator: the ``DaskCluster`` resource of a submit config
(``deploy/kubernetes/schlieren.yaml``) and the ``KubeCluster`` that creates it.

The resource starts from dask-kubernetes' own template (``make_cluster_spec``: scheduler
and worker containers, ports, health probes, the scheduler service) and adds what the
template cannot express, each in a small function: our worker and scheduler command lines
(one thread, ``TOMO``, memory limit, ``dask scheduler`` with its dashboard and TLS),
separate scheduler resources, the "restricted" Pod Security Standard, the volumes (data
and the TLS secret), the service account and the namespace.
"""

from __future__ import annotations

import copy
import json
import re
import secrets
from collections.abc import Callable, Mapping
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
#: keys of the ``kubernetes:`` section (with ``_``)
_KNOWN_KEYS = {
    "name", "image", "workers", "worker_memory", "worker_cpu", "scheduler_memory", "scheduler_cpu",
    "env", "tls_secret", "image_pull_policy", "service_account", "namespace", "volumes", "idle_timeout",
    "run_as_user",
}
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


def _sections(config: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``kubernetes:`` section (keys with ``_``; its name, image and uid checked) and
    the ``schlieren:`` section (:func:`~schlieren.workers.cluster.options.schlieren_section`)."""
    k8s = config.get("kubernetes")
    if not isinstance(k8s, Mapping):
        raise ValueError("the config has no 'kubernetes:' section")
    kc = underscore_keys(k8s)
    unknown = set(kc) - _KNOWN_KEYS
    if unknown:
        raise ValueError(f"unknown key(s) in the 'kubernetes' section: {', '.join(sorted(unknown))}")
    sec = schlieren_section(config)
    name = str(kc.get("name", "schlieren"))
    if not _K8S_NAME.match(name) or len(name) > _MAX_NAME + 7:
        raise ValueError(
            f"kubernetes.name {name!r}: lowercase letters, digits and '-', starting with a letter, at most {_MAX_NAME}"
        )
    if not kc.get("image"):
        raise ValueError("kubernetes.image is required (the image built from deploy/Containerfile)")
    if int(kc.get("run_as_user", IMAGE_UID)) < 1:
        raise ValueError("kubernetes.run-as-user must be a non-root uid (the image's is 10001)")
    return kc, sec


def _make_cluster_spec() -> Callable[..., dict[str, Any]]:
    """dask-kubernetes' ``make_cluster_spec`` (imported when a manifest is made: it loads kr8s)."""
    try:
        from dask_kubernetes.operator import make_cluster_spec
    except ImportError as exc:
        raise RuntimeError(_NOT_INSTALLED) from exc
    return make_cluster_spec


def _requests_are_limits(cpu: str, memory: str) -> dict[str, dict[str, str]]:
    return {"requests": {"cpu": cpu, "memory": memory}, "limits": {"cpu": cpu, "memory": memory}}


def _tls_args(tls_secret: Any, role: str) -> list[str]:
    """``--tls-*`` flags of ``role``, naming the files of the mounted ``tls-secret``."""
    if not tls_secret:
        return []
    return [
        "--tls-ca-file", f"{TLS_MOUNT}/ca.pem",
        "--tls-cert", f"{TLS_MOUNT}/{role}.pem",
        "--tls-key", f"{TLS_MOUNT}/{role}-key.pem",
    ]


def _worker_command(name: str, memory: str, tomo_slots: int, tls_secret: Any) -> list[str]:
    """``dask worker`` with one thread, a memory limit equal to the pod's, ``TOMO`` and TLS
    (the template appends ``--name $(DASK_WORKER_NAME)`` and the dashboard port)."""
    command = ["dask", "worker"]
    if tls_secret:
        # the operator's DASK_SCHEDULER_ADDRESS is tcp://; name the tls:// service address instead
        command.append(f"tls://{name}-scheduler:8786")
    return [
        *command,
        "--nthreads", "1",
        "--memory-limit", memory.replace("Gi", "GiB").replace("Mi", "MiB"),
        "--resources", f"{TOMO}={tomo_slots}",
        *_tls_args(tls_secret, "worker"),
    ]


def _scheduler_args(template_args: list[str], tls_secret: Any) -> list[str]:
    """The template's ``dask-scheduler ARGS`` (a script distributed removed in 2026.6) as
    ``dask scheduler ARGS`` with the dashboard on ``:8787`` and, with a secret, TLS."""
    args = ["dask", "scheduler", *template_args[1:], "--dashboard-address", ":8787"]
    if tls_secret:
        args += ["--protocol", "tls", *_tls_args(tls_secret, "scheduler")]
    return args


def _restrict(pod: dict[str, Any], uid: int) -> None:
    """The "restricted" Pod Security Standard on a pod spec and its containers.

    Pods run as ``uid`` and its gid, with it as ``fsGroup`` (mounted secrets are
    group-readable, mode 0440), ``seccompProfile: RuntimeDefault``; containers drop every
    capability and cannot escalate privileges.
    """
    pod["securityContext"] = {
        "runAsNonRoot": True,
        "runAsUser": uid,
        "runAsGroup": uid,
        "fsGroup": uid,
        # chown a volume only when its root is not yet ours: a store holds millions of chunk files
        "fsGroupChangePolicy": "OnRootMismatch",
        "seccompProfile": {"type": "RuntimeDefault"},
    }
    for container in pod["containers"]:
        container["securityContext"] = {
            "runAsNonRoot": True,
            "allowPrivilegeEscalation": False,
            "capabilities": {"drop": ["ALL"]},
        }


def _mount(pod: dict[str, Any], volumes: list[dict[str, Any]], mounts: list[dict[str, Any]]) -> None:
    """Add ``volumes`` to a pod spec and ``mounts`` to its (only) container, if any."""
    if volumes:
        pod["volumes"] = volumes
    if mounts:
        pod["containers"][0]["volumeMounts"] = mounts


def _tls_volume(tls_secret: Any) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The ``tls-secret`` as (pod volumes, container mounts), read-only at :data:`TLS_MOUNT`."""
    if not tls_secret:
        return [], []
    # 0440 + fsGroup: the kubelet makes the files root:<uid>, readable by the pod's group only
    return (
        [{"name": "tls", "secret": {"secretName": str(tls_secret), "defaultMode": 0o440}}],
        [{"name": "tls", "mountPath": TLS_MOUNT, "readOnly": True}],
    )


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

    Built on dask-kubernetes' ``make_cluster_spec`` (the ``kubernetes`` extra).
    """
    kc, sec = _sections(config)
    name = str(kc.get("name", "schlieren"))
    replicas = int(underscore_keys(config.get("schlieren") or {}).get("scale", kc.get("workers", 2)))
    wmem, smem = str(kc.get("worker_memory", "4Gi")), str(kc.get("scheduler_memory", "2Gi"))
    tls_secret = kc.get("tls_secret")
    data_volumes, data_mounts = _volumes(kc.get("volumes"))
    manifest = _make_cluster_spec()(
        name,
        image=kc["image"],
        n_workers=replicas,
        resources=_requests_are_limits(str(kc.get("worker_cpu", "1")), wmem),
        env={**THREAD_ENV, **{str(k): str(v) for k, v in (kc.get("env") or {}).items()}},
        worker_command=_worker_command(name, wmem, sec["tomo_slots"], tls_secret),
        idle_timeout=int(kc["idle_timeout"]) if kc.get("idle_timeout") is not None else 0,
    )
    worker_pod, scheduler_pod = manifest["spec"]["worker"]["spec"], manifest["spec"]["scheduler"]["spec"]
    (scheduler,) = scheduler_pod["containers"]
    scheduler["args"] = _scheduler_args(scheduler["args"], tls_secret)
    scheduler["resources"] = _requests_are_limits(str(kc.get("scheduler_cpu", "1")), smem)
    tls_volumes, tls_mounts = _tls_volume(tls_secret)
    _mount(worker_pod, tls_volumes + data_volumes, tls_mounts + data_mounts)
    _mount(scheduler_pod, tls_volumes, tls_mounts)  # the scheduler reads no data
    for pod in (worker_pod, scheduler_pod):
        pod["containers"][0]["imagePullPolicy"] = str(kc.get("image_pull_policy", "IfNotPresent"))
        _restrict(pod, int(kc.get("run_as_user", IMAGE_UID)))
        if kc.get("service_account"):
            pod["serviceAccountName"] = str(kc["service_account"])
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
