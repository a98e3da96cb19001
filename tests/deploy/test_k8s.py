"""Kubernetes manifests in deploy/k8s: schema-valid (offline schemas) and consistent with the service."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

yaml = pytest.importorskip("yaml", reason="PyYAML is in the dev extra: pip install -e '.[dev]'")
kubernetes_validate = pytest.importorskip(
    "kubernetes_validate", reason="kubernetes-validate is in the dev extra: pip install -e '.[dev]'"
)

from repnet.server.config import Settings  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
K8S = ROOT / "deploy" / "k8s"
WITH_MONITOR = K8S / "with-servicemonitor"
# The oldest and the newest Kubernetes whose schemas we check (all bundled with kubernetes-validate).
VERSIONS = ["1.29.0", "1.37.0"]
CRD_KINDS = {"ServiceMonitor"}


def kustomize(folder: Path) -> list[tuple[str, dict[str, Any]]]:
    """(file, object) for every object the kustomization in `folder` gives: its resources (files or
    folders with their own kustomization) and components, as `kubectl kustomize` gathers them."""
    spec = yaml.safe_load((folder / "kustomization.yaml").read_text())
    docs = []
    for entry in [*spec.get("resources", []), *spec.get("components", [])]:
        path = (folder / entry).resolve()
        if path.is_dir():
            docs += kustomize(path)
        else:
            docs += [(str(path.relative_to(K8S)), d) for d in yaml.safe_load_all(path.read_text()) if d]
    return docs


RESOURCES = kustomize(WITH_MONITOR)  # everything, the ServiceMonitor included


def one(kind: str, name: str = "repnet") -> dict[str, Any]:
    found = [d for _, d in RESOURCES if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(found) == 1, f"expected one {kind}/{name}, found {len(found)}"
    return found[0]


def default(setting: str) -> Any:
    """The service's default for a setting (not Settings(), which would read this process's env)."""
    return Settings.model_fields[setting].default


def container() -> dict[str, Any]:
    containers = one("Deployment")["spec"]["template"]["spec"]["containers"]
    assert len(containers) == 1
    return containers[0]


def ports() -> dict[str, int]:
    return {p["name"]: p["containerPort"] for p in container()["ports"]}


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize(
    ("filename", "resource"),
    [r for r in RESOURCES if r[1]["kind"] not in CRD_KINDS],
    ids=lambda v: v if isinstance(v, str) else f"{v['kind']}/{v['metadata']['name']}",
)
def test_manifest_is_valid_against_kubernetes_schema(
    filename: str, resource: dict[str, Any], version: str
) -> None:
    kubernetes_validate.validate(resource, version, strict=True)


def test_validator_rejects_an_unknown_field() -> None:
    broken = yaml.safe_load((K8S / "base" / "deployment.yaml").read_text())
    broken["spec"]["template"]["spec"]["containers"][0]["readinessprobe"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, VERSIONS[-1], strict=True)


def test_every_manifest_is_listed_in_its_kustomization() -> None:
    for kustomization in K8S.rglob("kustomization.yaml"):
        spec = yaml.safe_load(kustomization.read_text())
        listed = {r for r in spec.get("resources", []) if (kustomization.parent / r).is_file()}
        present = {p.name for p in kustomization.parent.glob("*.yaml")} - {"kustomization.yaml"}
        assert listed == present, kustomization


def test_default_apply_needs_no_prometheus_operator() -> None:
    """`kubectl apply -k deploy/k8s` must work on any cluster: no object of a CRD kind in it."""
    kinds = {doc["kind"] for _, doc in kustomize(K8S)}
    assert kinds == {"Deployment", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget"}


def test_servicemonitor_comes_with_its_overlay_only() -> None:
    default = {(d["kind"], d["metadata"]["name"]) for _, d in kustomize(K8S)}
    overlay = {(d["kind"], d["metadata"]["name"]) for _, d in RESOURCES}
    assert overlay - default == {("ServiceMonitor", "repnet")}
    component = yaml.safe_load((K8S / "components/servicemonitor/kustomization.yaml").read_text())
    assert component["kind"] == "Component"


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl is not installed")
@pytest.mark.parametrize("folder", [K8S, WITH_MONITOR], ids=["default", "with-servicemonitor"])
def test_kubectl_builds_each_kustomization_as_read_here(folder: Path) -> None:
    built = subprocess.run(["kubectl", "kustomize", str(folder)], capture_output=True, text=True,
                           timeout=60, check=True).stdout  # fmt: skip
    got = sorted((d["kind"], d["metadata"]["name"]) for d in yaml.safe_load_all(built) if d)
    assert got == sorted((d["kind"], d["metadata"]["name"]) for _, d in kustomize(folder))


def test_the_docs_say_how_to_get_the_image_into_a_cluster() -> None:
    """The Deployment runs an image no registry has: docs/API.md ("Container and deployment", linked
    from the README) must say how to push or load it."""
    image = container()["image"]
    readme = (ROOT / "docs" / "API.md").read_text()
    commands = [
        f"docker push registry.example.com/{image}",
        f"kind load docker-image {image}",
        f"minikube image load {image}",
        "kubectl apply -k deploy/k8s/with-servicemonitor",
    ]
    for command in commands:
        assert command in readme, command
    assert "kustomize edit set image" in readme  # pointing the Deployment at a pushed image


def test_ports_match_service_defaults_and_dockerfile() -> None:
    assert ports() == {"http": default("http_port"), "grpc": default("grpc_port")}
    exposed = re.search(r"^EXPOSE (.+)$", (ROOT / "Dockerfile").read_text(), re.MULTILINE)
    assert exposed is not None
    assert sorted(int(p) for p in exposed.group(1).split()) == sorted(ports().values())


def test_probes_use_health_endpoints() -> None:
    c = container()
    assert c["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "http"}
    assert c["livenessProbe"]["httpGet"] == {"path": "/healthz", "port": "http"}
    assert c["startupProbe"]["httpGet"]["path"] == "/healthz"


def test_pod_runs_non_root_with_the_image_user_and_bounded_resources() -> None:
    pod = one("Deployment")["spec"]["template"]["spec"]
    user = re.search(r"^USER (\d+):(\d+)$", (ROOT / "Dockerfile").read_text(), re.MULTILINE)
    assert user is not None
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert pod["securityContext"]["runAsUser"] == int(user.group(1))
    assert pod["securityContext"]["runAsGroup"] == int(user.group(2))
    sc = container()["securityContext"]
    assert sc["allowPrivilegeEscalation"] is False and sc["capabilities"]["drop"] == ["ALL"]
    resources = container()["resources"]
    assert {"cpu", "memory"} <= set(resources["requests"]) and {"cpu", "memory"} <= set(resources["limits"])


def test_graceful_termination_fits_in_the_grace_period() -> None:
    pod = one("Deployment")["spec"]["template"]["spec"]
    pre_stop = container()["lifecycle"]["preStop"]["exec"]["command"]
    assert pre_stop[0] == "sleep"
    env = {e["name"]: e.get("value") for e in container()["env"]}
    drain = float(env.get("REPNET_SHUTDOWN_GRACE_S") or default("shutdown_grace_s"))
    assert float(pre_stop[1]) + drain < pod["terminationGracePeriodSeconds"]


def test_workers_follow_the_cpu_limit_with_one_onnxruntime_thread_each() -> None:
    env = {e["name"]: e for e in container()["env"]}
    field = env["REPNET_WORKERS"]["valueFrom"]["resourceFieldRef"]
    assert field["resource"] == "limits.cpu" and field["containerName"] == container()["name"]
    assert env["REPNET_INTRA_OP_THREADS"]["value"] == "1"


def test_env_names_are_real_settings() -> None:
    fields = {f"REPNET_{name.upper()}" for name in Settings.model_fields}
    assert {e["name"] for e in container()["env"]} <= fields


def test_selectors_match_pod_labels() -> None:
    deployment = one("Deployment")
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert deployment["spec"]["selector"]["matchLabels"].items() <= labels.items()
    for _, doc in RESOURCES:
        if doc["kind"] == "Service":
            assert doc["spec"]["selector"].items() <= labels.items()
            for port in doc["spec"]["ports"]:
                assert port["targetPort"] in ports(), f"{doc['metadata']['name']}: {port}"
    assert one("PodDisruptionBudget")["spec"]["selector"]["matchLabels"].items() <= labels.items()
    target = one("HorizontalPodAutoscaler")["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == ("Deployment", deployment["metadata"]["name"])


def test_scrape_annotations_and_service_monitor_point_at_metrics() -> None:
    annotations = one("Deployment")["spec"]["template"]["metadata"]["annotations"]
    assert annotations["prometheus.io/scrape"] == "true"
    assert int(annotations["prometheus.io/port"]) == ports()["http"]
    assert annotations["prometheus.io/path"] == "/metrics"
    # ServiceMonitor is a CRD (Prometheus Operator): no bundled schema, so check its structure.
    monitor = one("ServiceMonitor")
    assert monitor["apiVersion"] == "monitoring.coreos.com/v1"
    service = one("Service")
    assert monitor["spec"]["selector"]["matchLabels"].items() <= service["metadata"]["labels"].items()
    [endpoint] = monitor["spec"]["endpoints"]
    assert endpoint["port"] in {p["name"] for p in service["spec"]["ports"]}
    assert endpoint["path"] == "/metrics"
