"""The deployment files, read as YAML and held against the code: ``docker-compose.yml`` (its ``cluster``
profile) and the Kubernetes manifests under ``deploy/k8s`` (docs/kubernetes.md).

What checks them: the settings they set are ``Settings`` fields (or the detector's own variables: the model,
the model cache) and build valid settings; the model cache the workers read is the one the compose pull step or
the Kubernetes Job fills, with the catalogue's default model; the KEDA triggers
name the ingest streams and consumer group the settings give; the HPA's metric is one ``/metrics`` serves;
what refers to what exists. Schemas: the Kubernetes kinds against the Kubernetes 1.37 JSON schemas (strict:
no unknown field) when ``kubernetes-validate`` is installed (it bundles them, so no network; it is not a
dependency of arcloud, so that case skips without it); the KEDA ScaledObject against ``SCALED_OBJECT``, a
schema of the fields used here written from KEDA's documentation (KEDA's CRD is in no package installable
here); the kustomization rendered by ``kubectl kustomize`` (offline) when kubectl is on PATH."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from arcloud.detectors.catalogue import DEFAULT_MODEL, MODELS_ENV_VAR, catalogue_model
from arcloud.detectors.factory import MODEL_ENV_VAR
from arcloud.service import metrics
from arcloud.service.settings import Settings
from arcloud.stores import keys

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"
KUBERNETES_VERSION = "1.37.0"
#: Manifests applied apart from the kustomization (kubectl apply -f).
APART = {"worker-hpa.yaml", "models-pull-job.yaml"}
#: Variables the detector reads itself (not ``Settings``): the model file, the model cache.
DETECTOR_VARIABLES = {MODEL_ENV_VAR, MODELS_ENV_VAR}


def documents() -> list[tuple[str, dict[str, Any]]]:
    """Every YAML document under deploy/k8s: (file name, document)."""
    found = []
    for path in sorted(K8S.glob("*.yaml")):
        found += [(path.name, doc) for doc in yaml.safe_load_all(path.read_text()) if doc is not None]
    return found


def only(kind: str, name: str | None = None) -> dict[str, Any]:
    (doc,) = [d for _, d in documents() if d["kind"] == kind and (name is None or d["metadata"]["name"] == name)]
    return doc


def container_env(deployment: dict[str, Any]) -> dict[str, str]:
    """The container's settings as the pod sees them: the ConfigMap's, then its own env (secrets as "secret")."""
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    env: dict[str, str] = {}
    for source in container.get("envFrom", []):
        env |= only("ConfigMap", source["configMapRef"]["name"])["data"]
    for item in container.get("env", []):
        value = item.get("value", "secret")
        env[item["name"]] = re.sub(r"\$\((\w+)\)", lambda m: env[m.group(1)], value)  # Kubernetes' $(VAR) expansion
    return env


def settings_of(env: dict[str, str]) -> Settings:
    arcloud = {
        k.removeprefix("ARCLOUD_").lower(): v for k, v in env.items() if k.startswith("ARCLOUD_") and k not in DETECTOR_VARIABLES
    }
    unknown = set(arcloud) - set(Settings.model_fields)
    assert not unknown, f"not settings: {unknown}"
    return Settings(**arcloud)


# --- Kubernetes ----------------------------------------------------------------------------------------
def test_every_manifest_is_named_and_listed_in_the_kustomization() -> None:
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    assert all((K8S / name).exists() for name in kustomization["resources"])
    assert set(kustomization["resources"]) | {"kustomization.yaml"} | APART == {p.name for p in K8S.glob("*.yaml")}
    for name, doc in documents():
        if doc["kind"] != "Kustomization":
            assert (
                doc["apiVersion"]
                and doc["metadata"]["name"]
                and doc["metadata"]["labels"]["app.kubernetes.io/part-of"] == "arcloud"
            ), name


def test_the_api_and_the_workers_share_their_settings_and_one_number_of_shards() -> None:
    api, worker = only("Deployment", "arcloud-api"), only("Deployment", "arcloud-worker")
    for deployment in (api, worker):
        template = deployment["spec"]["template"]
        assert deployment["spec"]["selector"]["matchLabels"].items() <= template["metadata"]["labels"].items()
    api_settings, worker_settings = settings_of(container_env(api)), settings_of(container_env(worker))
    assert api_settings.workers == 0 and api_settings.store.startswith("redis+cluster://:secret@")
    for field in ("store", "ingest_shards", "consumer_group", "detector", "claim_min_idle_s"):
        assert getattr(api_settings, field) == getattr(worker_settings, field), field
    (container,) = worker["spec"]["template"]["spec"]["containers"]
    assert container["command"] == ["python", "-m", "arcloud.tools.worker"]
    assert container["livenessProbe"]["exec"]["command"][-1] == "--healthcheck"
    assert worker["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] >= 60  # a frame in hand finishes


def test_keda_scales_the_workers_on_every_ingest_stream_of_their_group() -> None:
    scaled, worker = only("ScaledObject"), only("Deployment", "arcloud-worker")
    settings = settings_of(container_env(worker))
    assert scaled["spec"]["scaleTargetRef"]["name"] == worker["metadata"]["name"]
    triggers = scaled["spec"]["triggers"]
    streams = [keys.ingest_stream(keys.shard_tag(k, settings.ingest_shards)) for k in range(settings.ingest_shards)]
    assert [t["metadata"]["stream"] for t in triggers] == streams
    for trigger in triggers:
        assert trigger["type"] == "redis-cluster-streams" and trigger["metadata"]["consumerGroup"] == settings.consumer_group
        assert trigger["metadata"]["passwordFromEnv"] in container_env(worker)  # KEDA reads it from the target's container
    assert scaled["spec"]["minReplicaCount"] >= 1  # the API's /readyz wants a worker's heartbeat


def test_the_hpa_scales_the_workers_on_the_queue_depth_metrics_serves() -> None:
    hpa = only("HorizontalPodAutoscaler")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment", "name": "arcloud-worker"}
    (metric,) = hpa["spec"]["metrics"]
    assert metric["external"]["metric"]["name"] == "arcloud_queue_depth"
    assert '"arcloud_queue_depth"' in Path(metrics.__file__).read_text()


def test_the_workers_read_the_default_model_from_the_cache_the_job_fills() -> None:
    worker, job = only("Deployment", "arcloud-worker"), only("Job", "arcloud-models-pull")
    env, model = container_env(worker), catalogue_model(DEFAULT_MODEL)
    assert settings_of(env).detector == "onnx"  # onnx alone: the default model from the cache
    (container,) = worker["spec"]["template"]["spec"]["containers"]
    (mount,) = container["volumeMounts"]
    (volume,) = worker["spec"]["template"]["spec"]["volumes"]
    assert mount["mountPath"] == env[MODELS_ENV_VAR] and mount["readOnly"] and volume["name"] == mount["name"]
    claim = volume["persistentVolumeClaim"]["claimName"]
    assert "ReadOnlyMany" in only("PersistentVolumeClaim", claim)["spec"]["accessModes"]

    spec = job["spec"]["template"]["spec"]
    (export,), (pull,) = spec["initContainers"], spec["containers"]
    assert " ".join(export["command"]) == model.export_command
    assert pull["command"] == [
        "arcloud", "models", "pull", DEFAULT_MODEL, "--from", f"{export['workingDir']}/{model.exported_file}", "--exported",
    ]  # fmt: skip
    assert container_env(job)[MODELS_ENV_VAR] == env[MODELS_ENV_VAR]
    volumes = {v["name"]: v for v in spec["volumes"]}
    mounts = {m["name"]: m for m in pull["volumeMounts"]}
    (written,) = [m for m in mounts.values() if m["mountPath"] == env[MODELS_ENV_VAR]]
    assert not written.get("readOnly") and volumes[written["name"]]["persistentVolumeClaim"]["claimName"] == claim
    assert "ReadWriteOnce" in only("PersistentVolumeClaim", claim)["spec"]["accessModes"]
    assert {m["mountPath"] for m in export["volumeMounts"]} == {export["workingDir"]}


#: The ScaledObject fields these manifests use, as KEDA's documentation describes them (keda.sh/v1alpha1).
SCALED_OBJECT: dict[str, Any] = {
    "type": "object",
    "required": ["apiVersion", "kind", "metadata", "spec"],
    "properties": {
        "apiVersion": {"const": "keda.sh/v1alpha1"},
        "kind": {"const": "ScaledObject"},
        "metadata": {"type": "object", "required": ["name"]},
        "spec": {
            "type": "object",
            "required": ["scaleTargetRef", "triggers"],
            "additionalProperties": False,
            "properties": {
                "scaleTargetRef": {
                    "type": "object",
                    "required": ["name"],
                    "additionalProperties": False,
                    "properties": {"name": {"type": "string"}, "kind": {"type": "string"}, "apiVersion": {"type": "string"}},
                },
                "minReplicaCount": {"type": "integer", "minimum": 0},
                "maxReplicaCount": {"type": "integer", "minimum": 1},
                "pollingInterval": {"type": "integer", "minimum": 1},
                "cooldownPeriod": {"type": "integer", "minimum": 0},
                "advanced": {
                    "type": "object",
                    "additionalProperties": False,
                    "properties": {
                        "horizontalPodAutoscalerConfig": {"type": "object", "properties": {"behavior": {"type": "object"}}}
                    },
                },
                "triggers": {
                    "type": "array",
                    "minItems": 1,
                    "items": {
                        "type": "object",
                        "required": ["type", "metadata"],
                        "additionalProperties": False,
                        "properties": {
                            "type": {"enum": ["redis-streams", "redis-cluster-streams"]},
                            "metadata": {
                                "type": "object",
                                "required": ["stream"],
                                "additionalProperties": {"type": "string"},  # every value a string, as KEDA wants
                                "propertyNames": {
                                    "enum": [
                                        "address",
                                        "addresses",
                                        "host",
                                        "hosts",
                                        "port",
                                        "ports",
                                        "usernameFromEnv",
                                        "passwordFromEnv",
                                        "stream",
                                        "consumerGroup",
                                        "pendingEntriesCount",
                                        "streamLength",
                                        "lagCount",
                                        "activationLagCount",
                                        "enableTLS",
                                        "unsafeSsl",
                                        "databaseIndex",
                                    ]
                                },
                            },
                            "authenticationRef": {"type": "object", "required": ["name"]},
                        },
                    },
                },
            },
        },
    },
}


def test_the_scaled_object_has_the_shape_keda_documents() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.validate(only("ScaledObject"), SCALED_OBJECT)
    wrong = only("ScaledObject")
    wrong["spec"]["triggers"][0]["metadata"]["streamLength"] = 2  # a number, not a string
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(wrong, SCALED_OBJECT)


@pytest.mark.parametrize("name", sorted(p.name for p in K8S.glob("*.yaml")))
def test_the_kubernetes_kinds_match_the_kubernetes_schemas(name: str) -> None:
    validator = pytest.importorskip(
        "kubernetes_validate", reason="kubernetes-validate (bundled Kubernetes schemas) not installed"
    )
    for doc in yaml.safe_load_all((K8S / name).read_text()):
        if doc["apiVersion"].startswith(("keda.sh/", "kustomize.config.k8s.io/")):
            continue  # not Kubernetes' own kinds: checked above
        validator.validate(doc, KUBERNETES_VERSION, strict=True)


def test_kubectl_renders_the_kustomization() -> None:
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl not on PATH")
    rendered = subprocess.run([kubectl, "kustomize", str(K8S)], capture_output=True, text=True, timeout=60, check=True).stdout
    kinds = sorted(doc["kind"] for doc in yaml.safe_load_all(rendered))
    assert kinds == ["ConfigMap", "Deployment", "Deployment", "PersistentVolumeClaim", "ScaledObject", "Service"]


# --- docker compose ------------------------------------------------------------------------------------
def test_compose_mounts_the_hosts_model_cache_where_the_containers_look_for_it() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    for name in ("api", "worker", "api-cluster", "worker-cluster"):
        service = compose["services"][name]
        (volume,) = service["volumes"]
        host, target, mode = volume.rsplit(":", 2)
        assert host == "${ARCLOUD_MODELS:-~/.cache/arcloud/models}" and mode == "ro", name  # models_dir()'s default
        assert service["environment"][MODELS_ENV_VAR] == target, name
        assert service["environment"]["ARCLOUD_DETECTOR"] == "${ARCLOUD_DETECTOR:-onnx}", name
    header = (ROOT / "docker-compose.yml").read_text().split("\nname:")[0]
    assert f"arcloud models pull {DEFAULT_MODEL} --from FILE" in header


def test_the_compose_cluster_profile_runs_the_service_on_three_primaries() -> None:
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    profiled = {name for name, service in services.items() if "cluster" in service.get("profiles", [])}
    nodes = {"redis-node-1", "redis-node-2", "redis-node-3"}
    assert profiled == nodes | {"redis-cluster-create", "api-cluster", "worker-cluster"}
    assert not any(services[name].get("profiles") for name in ("redis", "api", "worker", "zenoh"))  # the default, as before
    for name in ("api-cluster", "worker-cluster"):
        env = {k: re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", v) for k, v in services[name]["environment"].items()}  # defaults
        settings = settings_of(env)
        assert settings.store.startswith("redis+cluster://") and settings.ingest_shards == 3
        assert {node.split(":")[0] for node in settings.store.removeprefix("redis+cluster://").split(",")} == nodes
        assert services[name]["depends_on"]["redis-cluster-create"] == {"condition": "service_completed_successfully"}
    assert set(services["redis-cluster-create"]["depends_on"]) == nodes
    assert all(f"--cluster-announce-hostname {n}" in " ".join(services[n]["command"]) for n in nodes)
    assert "--cluster-enabled yes" in " ".join(services["redis-node-1"]["command"])
    assert "redis-cli --cluster create" in services["redis-cluster-create"]["command"][0]
