"""A real Prometheus server scrapes the running service; the latency histogram is queried over its API."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.deploy.helpers import STANDING_POSE, RunningService, free_port

PROMETHEUS = shutil.which("prometheus")
# CI sets REQUIRE_PROMETHEUS=1: there a missing binary fails the test instead of skipping it.
REQUIRED = os.environ.get("REQUIRE_PROMETHEUS") == "1"
pytestmark = pytest.mark.skipif(
    PROMETHEUS is None and not REQUIRED,
    reason="prometheus binary not found: apt-get install prometheus (.ci/run installs it)",
)
DASHBOARD = Path(__file__).resolve().parents[2] / "deploy" / "grafana" / "dashboards" / "repnet.json"
LIFTS = 20


@pytest.fixture(scope="module")
def prometheus(running_service: RunningService, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """Prometheus scraping the service every second; yields its base URL."""
    if PROMETHEUS is None:
        pytest.fail("REQUIRE_PROMETHEUS=1 but no prometheus binary on PATH")
    work = tmp_path_factory.mktemp("prometheus")
    target = running_service.http_url.removeprefix("http://")
    config = {"global": {"scrape_interval": "1s", "evaluation_interval": "1s"},
              "scrape_configs": [{"job_name": "repnet", "metrics_path": "/metrics",
                                  "static_configs": [{"targets": [target]}]}]}  # fmt: skip
    (work / "prometheus.yml").write_text(json.dumps(config))  # JSON is YAML
    url = f"http://127.0.0.1:{free_port()}"
    log = (work / "prometheus.log").open("wb")
    process = subprocess.Popen(
        [PROMETHEUS, f"--config.file={work / 'prometheus.yml'}", f"--storage.tsdb.path={work / 'data'}",
         f"--web.listen-address={url.removeprefix('http://')}", "--log.level=warn"],
        stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
    try:
        wait_for(lambda: httpx.get(f"{url}/-/ready", timeout=1).status_code == 200, "Prometheus ready",
                 process, work / "prometheus.log")  # fmt: skip
        yield url
    finally:
        process.terminate()
        process.wait(timeout=30)
        log.close()


def wait_for(check: Any, what: str, process: subprocess.Popen[bytes], log: Path, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(f"prometheus exited with {process.returncode}: {log.read_text()[-2000:]}")
        try:
            if check():
                return
        except httpx.TransportError:
            pass
        time.sleep(0.25)
    pytest.fail(f"timed out waiting for {what}: {log.read_text()[-2000:]}")


def query(url: str, promql: str) -> list[dict[str, Any]]:
    """An instant query through Prometheus's HTTP API; the result vector."""
    reply = httpx.get(f"{url}/api/v1/query", params={"query": promql}, timeout=10)
    body = reply.json()
    assert reply.status_code == 200 and body["status"] == "success", f"{promql}: {body}"
    result: list[dict[str, Any]] = body["data"]["result"]
    return result


def scalar(url: str, promql: str) -> float:
    result = query(url, promql)
    assert len(result) == 1, f"{promql}: expected one series, got {result}"
    return float(result[0]["value"][1])


def send_lifts(service: RunningService, count: int) -> None:
    with httpx.Client(base_url=service.http_url, timeout=10) as client:
        for _ in range(count):
            reply = client.post("/lift", json={"poses": [{"keypoints": STANDING_POSE}]})
            assert reply.status_code == 200, reply.text


def test_prometheus_scrapes_latency_histogram(running_service: RunningService, prometheus: str) -> None:
    send_lifts(running_service, LIFTS)
    count_query = 'sum(repnet_request_duration_seconds_count{transport="http", outcome="ok"})'

    def scraped_all() -> bool:
        result = query(prometheus, count_query)
        return bool(result) and float(result[0]["value"][1]) >= LIFTS

    wait_for(scraped_all, f"a scrape counting {LIFTS} lifts", running_service.process, Path("/dev/null"))
    assert scalar(prometheus, 'up{job="repnet"}') == 1
    assert scalar(prometheus, count_query) == LIFTS
    inf_bucket = 'sum(repnet_request_duration_seconds_bucket{transport="http", outcome="ok", le="+Inf"})'
    assert scalar(prometheus, inf_bucket) == LIFTS

    # A second burst gives the histogram a rate over the last scrapes, hence a quantile.
    time.sleep(1.5)
    send_lifts(running_service, LIFTS)
    wait_for(lambda: scalar(prometheus, count_query) >= 2 * LIFTS, "the second burst",
             running_service.process, Path("/dev/null"))  # fmt: skip
    rate = 'rate(repnet_request_duration_seconds_bucket{transport="http"}[30s])'
    p99 = scalar(prometheus, f"histogram_quantile(0.99, sum by (le) ({rate}))")
    assert math.isfinite(p99) and 0 < p99 < 10, p99
    assert scalar(prometheus, "sum(repnet_inference_seconds_count)") >= 1


def test_dashboard_queries_run_against_real_data(running_service: RunningService, prometheus: str) -> None:
    panels = json.loads(DASHBOARD.read_text())["panels"]
    send_lifts(running_service, 5)
    time.sleep(2)
    empty = []
    for panel in panels:
        for target in panel["targets"]:
            if not query(prometheus, target["expr"].replace("$__rate_interval", "1m")):
                empty.append(f"{panel['title']}: {target['expr']}")
    # Error-only panels are legitimately empty while every request succeeds; the rest must show data.
    assert all("outcome!=" in e or "rejected" in e for e in empty), empty
