"""deploy/kuberay/rayservice.yaml against the code. No Kubernetes and no Ray cluster here: check that what
the operator, Serve and the kubelet read agrees with itself, with the Dockerfile and README, and with the
settings the application builds from (ServerConfig, ClusterConfig, app.SERVICER_FUNCTIONS)."""

from __future__ import annotations

import dataclasses
import importlib
import re
import shlex
import tomllib
from pathlib import Path, PurePosixPath

import pytest
import yaml

from fmgs.flags import build
from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.config import ServerConfig
from fmgs_wire import DEFAULT_PORT

ROOT = Path(__file__).resolve().parents[2]
MANIFEST = ROOT / "deploy/kuberay/rayservice.yaml"
README = ROOT / "deploy/README.md"
MAX_MESSAGE_ENV = "RAY_SERVE_GRPC_MAX_MESSAGE_SIZE"


# ------------------------------------------------------------------ reading the manifest


def _docs() -> list[dict]:
    return [d for d in yaml.safe_load_all(MANIFEST.read_text()) if d]


def _one(kind: str) -> dict:
    found = [d for d in _docs() if d.get("kind") == kind]
    assert len(found) == 1, f"expected one {kind} in {MANIFEST.name}, found {len(found)}"
    return found[0]


def _cluster() -> dict:
    return _one("RayService")["spec"]["rayClusterConfig"]


def _serve() -> dict:
    text = _one("RayService")["spec"]["serveConfigV2"]
    assert isinstance(text, str), "serveConfigV2 is a string (a YAML document) in the RayService CRD"
    return yaml.safe_load(text)


def _app() -> dict:
    (app,) = _serve()["applications"]
    return app


def _templates() -> dict[str, dict]:
    """Pod template of the head and of each worker group, by group name."""
    c = _cluster()
    out = {"head": c["headGroupSpec"]["template"]}
    for g in c["workerGroupSpecs"]:
        out[g["groupName"]] = g["template"]
    return out


def _pod_specs() -> dict[str, dict]:
    return {name: t["spec"] for name, t in _templates().items()}


def _ray_containers() -> dict[str, dict]:
    """The Ray container of each group (KubeRay runs `ray start` in a pod's first container)."""
    return {name: spec["containers"][0] for name, spec in _pod_specs().items()}


def _server_config() -> ServerConfig:
    cfg = build(ServerConfig, tomllib.loads(_server_toml()), "ConfigMap server.toml")
    cfg.validate()
    return cfg


def _config_path() -> PurePosixPath:
    return PurePosixPath(_app()["args"]["config"])


def _server_toml() -> str:
    cm = _one("ConfigMap")
    name = _config_path().name
    assert name in cm["data"], f"args.config names {name}, which the ConfigMap does not hold"
    return cm["data"][name]


def _cluster_config() -> ClusterConfig:
    fields = {k: v for k, v in _app()["args"].items() if k != "config"}
    cc = build(ClusterConfig, fields, "serveConfigV2 args")
    cc.validate()
    return cc


def _volume(spec: dict, name: str) -> dict:
    (vol,) = [v for v in spec.get("volumes", []) if v["name"] == name]
    return vol


def _mount_of(kind: str) -> dict[str, dict]:
    """Per group: the Ray container's mount of the (single) volume of ``kind`` (configMap, ...)."""
    out = {}
    for group, spec in _pod_specs().items():
        vols = [v["name"] for v in spec.get("volumes", []) if kind in v]
        assert len(vols) == 1, f"{group}: expected one {kind} volume, found {vols}"
        mounts = [m for m in spec["containers"][0].get("volumeMounts", []) if m["name"] == vols[0]]
        assert len(mounts) == 1, f"{group}: the Ray container does not mount the {kind} volume once"
        out[group] = {**mounts[0], "volume": _volume(spec, vols[0])}
    return out


