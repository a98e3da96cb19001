"""gRPC poses in: a proto Pose2D (with the request's defaults) -> PoseInput, its layout rules."""

from __future__ import annotations

import math

import numpy as np

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.inputs import PoseInput


def intrinsics_violations(camera: lifter_pb2.CameraIntrinsics, field: str) -> list[Violation]:
    """fx, fy must be finite and > 0, cx, cy finite."""
    found = []
    for name in ("fx", "fy", "cx", "cy"):
        value = getattr(camera, name)
        if not math.isfinite(value) or (name in ("fx", "fy") and value <= 0):
            rule = "finite and > 0" if name in ("fx", "fy") else "finite"
            found.append(Violation(f"{field}.{name}", f"must be {rule}, got {value}", "intrinsics"))
    return found


def image_size_violations(size: lifter_pb2.ImageSize, field: str) -> list[Violation]:
    """width and height must be finite and > 0 (pixels)."""
    found = []
    for name in ("width", "height"):
        value = getattr(size, name)
        if not (math.isfinite(value) and value > 0):
            reason = f"must be a finite number of pixels > 0, got {value}"
            found.append(Violation(f"{field}.{name}", reason, "image_size"))
    return found


def _structure_violations(pose: lifter_pb2.Pose2D) -> list[Violation]:
    """Layout rules that JSON expresses by nesting and proto by counts (fields named within the pose)."""
    found = []
    values = len(pose.keypoints)
    if values % 2:
        reason = f"expected 2 values (x, y) per joint, got {values} values"
        if values % 3 == 0 or values % 4 == 0:
            reason += (
                "; send x, y in `keypoints` and a detector's confidence (MediaPipe: visibility) in "
                "`confidence`, one per joint"
            )
        found.append(Violation("keypoints", reason, "joint_count"))
    if pose.missing and len(pose.missing) != values // 2:
        reason = f"expected no values or one per joint ({values // 2}), got {len(pose.missing)}"
        found.append(Violation("missing", reason, "missing_count"))
    if pose.HasField("intrinsics"):
        found += intrinsics_violations(pose.intrinsics, "intrinsics")
    if pose.HasField("image_size"):
        found += image_size_violations(pose.image_size, "image_size")
    return found


def to_pose_input(
    pose: lifter_pb2.Pose2D,
    default_format: str,
    default_intrinsics: lifter_pb2.CameraIntrinsics | None,
    default_size: lifter_pb2.ImageSize | None = None,
    default_height: float | None = None,
    threshold: float | None = None,
) -> PoseInput:
    """A proto pose in its wire-independent form, float32 as the wire carries it; InvalidKeypoints
    (named within the pose) on a bad layout. default_intrinsics, default_size, default_height: those
    of a pose without its own; threshold: its confidence threshold (a stream frame's; None: the
    request's). Normalised keypoints are multiplied by the image size, as over HTTP."""
    if found := _structure_violations(pose):
        raise InvalidKeypoints(found)
    points = np.array(pose.keypoints, dtype=np.float32).reshape(-1, 2)
    size = pose.image_size if pose.HasField("image_size") else default_size
    if size is not None:
        points = points * np.array([size.width, size.height], np.float32)  # (K, 2) px
    present = ~np.array(pose.missing, dtype=bool) if pose.missing else np.ones(len(points), dtype=bool)
    confidence = np.array(pose.confidence, dtype=np.float32) if pose.confidence else None
    camera = pose.intrinsics if pose.HasField("intrinsics") else default_intrinsics
    intrinsics = None if camera is None else (camera.fx, camera.fy, camera.cx, camera.cy)
    height = pose.person_height_m if pose.HasField("person_height_m") else default_height
    fmt = pose.format or default_format
    return PoseInput(points, present, confidence, fmt, intrinsics, threshold, height)
