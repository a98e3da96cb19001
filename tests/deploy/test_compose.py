"""deploy/compose.yaml, the Prometheus scrape config and the Grafana dashboard agree with the service."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from prometheus_client import CollectorRegistry

from repnet.server.config import Settings
from repnet.server.metrics import Metrics

yaml = pytest.importorskip("yaml", reason="PyYAML is in the dev extra: pip install -e '.[dev]'")

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
DASHBOARD = DEPLOY / "grafana" / "dashboards" / "repnet.json"
SUFFIXES = {"counter": ["_total", "_created"], "histogram": ["_bucket", "_sum", "_count", "_created"],
            "gauge": [""]}  # fmt: skip


def compose() -> dict[str, Any]:
    return yaml.safe_load((DEPLOY / "compose.yaml").read_text())


def dashboard_exprs() -> list[str]:
    panels = json.loads(DASHBOARD.read_text())["panels"]
    return [t["expr"] for p in panels for t in p["targets"]]


def service_series_names() -> set[str]:
    """Every series name the service can expose, from its own Metrics on a fresh registry."""
    registry = CollectorRegistry()
    Metrics(registry)
    return {f.name + s for f in registry.collect() for s in SUFFIXES[f.type]}


def test_compose_publishes_the_service_ports() -> None:
    service = compose()["services"]["repnet"]
    http, grpc = (Settings.model_fields[f].default for f in ("http_port", "grpc_port"))
    assert service["ports"] == [f"{http}:{http}", f"{grpc}:{grpc}"]
    assert (DEPLOY / service["build"]["context"] / service["build"]["dockerfile"]).is_file()


def test_compose_mounts_existing_files() -> None:
    for name, service in compose()["services"].items():
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            assert (DEPLOY / source).exists(), f"{name}: {source} does not exist"


def test_prometheus_scrapes_the_compose_service() -> None:
    config = yaml.safe_load((DEPLOY / "prometheus.yml").read_text())
    [job] = config["scrape_configs"]
    assert job["metrics_path"] == "/metrics"
    http = Settings.model_fields["http_port"].default
    assert job["static_configs"][0]["targets"] == [f"repnet:{http}"]
    assert "repnet" in compose()["services"]


def test_prometheus_config_passes_promtool() -> None:
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool not installed (Debian package prometheus; .ci/run installs it)")
    result = subprocess.run([promtool, "check", "config", str(DEPLOY / "prometheus.yml")],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr


def _datasources(node: Any) -> list[dict[str, Any]]:
    """Every `datasource` reference in the dashboard (panels and their queries)."""
    if isinstance(node, dict):
        found = [node["datasource"]] if isinstance(node.get("datasource"), dict) else []
        return found + [d for value in node.values() for d in _datasources(value)]
    if isinstance(node, list):
        return [d for value in node for d in _datasources(value)]
    return []


def test_dashboard_imports_into_any_grafana_through_a_datasource_variable() -> None:
    """No hard-coded datasource uid: every query uses ${datasource}, a variable of Prometheus data
    sources, which the provisioned (default) Prometheus fills in the compose stack."""
    dashboard = json.loads(DASHBOARD.read_text())
    [variable] = [v for v in dashboard["templating"]["list"] if v["type"] == "datasource"]
    assert variable["name"] == "datasource" and variable["query"] == "prometheus"
    references = _datasources(dashboard["panels"])
    assert len(references) > len(dashboard["panels"])  # the panels and their queries
    assert all(d == {"type": "prometheus", "uid": "${datasource}"} for d in references), references
    provisioned = yaml.safe_load((DEPLOY / "grafana/provisioning/datasources/prometheus.yml").read_text())
    assert [d["type"] for d in provisioned["datasources"] if d.get("isDefault")] == ["prometheus"]


def test_dashboard_covers_latency_throughput_batch_size_and_errors() -> None:
    exprs = " ".join(dashboard_exprs())
    for series in ["repnet_request_duration_seconds_bucket", "repnet_requests_total",
                   "repnet_batch_size_poses_bucket", 'outcome!="ok"']:  # fmt: skip
        assert series in exprs


def test_dashboard_queries_only_metrics_the_service_exposes() -> None:
    known = service_series_names()
    used = {name for expr in dashboard_exprs() for name in re.findall(r"\brepnet_[a-z0-9_]+", expr)}
    assert used, "the dashboard queries no repnet metric"
    assert used <= known, f"unknown series: {sorted(used - known)}"


def test_dashboard_queries_are_valid_promql(tmp_path: Path) -> None:
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool not installed (Debian package prometheus; .ci/run installs it)")
    rules = [{"record": f"repnet:dashboard_query:{i}", "expr": expr.replace("$__rate_interval", "1m")}
             for i, expr in enumerate(dashboard_exprs())]  # fmt: skip
    path = tmp_path / "rules.yml"
    path.write_text(yaml.safe_dump({"groups": [{"name": "dashboard", "rules": rules}]}))
    result = subprocess.run([promtool, "check", "rules", str(path)],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
