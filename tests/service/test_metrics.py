"""Metrics on a fresh registry per test: names with units, outcomes, rejections, in-flight."""

from __future__ import annotations

import json
import re
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from prometheus_client import CollectorRegistry, generate_latest, multiprocess
from prometheus_client.mmap_dict import MmapedDict, mmap_key

from repnet._proto.repnet.v1 import lifter_pb2_grpc
from repnet.core.errors import InvalidKeypoints, ModelNotReady, Overloaded, Violation
from repnet.server.metrics import Metrics, worker_metrics
from tests.conftest import POSE_2D
from tests.service.invalid_inputs import good, to_proto_request

NAMES = {
    "repnet_requests_total", "repnet_request_duration_seconds", "repnet_rejected_inputs_total",
    "repnet_in_flight_requests", "repnet_open_streams", "repnet_batch_queue_wait_seconds",
    "repnet_inference_seconds", "repnet_batch_size_poses", "repnet_batch_queue_poses", "repnet_model_info",
    "repnet_pose_plausibility_ratio", "repnet_request_parse_seconds", "repnet_idle_streams_closed_total",
    "repnet_model_output_errors_total", "repnet_open_tracks", "repnet_track_state_bytes",
    "repnet_lifted_poses_total",
}  # fmt: skip


def test_every_metric_is_registered_with_its_unit(registry: CollectorRegistry) -> None:
    Metrics(registry)
    names = {m.name + ("_total" if m.type == "counter" else "") for m in registry.collect()}
    assert names == NAMES
    units = ("_total", "_seconds", "_poses", "_requests", "_streams", "_info", "_ratio", "_tracks", "_bytes")
    assert all(n.endswith(units) for n in names)
    Metrics(CollectorRegistry())  # a second registry: no clash, nothing global


def test_every_metric_is_in_the_docs_table(registry: CollectorRegistry) -> None:
    """Issue 31: repnet_open_tracks and repnet_track_state_bytes were served but not documented."""
    Metrics(registry)
    section = (Path(__file__).parents[2] / "docs" / "API.md").read_text().split("## Metrics", 1)[1]
    table = section.split("\n## ", 1)[0]
    documented = set(re.findall(r"^\| `(repnet_[a-z_]+)` \|", table, re.M))
    served = {m.name + ("_total" if m.type == "counter" else "") for m in registry.collect()}
    assert documented == served


def test_track_classifies_outcomes_and_counts_rejections(registry: CollectorRegistry) -> None:
    metrics = Metrics(registry)
    violations = [
        Violation("poses[0].keypoints[1]", "x", "non_finite"),
        Violation("poses[1]", "y", "non_finite"),
        Violation("poses[2].format", "z", "unknown_format"),
    ]
    errors = [
        None,
        InvalidKeypoints(violations),
        Overloaded("full"),
        ModelNotReady("stopping"),
        RuntimeError("bug"),
    ]

    def handle(error: Exception | None) -> None:
        with metrics.track("grpc", "Lift"):
            assert registry.get_sample_value("repnet_in_flight_requests", {"transport": "grpc"}) == 1
            if error:
                raise error

    for error in errors:
        if error is None:
            handle(error)
        else:
            with pytest.raises(type(error)):
                handle(error)
    for outcome in ("ok", "invalid", "overloaded", "unavailable", "error"):
        labels = {"transport": "grpc", "method": "Lift", "outcome": outcome}
        assert registry.get_sample_value("repnet_requests_total", labels) == 1, outcome
        assert registry.get_sample_value("repnet_request_duration_seconds_count", labels) == 1, outcome
    rejected = {"transport": "grpc", "reason": "non_finite"}
    assert registry.get_sample_value("repnet_rejected_inputs_total", rejected) == 1  # once per request
    assert (
        registry.get_sample_value("repnet_rejected_inputs_total", {**rejected, "reason": "unknown_format"})
        == 1
    )
    assert registry.get_sample_value("repnet_in_flight_requests", {"transport": "grpc"}) == 0


def test_model_info_names_the_current_model(registry: CollectorRegistry) -> None:
    metrics = Metrics(registry)
    metrics.set_model("old", "h36m17")
    metrics.set_model("repnet-h36m-v1", "h36m17")
    text = generate_latest(registry).decode()
    assert 'repnet_model_info{default="true",model_id="repnet-h36m-v1",skeleton="h36m17"} 1.0' in text
    assert 'model_id="old"' not in text


def test_parse_histogram_times_each_request_from_its_arrival(
    client: TestClient, stub: lifter_pb2_grpc.PoseLifterStub, registry: CollectorRegistry
) -> None:
    """repnet_request_parse_seconds: valid and rejected HTTP requests and gRPC Lift calls, a slow
    upload included (the time from the request's arrival until its poses are checked)."""

    def count(transport: str) -> float | None:
        return registry.get_sample_value("repnet_request_parse_seconds_count", {"transport": transport})

    assert client.post("/lift", json={"keypoints": POSE_2D.tolist()}).status_code == 200
    assert client.post("/lift", json={"keypoints": [[1.0, 2.0, 3.0, 4.0, 5.0]] * 17}).status_code == 422
    assert count("http") == 2
    body = json.dumps({"keypoints": POSE_2D.tolist()}).encode()

    def slow_upload() -> Iterator[bytes]:
        for start in range(0, len(body), len(body) // 3 + 1):
            time.sleep(0.15)
            yield body[start : start + len(body) // 3 + 1]

    before = registry.get_sample_value("repnet_request_parse_seconds_sum", {"transport": "http"}) or 0.0
    response = client.post("/lift", content=slow_upload(), headers={"content-type": "application/json"})
    assert response.status_code == 200
    after = registry.get_sample_value("repnet_request_parse_seconds_sum", {"transport": "http"}) or 0.0
    assert after - before >= 0.3  # the upload's three pauses
    stub.Lift(to_proto_request({"poses": [good()]}), timeout=10)
    assert count("grpc") == 1


def test_worker_metrics_are_read_past_a_file_a_worker_is_still_creating(tmp_path: Path) -> None:
    """A worker opens its metrics file empty before it sizes it: a scrape (or the supervisor's last
    line) at that moment reads the other files, where prometheus_client's collector failed."""
    written = MmapedDict(str(tmp_path / "counter_101.db"))
    key = mmap_key("repnet_requests", "repnet_requests_total", ["transport"], ["http"], "requests")
    written.write_value(key, 3.0, 0.0)
    written.close()
    (tmp_path / "counter_102.db").touch()  # the starting worker's
    with pytest.raises(struct.error):
        list(multiprocess.MultiProcessCollector(CollectorRegistry(), str(tmp_path)).collect())
    text = generate_latest(worker_metrics(str(tmp_path))).decode()
    assert 'repnet_requests_total{transport="http"} 3.0' in text
