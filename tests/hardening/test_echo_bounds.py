"""Input echoed in errors is cut to about 100 characters, on HTTP and gRPC; a long echo over gRPC
stays INVALID_ARGUMENT instead of overflowing the status metadata into RESOURCE_EXHAUSTED."""

from __future__ import annotations

import json

import grpc
import httpx
import pytest

from bench.server import ServiceProcess
from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from tests.conftest import POSE_2D

MAX_ECHO_CHARS = 100  # repnet.core.errors.MAX_ECHO_CHARS, the figure the issue asks for

# Room for the field name, the reason's own words and the list of formats around an echo.
MAX_ITEM_CHARS = MAX_ECHO_CHARS + 300


def check_short(response: httpx.Response, needle: str) -> dict[str, object]:
    assert response.status_code == 422, response.text[:300]
    assert len(response.content) < 4096, len(response.content)
    (item,) = response.json()["detail"]
    for key in ("field", "reason", "message"):
        assert len(item[key]) <= MAX_ITEM_CHARS, (key, item[key][:200])
    assert needle in item["message"], item
    return dict(item)


def test_http_does_not_echo_a_huge_key_or_format(service_process: ServiceProcess) -> None:
    pose = {"keypoints": POSE_2D.tolist()}
    key = "k" * 1_000_000
    response = httpx.post(f"{service_process.url}/lift", json={"poses": [{**pose, key: 1}]}, timeout=60)
    item = check_short(response, "(1000000 characters)")
    assert str(item["field"]).startswith("poses[0].kkkk") and item["reason"].startswith("unknown field")

    fmt = "f" * 3_000_000
    response = httpx.post(f"{service_process.url}/lift", json={"poses": [pose], "format": fmt}, timeout=60)
    item = check_short(response, "(3000000 characters)")
    assert item["field"] == "poses[0].format" and item["code"] == "unknown_format"

    # A request's default format is echoed once per pose that uses it: still one short item each.
    body = json.dumps({"poses": [pose] * 16, "format": fmt})
    response = httpx.post(
        f"{service_process.url}/lift", content=body, headers={"content-type": "application/json"}, timeout=60
    )
    assert response.status_code == 422 and len(response.content) < 16 * 4096, len(response.content)


def test_grpc_unknown_format_is_invalid_argument_with_a_short_message(
    service_process: ServiceProcess,
) -> None:
    fmt = "f" * 20_000
    pose = lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist(), format=fmt)
    with grpc.insecure_channel(service_process.target) as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        with pytest.raises(grpc.RpcError) as refused:
            stub.Lift(lifter_pb2.LiftRequest(poses=[pose]), timeout=30)
        err = refused.value
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT, (err.code(), err.details()[:200])
        assert len(err.details()) <= MAX_ITEM_CHARS and "(20000 characters)" in err.details()

        (result,) = stub.LiftStream(iter([lifter_pb2.LiftFrame(frame_id=7, pose=pose)]), timeout=30)
        assert result.WhichOneof("result") == "error"
        assert result.error.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
        assert len(result.error.message) <= MAX_ITEM_CHARS
        (violation,) = result.error.violations
        assert violation.field == "pose.format" and len(violation.reason) <= MAX_ITEM_CHARS
