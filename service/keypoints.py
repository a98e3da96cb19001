"""Detector keypoints -> model input: every input rule of the service and the format conversion."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt

from service.errors import InvalidKeypoints, Violation, echo
from service.formats import (
    FORMAT_NAMES,
    FORMATS,
    MODEL_JOINTS,
    KeypointFormat,
    lookalike_of,
    nose_height,
    to_model_joints,
)
from service.geometry import BoolArray, FloatArray, visible_stats

DEFAULT_FORMAT = "h36m17"
# Below this spread (px) the visible joints count as one point: the input cannot be normalised.
MIN_SPREAD_PX = 1e-3


@dataclass(frozen=True)
class Limits:
    """The documented input limits, from Settings."""

    max_request_poses: int = 1024
    min_visible_joints: int = 6
    confidence_threshold: float = 0.2  # default when a request does not set its own
    max_coordinate: float = 1e6  # px


@dataclass(frozen=True)
class PoseInput:
    """One detector pose as a transport received it."""

    points: npt.NDArray[np.float64]  # (K, 2) px; rows of absent joints are ignored
    present: BoolArray  # (K,) False where the request marks the joint missing (JSON null)
    confidence: npt.NDArray[np.float64] | None = None  # (K,) in [0, 1], or None
    format: str = DEFAULT_FORMAT
    # (fx, fy, cx, cy) px of the pinhole camera that saw the pose, if the client knows it.
    intrinsics: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class ModelInput:
    """N poses in the model's joints, ready for Lifter.lift."""

    keypoints_2d: FloatArray  # (N, 17, 2) px; 0 where not visible
    visible: BoolArray  # (N, 17)
    derived: BoolArray  # (N, 17) the joint is the midpoint of two detector joints
    imputed: BoolArray  # (N, 17) no visible source: the model fills the joint in
    format_index: npt.NDArray[np.int8]  # (N,) the pose's format, an index into formats.FORMAT_NAMES
    nose_height: npt.NDArray[np.float32]  # (N,) formats.nose_height of its 17 input joints, or NaN
    intrinsics: FloatArray  # (N, 4) fx, fy, cx, cy px of the pose's camera; NaN where not given

    def __len__(self) -> int:
        return int(self.keypoints_2d.shape[0])


def pose_field(prefix: str, index: int) -> str:
    """The field name of pose `index`: "poses[3]" in a batch; the prefix itself for one frame."""
    return f"{prefix}[{index}]" if prefix == "poses" else prefix


def check_threshold(threshold: float | None, limits: Limits) -> float:
    """The request's confidence threshold, or the server default when it sets none."""
    if threshold is None:
        return limits.confidence_threshold
    if not (np.isfinite(threshold) and 0.0 <= threshold <= 1.0):
        raise InvalidKeypoints(
            [
                Violation(
                    "confidence_threshold",
                    f"must be a number in [0, 1], got {threshold:g}",
                    "confidence_range",
                )
            ]
        )
    return float(threshold)


def _count_violations(poses: Sequence[PoseInput], limits: Limits, prefix: str) -> list[Violation]:
    if not poses:
        return [Violation(prefix, "the batch is empty; send at least one pose", "empty_batch")]
    if len(poses) > limits.max_request_poses:
        reason = f"{len(poses)} poses in one request, the limit is {limits.max_request_poses}"
        return [Violation(prefix, reason, "batch_too_large")]
    return []


def _shape_violations(pose: PoseInput, i: int, prefix: str) -> list[Violation]:
    """Format and per-joint counts; a pose with any of these is not checked further."""
    base = pose_field(prefix, i)
    fmt = FORMATS.get(pose.format)
    if fmt is None:
        reason = f"unknown format {echo(pose.format)}; expected one of {', '.join(FORMATS)}"
        return [Violation(f"{base}.format", reason, "unknown_format", pose=i)]
    joints = len(fmt.joint_names)
    if pose.points.shape[0] != joints:
        reason = f"format {fmt.name} has {joints} joints, got {pose.points.shape[0]}"
        return [Violation(f"{base}.keypoints", reason, "joint_count", pose=i)]
    if pose.confidence is not None and pose.confidence.shape[0] != joints:
        reason = f"expected {joints} values (one per joint of {fmt.name}), got {pose.confidence.shape[0]}"
        return [Violation(f"{base}.confidence", reason, "confidence_count", pose=i)]
    return []


def _value_violations(
    fmt: KeypointFormat,
    index: Sequence[int],
    points: np.ndarray,
    used: np.ndarray,
    confidence: np.ndarray,
    limits: Limits,
    prefix: str,
) -> list[Violation]:
    """Coordinates and confidences of (n, K) stacked poses of one format."""
    found: list[Violation] = []
    with np.errstate(invalid="ignore"):
        bad_conf = ~((confidence >= 0.0) & (confidence <= 1.0))  # NaN fails both
    for p, j in np.argwhere(bad_conf) if bad_conf.any() else ():  # argwhere costs more than any()
        found.append(
            Violation(
                f"{pose_field(prefix, index[p])}.confidence[{j}]",
                f"confidence must be a number in [0, 1], got {confidence[p, j]:g}",
                "confidence_range",
                pose=index[p],
                joint=int(j),
                joint_name=fmt.joint_names[j],
            )
        )
    finite = np.isfinite(points).all(axis=-1)  # (n, K)
    with np.errstate(invalid="ignore"):
        in_range = (np.abs(points) <= limits.max_coordinate).all(axis=-1)
    bad_points = used & ~(finite & in_range)
    for p, j in np.argwhere(bad_points) if bad_points.any() else ():
        xy = f"[{points[p, j, 0]:g}, {points[p, j, 1]:g}]"
        if finite[p, j]:
            reason, code = (
                f"coordinates must be within ±{limits.max_coordinate:g} px, got {xy}",
                "out_of_range",
            )
        else:
            reason, code = f"coordinates must be finite numbers, got {xy}", "non_finite"
        found.append(
            Violation(
                f"{pose_field(prefix, index[p])}.keypoints[{j}]",
                reason,
                code,
                pose=index[p],
                joint=int(j),
                joint_name=fmt.joint_names[j],
            )
        )
    return found


