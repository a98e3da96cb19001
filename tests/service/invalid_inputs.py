"""Requests that break one input rule each, with the field and reason both transports must name."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.errors import SPLIT_HINT
from tests.conftest import POSE_2D

NAN, INF = float("nan"), float("inf")


def good(**fields: Any) -> dict[str, Any]:
    """A valid h36m17 pose (as JSON-ready dict), with `fields` replaced."""
    return {"keypoints": POSE_2D.tolist(), **fields}


def with_joint(index: int, value: Any) -> dict[str, Any]:
    keypoints: list[Any] = POSE_2D.tolist()
    keypoints[index] = value
    return good(keypoints=keypoints)


def visible_only(count: int) -> dict[str, Any]:
    return good(keypoints=[p if j < count else None for j, p in enumerate(POSE_2D.tolist())])


def confidence_at(index: int, value: float) -> dict[str, Any]:
    confidence = [0.9] * 17
    confidence[index] = value
    return good(confidence=confidence)


@dataclass(frozen=True)
class Case:
    """A request body, and the error item expected in the reply."""

    id: str
    request: dict[str, Any]
    field: str
    code: str
    reason: str  # a part of the reason
    pose: int | None = None
    joint: int | None = None
    joint_name: str | None = None


CASES = [
    Case("wrong_joint_count", {"poses": [good(), good(keypoints=POSE_2D[:16].tolist())]},
         "poses[1].keypoints", "joint_count", "format h36m17 has 17 joints, got 16", pose=1),
    Case("wrong_joint_count_for_format", {"poses": [good(format="mpii16")]},
         "poses[0].keypoints", "joint_count", "format mpii16 has 16 joints, got 17", pose=0),
    Case("nan", {"poses": [good(), with_joint(4, [NAN, 1.0])]},
         "poses[1].keypoints[4]", "non_finite", "finite numbers, got [nan, 1]", 1, 4, "left_hip"),
    Case("infinite", {"poses": [with_joint(16, [2.0, INF])]},
         "poses[0].keypoints[16]", "non_finite", "finite numbers, got [2, inf]", 0, 16, "right_wrist"),
    Case("out_of_range", {"poses": [with_joint(0, [2e6, 5.0])]},
         "poses[0].keypoints[0]", "out_of_range", "within ±1e+06 px, got [2e+06, 5]", 0, 0, "pelvis"),
    Case("confidence_above_one", {"poses": [confidence_at(3, 1.5)]},
         "poses[0].confidence[3]", "confidence_range", "in [0, 1], got 1.5", 0, 3, "right_ankle"),
    Case("confidence_negative", {"poses": [confidence_at(2, -0.25)]},
         "poses[0].confidence[2]", "confidence_range", "in [0, 1], got -0.25", 0, 2, "right_knee"),
    Case("confidence_nan", {"poses": [confidence_at(9, NAN)]},
         "poses[0].confidence[9]", "confidence_range", "in [0, 1], got nan", 0, 9, "neck"),
    Case("confidence_count", {"poses": [good(confidence=[0.5] * 5)]},
         "poses[0].confidence", "confidence_count", "expected 17 values", pose=0),
    Case("too_few_visible", {"poses": [visible_only(5)]},
         "poses[0].keypoints", "too_few_visible", "5 of 17 model joints are visible", pose=0),
    Case("too_few_confident", {"poses": [good(confidence=[0.9] * 3 + [0.1] * 14)]},
         "poses[0].keypoints", "too_few_visible", "3 of 17 model joints", pose=0),
    Case("all_at_one_point", {"poses": [good(keypoints=[[321.0, 123.0]] * 17)]},
         "poses[0].keypoints", "degenerate", "at one point (321, 123)", pose=0),
    Case("empty_batch", {"poses": []}, "poses", "empty_batch", "the batch is empty"),
    Case("batch_too_large", {"poses": [good()] * 17}, "poses", "batch_too_large",
         f"17 poses in one request, the limit is 16; {SPLIT_HINT}"),
    Case("unknown_format", {"poses": [good(format="openpose")]},
         "poses[0].format", "unknown_format", "unknown format 'openpose'", pose=0),
    Case("threshold_out_of_range", {"poses": [good()], "confidence_threshold": 2.0},
         "confidence_threshold", "confidence_range", "in [0, 1], got 2"),
    Case("person_height_in_mm", {"poses": [good(person_height_m=1750.0)]},
         "poses[0].person_height_m", "person_height", "got 1750 (millimetres? divide by 1000)", pose=0),
    Case("request_person_height_too_small", {"poses": [good()], "person_height_m": 0.25},
         "poses[0].person_height_m", "person_height", "in [0.5, 2.5], got 0.25", pose=0),
]  # fmt: skip


def to_proto_pose(pose: dict[str, Any]) -> lifter_pb2.Pose2D:
    """The same pose on the gRPC wire: flat keypoints, missing flags where JSON has null."""
    keypoints = [v for p in pose["keypoints"] for v in (p if p is not None else (0.0, 0.0))]
    missing = [p is None for p in pose["keypoints"]]
    return lifter_pb2.Pose2D(
        keypoints=keypoints,
        missing=missing if any(missing) else [],
        confidence=pose.get("confidence") or [],
        format=pose.get("format", ""),
        person_height_m=pose.get("person_height_m"),
    )


def to_proto_request(request: dict[str, Any]) -> lifter_pb2.LiftRequest:
    message = lifter_pb2.LiftRequest(poses=[to_proto_pose(p) for p in request["poses"]])
    if "confidence_threshold" in request:
        message.confidence_threshold = request["confidence_threshold"]
    if "person_height_m" in request:
        message.person_height_m = request["person_height_m"]
    return message