def _quantity(q) -> float:
    """A Kubernetes resource quantity as a number ("500m" -> 0.5, "8Gi" -> 8 * 2**30)."""
    units = {"m": 1e-3, "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12}
    units |= {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40}
    m = re.fullmatch(r"([0-9.]+)([a-zA-Z]*)", str(q))
    assert m and (m.group(2) in units or not m.group(2)), f"not a quantity: {q!r}"
    return float(m.group(1)) * units.get(m.group(2), 1)


def _grpc_port() -> int:
    return _serve()["grpc_options"]["port"]


def _container_port(container: dict, port) -> int:
    """A Service targetPort (number or container port name) resolved against ``container``."""
    if isinstance(port, int):
        return port
    named = [p["containerPort"] for p in container.get("ports", []) if p.get("name") == port]
    assert named, f"{container['name']} has no port named {port!r}"
    return named[0]


# ------------------------------------------------------------------ tests


def test_objects_and_shape():
    kinds = {(d["apiVersion"], d["kind"]) for d in _docs()}
    assert kinds == {("v1", "ConfigMap"), ("ray.io/v1", "RayService"), ("v1", "Service")}
    c = _cluster()
    assert c["headGroupSpec"]["template"]["spec"]["containers"]
    assert len(c["workerGroupSpecs"]) == 1
    w = c["workerGroupSpecs"][0]
    assert 0 <= w["minReplicas"] <= w["replicas"] <= w["maxReplicas"]


def test_serve_config_is_valid_for_the_pinned_ray():
    from ray.serve.schema import ServeDeploySchema

    ServeDeploySchema.model_validate(_serve())
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["ray"]
    pin = next(r for r in extra if r.startswith("ray[serve]==")).split("==")[1]
    assert _cluster()["rayVersion"] == pin, "rayVersion must be the image's Ray (KubeRay picks probes by it)"


def test_application_and_servicer_functions_import():
    from fmgs_server.cluster import app as cluster_app

    a = _app()
    assert a["route_prefix"] == "/" + a["name"]
    module, _, attr = a["import_path"].partition(":")
    builder = getattr(importlib.import_module(module), attr)
    assert callable(builder) and builder is cluster_app.app_builder
    functions = _serve()["grpc_options"]["grpc_servicer_functions"]
    assert functions == cluster_app.SERVICER_FUNCTIONS
    for path in functions:
        module, _, attr = path.rpartition(".")
        assert callable(getattr(importlib.import_module(module), attr)), path


def test_app_builder_builds_from_the_manifest(tmp_path):
    """The application KubeRay would build, from the ConfigMap's TOML and the args (no cluster started)."""
    import ray
    from ray import serve

    from fmgs_server.cluster import app as cluster_app

    toml = tmp_path / _config_path().name
    toml.write_text(_server_toml())
    built = cluster_app.app_builder({**_app()["args"], "config": str(toml)})
    assert isinstance(built, serve.Application)
    assert not ray.is_initialized()


def test_grpc_port_is_exposed_served_and_probed():
    port = _grpc_port()
    assert port == DEFAULT_PORT
    assert _serve()["http_options"]["port"] != port
    containers = _ray_containers()
    for group, c in containers.items():
        assert port in [p["containerPort"] for p in c.get("ports", [])], f"{group} does not expose {port}"
    svc = _one("Service")
    (sp,) = [p for p in svc["spec"]["ports"] if p["port"] == port]
    for group, c in containers.items():
        assert _container_port(c, sp.get("targetPort", sp["port"])) == port, group
    # gRPC probes ask the Serve proxy's port, service "" (the server as a whole).
    probed = []
    for group, c in containers.items():
        for kind in ("readinessProbe", "livenessProbe", "startupProbe"):
            grpc = c.get(kind, {}).get("grpc")
            if grpc is not None:
                assert grpc["port"] == port and grpc.get("service", "") == "", f"{group} {kind}"
                probed.append((group, kind))
    assert any(kind == "readinessProbe" and group != "head" for group, kind in probed)


def test_head_is_not_gated_on_serve():
    """KubeRay submits serveConfigV2 only once the head pod is Ready: a head probe that waits for the
    Serve proxy (which that submission starts) would keep the application from ever deploying."""
    head = _ray_containers()["head"]
    for kind in ("readinessProbe", "startupProbe"):
        probe = head.get(kind) or {}
        assert "grpc" not in probe, f"head {kind} waits for Serve's gRPC proxy"
        ports = {probe.get(k, {}).get("port") for k in ("httpGet", "tcpSocket")} - {None}
        assert not ports & {_grpc_port(), _serve()["http_options"]["port"], "serve", "grpc"}, kind


def test_service_selects_the_serving_ray_pods():
    sel = _one("Service")["spec"]["selector"]
    assert sel.get("ray.io/serve") == "true", "only pods whose proxy may take traffic"
    own = {k: v for k, v in sel.items() if k != "ray.io/serve"}
    assert own
    for group, template in _templates().items():
        labels = template["metadata"]["labels"]
        assert own.items() <= labels.items(), f"the Service does not select the {group} pods"
        # KubeRay's own Services select on these: pod templates must not override them.
        assert not [k for k in labels if k.startswith(("ray.io/", "app.kubernetes.io/"))], group


def test_image_is_the_one_the_readme_builds():
    m = re.search(r"docker build (.+)", README.read_text())
    assert m, "deploy/README.md shows no `docker build`"
    argv = shlex.split(m.group(1))
    tag, context = argv[argv.index("-t") + 1], argv[-1]
    assert (ROOT / context / "Dockerfile").is_file()
    # scripts/image.sh tags fmgs:VERSION-FLAVOUR; the cluster runs the cuda flavour.
    assert "tag=${tag:-fmgs:$version-$flavour}" in (ROOT / "scripts/image.sh").read_text()
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert tag == f"fmgs:{version}-cuda", f"deploy/README.md builds {tag}, image.sh fmgs:{version}-cuda"
    for group, c in _ray_containers().items():
        assert c["image"] == tag, f"{group} runs {c['image']}, the README builds {tag}"
    svc = _one("Service")["metadata"]["name"]
    assert f"port-forward svc/{svc} " in README.read_text()


def test_volume_mounts_reference_declared_volumes():
    for group, spec in _pod_specs().items():
        names = [v["name"] for v in spec.get("volumes", [])]
        assert len(names) == len(set(names)), group
        for c in spec["containers"]:
            for mount in c.get("volumeMounts", []):
                assert mount["name"] in names, f"{group}/{c['name']} mounts undeclared {mount['name']}"


def test_scene_repository_is_the_read_only_claim_at_models():
    cfg = _server_config()
    for group, mount in _mount_of("persistentVolumeClaim").items():
        claim = mount["volume"]["persistentVolumeClaim"]
        assert claim["claimName"] and claim.get("readOnly") is True, group
        assert mount.get("readOnly") is True, group
        assert mount["mountPath"] == str(cfg.models), f"{group} mounts the scenes away from models"


def test_server_settings_suit_serve_and_the_probe():
    cfg = _server_config()
    assert cfg.tls_cert is None, "Serve's gRPC proxy has no TLS (fmgs-server --ray refuses it)"
    assert cfg.health_open, "the kubelet's gRPC probe sends no token"
    assert cfg.port == _grpc_port(), "the port fmgs-server --ray would give Serve's gRPC proxy"
    for group, c in _ray_containers().items():
        env = {e["name"]: e.get("value") for e in c.get("env", [])}
        assert MAX_MESSAGE_ENV in env, f"{group}: the proxy's message limit is unset"
        assert int(env[MAX_MESSAGE_ENV]) >= max(cfg.max_send_bytes, cfg.max_receive_bytes), group


def test_config_file_lies_under_the_configmap_mount():
    cm = _one("ConfigMap")["metadata"]["name"]
    path = _config_path()
    for group, mount in _mount_of("configMap").items():
        assert mount["volume"]["configMap"]["name"] == cm, group
        assert path.parent == PurePosixPath(mount["mountPath"]), f"{group}: {path} is not on the mount"


def test_args_are_cluster_settings():
    args = _app()["args"]
    names = {f.name for f in dataclasses.fields(ClusterConfig)}
    assert set(args) - {"config"} <= names, set(args) - {"config"} - names
    assert set(args) - {"config"}, "no cluster settings given"
    _cluster_config()
    # app_builder does not apply these two: the application's name and the proxy's timeout belong to
    # serveConfigV2 itself.
    assert args.get("app_name", _app()["name"]) == _app()["name"]
    assert "request_timeout_s" not in args, "set grpc_options.request_timeout_s instead"
    assert _serve()["grpc_options"].get("request_timeout_s", 0) > 0, "client deadlines are not forwarded"


@pytest.mark.parametrize("kind", ["requests", "limits"])
def test_every_container_has_resources(kind):
    for group, spec in _pod_specs().items():
        for c in spec["containers"]:
            res = c.get("resources", {}).get(kind, {})
            assert {"cpu", "memory"} <= set(res), f"{group}/{c['name']} lacks {kind}"
    auto = _cluster()["autoscalerOptions"]["resources"][kind]
    assert {"cpu", "memory"} <= set(auto)


def test_workers_hold_the_scene_replicas_asked_for():
    cfg, cc = _server_config(), _cluster_config()
    assert 0 < cfg.workers <= cc.replica_cpus, "workers: compute slots within the CPUs reserved"
    (g,) = _cluster()["workerGroupSpecs"]
    limits = g["template"]["spec"]["containers"][0]["resources"]["limits"]
    gpus = _quantity(limits.get("nvidia.com/gpu", 0))
    if cfg.device == "cuda":
        assert cc.replica_gpus > 0 and gpus > 0, "device cuda needs GPUs for the replicas"
    per_pod = _quantity(limits["cpu"]) // cc.replica_cpus
    if cc.replica_gpus:
        per_pod = min(per_pod, gpus // cc.replica_gpus)
    assert per_pod >= 1, "a worker pod cannot hold one scene replica"
    assert per_pod * g["maxReplicas"] >= cc.max_replicas, "max_replicas does not fit maxReplicas pods"
    if cfg.memory_budget_bytes:
        need = per_pod * (cfg.memory_budget_bytes + cfg.work_memory_bytes)
        assert need < _quantity(limits["memory"]), "scene budgets exceed the worker's memory limit"


def test_replicas_warm_before_traffic_admin_closed_and_proxies_replaced_fast():
    """preload: a scene replica's constructor warms it, and Serve routes to it (and the gRPC readiness
    probe sees SERVING) only after; admin calls closed (Serve's proxy listens on every interface); the
    controller (on the head) checks proxies often enough to replace a lost one within seconds."""
    from fmgs_server.cluster.launch import PROXY_HEALTH_ENV

    cfg = _server_config()
    assert cfg.preload
    assert not cfg.admin_open and cfg.admin_token_file is None
    head = _ray_containers()["head"]
    env = {e["name"]: e.get("value") for e in head.get("env", [])}
    for key, value in PROXY_HEALTH_ENV.items():
        assert env.get(key) == value, f"head: {key} is not {value}"
    assert float(env["RAY_SERVE_PROXY_HEALTH_CHECK_PERIOD_S"]) * 3 <= 5.0
    for group, c in _ray_containers().items():
        if group != "head":
            assert c["readinessProbe"]["grpc"]["port"] == _grpc_port(), group