def _model_violations(
    index: Sequence[int], points: np.ndarray, visible: np.ndarray, limits: Limits, prefix: str
) -> list[Violation]:
    """Rules on the converted (n, 17) model joints: enough of them, and not all at one point."""
    found: list[Violation] = []
    count = visible.sum(axis=1)  # (n,)
    mean, spread = visible_stats(points, visible)  # (n, 2), (n,) px
    for p in range(len(index)):
        field = f"{pose_field(prefix, index[p])}.keypoints"
        if count[p] < limits.min_visible_joints:
            reason = (
                f"{count[p]} of {len(MODEL_JOINTS)} model joints are visible after the confidence "
                f"threshold and format conversion, need at least {limits.min_visible_joints}"
            )
            found.append(Violation(field, reason, "too_few_visible", pose=index[p]))
        elif spread[p] < MIN_SPREAD_PX:
            reason = (
                f"all visible joints are at one point ({mean[p, 0]:g}, {mean[p, 1]:g}); "
                "the pose needs a spatial extent"
            )
            found.append(Violation(field, reason, "degenerate", pose=index[p]))
    return found


@cache
def _used(fmt: KeypointFormat) -> np.ndarray:
    """(K,) the format's joints that feed a model joint; the others (face joints etc.) are ignored."""
    used = np.zeros(len(fmt.joint_names), bool)
    used[[k for src in fmt.sources for k in src]] = True
    return used


def _stack(fmt: KeypointFormat, poses: Sequence[PoseInput], cut: float) -> tuple[np.ndarray, ...]:
    """Points (n, K, 2), confidences (n, K) (1 where none given) and visibility (n, K) of poses."""
    points = np.stack([p.points for p in poses]).astype(np.float64)
    ones = np.ones(len(fmt.joint_names))
    confidence = np.stack([ones if p.confidence is None else p.confidence for p in poses]).astype(np.float64)
    with np.errstate(invalid="ignore"):  # a NaN confidence is reported, not used
        visible = np.stack([p.present for p in poses]).astype(bool) & (confidence >= cut)
    return points, confidence, visible


def prepare_poses(
    poses: Sequence[PoseInput], limits: Limits, threshold: float | None = None, prefix: str = "poses"
) -> ModelInput:
    """Check `poses` against every input rule and convert them to the model's joints.

    Raises InvalidKeypoints listing each broken rule with its field (pose index and joint).
    `prefix` names the poses in messages: "poses" for a batch, "pose" for one stream frame.
    """
    cut = check_threshold(threshold, limits)
    if found := _count_violations(poses, limits, prefix):
        raise InvalidKeypoints(found)
    violations: list[Violation] = []
    groups: dict[str, list[int]] = {}
    for i, pose in enumerate(poses):
        if shape := _shape_violations(pose, i, prefix):
            violations.extend(shape)
        else:
            groups.setdefault(pose.format, []).append(i)
    n = len(poses)
    intrinsics = np.array([p.intrinsics or (np.nan,) * 4 for p in poses], np.float32).reshape(n, 4)
    out = ModelInput(
        keypoints_2d=np.zeros((n, len(MODEL_JOINTS), 2), np.float32),
        visible=np.zeros((n, len(MODEL_JOINTS)), bool),
        derived=np.zeros((n, len(MODEL_JOINTS)), bool),
        imputed=np.zeros((n, len(MODEL_JOINTS)), bool),
        format_index=np.zeros(n, np.int8),
        nose_height=np.full(n, np.nan, np.float32),
        intrinsics=intrinsics,
    )
    for name, index in groups.items():
        fmt = FORMATS[name]
        points, confidence, visible = _stack(fmt, [poses[i] for i in index], cut)
        if found := _value_violations(fmt, index, points, visible & _used(fmt), confidence, limits, prefix):
            violations.extend(found)
            continue
        converted = to_model_joints(fmt, points, visible)
        if found := _model_violations(index, converted[0], converted[1], limits, prefix):
            violations.extend(found)
            continue
        # The geometry a format mix-up shows, kept for the reply's warnings (service.lookalike).
        height = nose_height(points, visible) if lookalike_of(name) else np.full(len(index), np.nan)
        format_index = np.full(len(index), FORMAT_NAMES.index(name), np.int8)
        if len(index) == n and not violations:  # one format for the whole request: no scatter
            return ModelInput(
                *converted, format_index=format_index, nose_height=height, intrinsics=intrinsics
            )
        targets: tuple[np.ndarray, ...] = (out.keypoints_2d, out.visible, out.derived, out.imputed)
        for target, value in zip(
            (*targets, out.format_index, out.nose_height), (*converted, format_index, height), strict=True
        ):
            target[index] = value
    if violations:
        raise InvalidKeypoints(sorted(violations, key=lambda v: (v.pose or 0, v.joint or -1)))
    return out
