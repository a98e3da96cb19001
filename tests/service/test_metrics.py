"""Metrics on a fresh registry per test: names with units, outcomes, rejections, in-flight."""

from __future__ import annotations

import pytest
from prometheus_client import CollectorRegistry, generate_latest

from service.errors import InvalidKeypoints, ModelNotReady, Overloaded, Violation
from service.metrics import Metrics

NAMES = {
    "repnet_requests_total", "repnet_request_duration_seconds", "repnet_rejected_inputs_total",
    "repnet_in_flight_requests", "repnet_open_streams", "repnet_batch_queue_wait_seconds",
    "repnet_inference_seconds", "repnet_batch_size_poses", "repnet_batch_queue_poses", "repnet_model_info",
    "repnet_pose_plausibility_ratio",
}  # fmt: skip


def test_every_metric_is_registered_with_its_unit(registry: CollectorRegistry) -> None:
    Metrics(registry)
    names = {m.name + ("_total" if m.type == "counter" else "") for m in registry.collect()}
    assert names == NAMES
    units = ("_total", "_seconds", "_poses", "_requests", "_streams", "_info", "_ratio")
    assert all(n.endswith(units) for n in names)
    Metrics(CollectorRegistry())  # a second registry: no clash, nothing global


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
    assert 'repnet_model_info{model_id="repnet-h36m-v1",skeleton="h36m17"} 1.0' in text
    assert 'model_id="old"' not in text
