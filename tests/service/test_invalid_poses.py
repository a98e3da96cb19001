"""`invalid_poses: report` (HTTP POST /lift) and INVALID_POSES_REPORT (gRPC Lift): the valid poses of a
request are lifted as they would be alone, the others answered null (an empty PoseResult) with their
own errors, in request order; the request's own rules still refuse it whole."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import grpc
import numpy as np
import pytest

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.report import MAX_POSE_ERRORS
from repnet.runtime.lifter import Lifter
from repnet.server.config import Settings
from repnet.server.http.body import OFF_LOOP_BYTES
from tests.conftest import POSE_2D
from tests.service.test_temporal import Temporal, clip, temporal_service

GOOD = POSE_2D.tolist()
FEW = [p if j < 3 else None for j, p in enumerate(GOOD)]  # 3 of 17 joints: too few to lift
SHIFTED = (POSE_2D + [40.0, -10.0]).tolist()


@pytest.fixture(scope="module")
def service(lifter: Lifter) -> Iterator[Temporal]:
    yield from temporal_service(lifter, Settings(grpc_port=0, intra_op_threads=1, max_request_poses=256))


def post(service: Temporal, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    headers = {"content-type": "application/json"}  # NaN and Infinity as Python's json writes them
    response = service.client.post("/lift", content=json.dumps(body), headers=headers)
    return response.status_code, response.json()


def mixed() -> list[Any]:
    """A valid pose, one with too few joints, one the schema refuses, one with a bad layout (rows of
    4 values without image_size), a valid one, and one with a non-finite coordinate."""
    nan_row = [[float("nan"), 1.0]] + GOOD[1:]
    return [
        {"keypoints": GOOD},
        {"keypoints": FEW},
        {"keypoints": [["x", 1.0]] + GOOD[1:]},
        {"keypoints": [[x, y, 0.0, 0.9] for x, y in GOOD], "format": "mediapipe33"},
        {"keypoints": SHIFTED},
        {"keypoints": nan_row},
    ]


def test_report_lifts_the_valid_poses_as_alone_and_names_the_others(service: Temporal) -> None:
    body = {"poses": mixed(), "invalid_poses": "report"}
    status, got = post(service, body)
    assert status == 200, got
    assert [p is None for p in got["poses"]] == [False, True, True, True, False, True]
    status, alone = post(service, {"poses": [{"keypoints": GOOD}, {"keypoints": SHIFTED}]})
    assert status == 200
    assert got["poses"][0] == alone["poses"][0] and got["poses"][4] == alone["poses"][1]
    by_pose = {e["pose"]: e for e in got["errors"]}
    assert sorted(by_pose) == [1, 2, 3, 5]
    assert [e["pose"] for e in got["errors"]] == sorted(e["pose"] for e in got["errors"])  # request order
    assert by_pose[1]["field"] == "poses[1].keypoints" and "3 of 17" in by_pose[1]["reason"]
    assert by_pose[2]["field"] == "poses[2].keypoints[0][0]" and by_pose[2]["joint"] == 0
    assert by_pose[3]["field"] == "poses[3].image_size"
    assert by_pose[5]["field"].startswith("poses[5].keypoints[0]") and by_pose[5]["code"] == "non_finite"
    assert got["error_count"] == len(got["errors"]) == 4
    assert all(e["message"].startswith(e["field"]) for e in got["errors"])


def test_refuse_is_the_default_and_names_the_same_poses(service: Temporal) -> None:
    status, got = post(service, {"poses": mixed()})
    assert status == 422
    assert "poses[2].keypoints[0][0]" in {e["field"] for e in got["detail"]}  # the schema's error first
    status, got = post(service, {"poses": [p for i, p in enumerate(mixed()) if i not in (2, 3)]})
    assert status == 422
    assert sorted({e["pose"] for e in got["detail"]}) == [1, 3]  # FEW and the NaN


def test_report_lists_a_few_errors_per_pose_and_counts_them_all(service: Temporal) -> None:
    broken = [[float("inf"), 1.0]] * 17  # every joint non-finite: 17 violations
    status, got = post(
        service, {"poses": [{"keypoints": GOOD}, {"keypoints": broken}], "invalid_poses": "report"}
    )
    assert status == 200
    assert got["poses"][1] is None and len(got["errors"]) == MAX_POSE_ERRORS
    assert got["error_count"] == 17


def test_the_requests_own_rules_still_refuse_it_whole(service: Temporal) -> None:
    for body, field in (
        ({"poses": [], "invalid_poses": "report"}, "poses"),
        ({"poses": [{"keypoints": GOOD}] * 257, "invalid_poses": "report"}, "poses"),
        (
            {"poses": [{"keypoints": GOOD}], "confidence_threshold": 2.0, "invalid_poses": "report"},
            "confidence_threshold",
        ),
        ({"poses": [{"keypoints": GOOD}], "invalid_poses": "skip"}, "invalid_poses"),
    ):
        status, got = post(service, body)
        assert status == 422, body
        assert got["detail"][0]["field"] == field


def test_every_pose_invalid_is_an_answer_of_nulls(service: Temporal) -> None:
    status, got = post(service, {"poses": [{"keypoints": FEW}] * 3, "invalid_poses": "report"})
    assert status == 200
    assert got["poses"] == [None, None, None] and [e["pose"] for e in got["errors"]] == [0, 1, 2]


def test_a_single_pose_body_takes_the_option(service: Temporal) -> None:
    status, got = post(service, {"keypoints": FEW, "invalid_poses": "report"})
    assert status == 200 and got["poses"] == [None] and got["errors"][0]["pose"] == 0


def test_a_large_body_is_answered_as_a_small_one(service: Temporal) -> None:
    poses = [{"keypoints": GOOD if i % 7 else FEW, "track_id": f"{i:0128d}"} for i in range(200)]
    padded = {"poses": poses, "invalid_poses": "report"}
    assert len(json.dumps(padded)) > OFF_LOOP_BYTES  # decoded and validated off the event loop
    status, got = post(service, padded)
    assert status == 200
    assert [p is None for p in got["poses"]] == [i % 7 == 0 for i in range(200)]
    assert [p["track_id"] for p in got["poses"] if p is not None] == [
        f"{i:0128d}" for i in range(200) if i % 7
    ]
    assert [e["pose"] for e in got["errors"]] == list(range(0, 200, 7))


def test_a_temporal_clip_skips_its_invalid_frames_as_gaps(service: Temporal) -> None:
    points = clip(12, noise_px=2.0)
    poses = [{"keypoints": p.tolist(), "track_id": "a", "frame": f} for f, p in enumerate(points)]
    poses[5] = {"keypoints": FEW, "track_id": "a", "frame": 5}
    for mode in ("causal", "offline"):
        status, got = post(
            service, {"poses": poses, "temporal": mode, "fps": 30.0, "invalid_poses": "report"}
        )
        assert status == 200, got
        assert got["poses"][5] is None and [e["pose"] for e in got["errors"]] == [5]
        without = [p for i, p in enumerate(poses) if i != 5]
        status, gap = post(service, {"poses": without, "temporal": mode, "fps": 30.0})
        assert status == 200
        assert [p for p in got["poses"] if p is not None] == gap["poses"]
        assert all(p["temporal"] for p in gap["poses"])
    status, got = post(service, {"poses": poses, "temporal": "causal", "fps": 30.0})
    assert status == 422 and got["detail"][0]["pose"] == 5


def grpc_pose(points: Any) -> lifter_pb2.Pose2D:
    flat = [v for row in points for v in (row or (0.0, 0.0))]
    return lifter_pb2.Pose2D(keypoints=flat, missing=[row is None for row in points])


def test_grpc_lift_reports_the_same_poses_with_empty_results(service: Temporal) -> None:
    nan_row = [[float("nan"), 1.0]] + GOOD[1:]
    poses = [grpc_pose(GOOD), grpc_pose(FEW), grpc_pose(SHIFTED), grpc_pose(nan_row)]
    request = lifter_pb2.LiftRequest(poses=poses, invalid_poses=lifter_pb2.INVALID_POSES_REPORT)
    got = service.stub.Lift(request)
    assert [len(p.pose_3d) for p in got.poses] == [51, 0, 51, 0]
    alone = service.stub.Lift(lifter_pb2.LiftRequest(poses=[poses[0], poses[2]]))
    assert got.poses[0] == alone.poses[0] and got.poses[2] == alone.poses[1]
    assert [e.pose for e in got.errors] == [1, 3]
    assert got.errors[0].error.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
    assert got.errors[0].error.violations[0].field == "poses[1].keypoints"
    assert got.errors[1].error.violations[0].code == "non_finite"
    status, http = post(
        service, {"poses": [{"keypoints": GOOD}, {"keypoints": FEW}], "invalid_poses": "report"}
    )
    assert got.errors[0].error.message == http["errors"][0]["message"]
    with pytest.raises(grpc.RpcError) as refused:  # the default refuses the call
        service.stub.Lift(lifter_pb2.LiftRequest(poses=poses))
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(grpc.RpcError) as empty:  # the request's own rules refuse it in report too
        service.stub.Lift(lifter_pb2.LiftRequest(invalid_poses=lifter_pb2.INVALID_POSES_REPORT))
    assert empty.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert np.isfinite(np.array(got.poses[0].pose_3d)).all()


def test_the_poses_not_lifted_are_counted_as_rejected_input(service: Temporal) -> None:
    def rejected(transport: str) -> float:
        value = service.metrics.rejected.labels(transport=transport, reason="too_few_visible")._value.get()
        return float(value)

    http_before, grpc_before = rejected("http"), rejected("grpc")
    status, _ = post(service, {"poses": [{"keypoints": GOOD}, {"keypoints": FEW}], "invalid_poses": "report"})
    assert status == 200 and rejected("http") == http_before + 1
    request = lifter_pb2.LiftRequest(
        poses=[grpc_pose(GOOD), grpc_pose(FEW)], invalid_poses=lifter_pb2.INVALID_POSES_REPORT
    )
    service.stub.Lift(request)
    assert rejected("grpc") == grpc_before + 1
