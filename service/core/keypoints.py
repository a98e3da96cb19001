"""Input rules: detector poses (PoseInput) -> the valid ones as model input, and each other's violations."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt

from repnet.core.errors import SPLIT_HINT, InvalidKeypoints, Violation, echo
from repnet.core.format_hints import alias_of, hint_for, lookalike_of, nose_height
from repnet.core.formats import (
    FORMAT_NAMES,
    FORMATS,
    MODEL_JOINTS,
    KeypointFormat,
    to_model_joints,
)
from repnet.core.geometry import BoolArray, height_problem, visible_stats
from repnet.core.inputs import MIN_SPREAD_PX, Limits, ModelInput, PoseInput, Prepared


def check_threshold(threshold: float | None, limits: Limits) -> float:
    """The request's confidence threshold, or the server default when it sets none."""
    if threshold is None:
        return limits.confidence_threshold
    if not (np.isfinite(threshold) and 0.0 <= threshold <= 1.0):
        reason = f"must be a number in [0, 1], got {threshold:g}"
        raise InvalidKeypoints([Violation("confidence_threshold", reason, "confidence_range")])
    return float(threshold)


def check_request(count: int, threshold: float | None, limits: Limits) -> None:
    """The rules on a request as a whole (an HTTP body, a gRPC Lift): its threshold, its pose count."""
    check_threshold(threshold, limits)
    if not count:
        raise InvalidKeypoints(
            [Violation("poses", "the batch is empty; send at least one pose", "empty_batch")]
        )
    if count > limits.max_request_poses:
        reason = f"{count} poses in one request, the limit is {limits.max_request_poses}; {SPLIT_HINT}"
        raise InvalidKeypoints([Violation("poses", reason, "batch_too_large")])


def prepare_request(
    count: int, read: Callable[[int], PoseInput], threshold: float | None, limits: Limits
) -> ModelInput:
    """The model input of a request (an HTTP body, a gRPC Lift) of `count` poses, all valid; else
    InvalidKeypoints listing what is wrong: the layout of the poses (read(i) converts pose i from the
    wire, or raises InvalidKeypoints named within the pose), else the request's rules, else each
    pose's rules."""
    poses = read_request(count, read, threshold, limits)
    return prepare_poses(poses, limits, threshold).check()


def read_request(
    count: int, read: Callable[[int], PoseInput], threshold: float | None, limits: Limits
) -> list[PoseInput]:
    """The poses of a request of `count` poses as read from the wire, checked as a request (the rules
    of each pose are prepare_poses'); else InvalidKeypoints: the layout of the poses (read(i) converts
    pose i, or raises InvalidKeypoints named within the pose), else the request's rules."""
    poses: list[PoseInput] = []
    found: list[Violation] = []
    for i in range(count):
        try:
            poses.append(read(i))
        except InvalidKeypoints as err:
            found.extend(v.within(f"poses[{i}]") for v in err.violations)
    if found:
        raise InvalidKeypoints(found)
    check_request(count, threshold, limits)
    return poses


def _shape_violations(pose: PoseInput, i: int) -> list[Violation]:
    """Format and per-joint counts; a pose with any of these is not checked further."""
    fmt = FORMATS.get(pose.format)
    if fmt is None:
        alias = alias_of(pose.format)
        means = f'; for {FORMATS[alias].description} send format "{alias}"' if alias else ""
        reason = f"unknown format {echo(pose.format)}; expected one of {', '.join(FORMATS)}{means}"
        return [Violation("format", reason, "unknown_format", pose=i)]
    joints = len(fmt.joint_names)
    if pose.points.shape[0] != joints:
        hint = hint_for(pose.points, pose.present, fmt.name)
        reason = f"format {fmt.name} has {joints} joints, got {pose.points.shape[0]}{hint}"
        return [Violation("keypoints", reason, "joint_count", pose=i)]
    if pose.confidence is not None and pose.confidence.shape[0] != joints:
        reason = f"expected {joints} values (one per joint of {fmt.name}), got {pose.confidence.shape[0]}"
        return [Violation("confidence", reason, "confidence_count", pose=i)]
    if pose.person_height_m is not None and (problem := height_problem(pose.person_height_m)):
        return [Violation("person_height_m", problem, "person_height", pose=i)]
    return []


def _value_violations(
    fmt: KeypointFormat,
    index: npt.NDArray[np.intp],
    points: np.ndarray,
    used: np.ndarray,
    confidence: np.ndarray,
    limits: Limits,
) -> list[Violation]:
    """Coordinates and confidences of (n, K) stacked poses of one format; `index`: their request index."""
    found: list[Violation] = []
    with np.errstate(invalid="ignore"):
        bad_conf = ~((confidence >= 0.0) & (confidence <= 1.0))  # NaN fails both
    for p, j in np.argwhere(bad_conf) if bad_conf.any() else ():  # argwhere costs more than any()
        reason = f"confidence must be a number in [0, 1], got {confidence[p, j]:g}"
        found.append(_joint_violation(fmt, f"confidence[{j}]", reason, "confidence_range", int(index[p]), j))
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
        found.append(_joint_violation(fmt, f"keypoints[{j}]", reason, code, int(index[p]), j))
    return found


def _joint_violation(
    fmt: KeypointFormat, field: str, reason: str, code: str, pose: int, joint: int
) -> Violation:
    return Violation(field, reason, code, pose=pose, joint=int(joint), joint_name=fmt.joint_names[joint])


def _model_violations(
    index: npt.NDArray[np.intp], points: np.ndarray, visible: np.ndarray, limits: Limits, zeroed: np.ndarray
) -> list[Violation]:
    """Rules on the converted (n, 17) model joints: enough of them, and not all at one point.
    zeroed: (n,) the pose's joints read as missing at (0, 0), named when too few are left."""
    found: list[Violation] = []
    count = visible.sum(axis=1)  # (n,)
    mean, spread = visible_stats(points, visible)  # (n, 2), (n,) px
    for p in range(len(index)):
        if count[p] < limits.min_visible_joints:
            reason = (
                f"{count[p]} of {len(MODEL_JOINTS)} model joints are visible after the confidence "
                f"threshold and format conversion, need at least {limits.min_visible_joints}"
            )
            if zeroed[p]:
                reason += f" ({zeroed[p]} joints at exactly (0, 0) without confidence count as missing)"
            found.append(Violation("keypoints", reason, "too_few_visible", pose=int(index[p])))
        elif spread[p] < MIN_SPREAD_PX:
            reason = (
                f"all visible joints are at one point ({mean[p, 0]:g}, {mean[p, 1]:g}); "
                "the pose needs a spatial extent"
            )
            found.append(Violation("keypoints", reason, "degenerate", pose=int(index[p])))
    return found


@cache
def _used(fmt: KeypointFormat) -> np.ndarray:
    """(K,) the format's joints that feed a model joint; the others (face joints etc.) are ignored."""
    used = np.zeros(len(fmt.joint_names), bool)
    used[[k for src in fmt.sources for k in src]] = True
    return used


def _stack(
    fmt: KeypointFormat, poses: Sequence[PoseInput], cut: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points (n, K, 2), confidences (n, K) (1 where none given), visibility (n, K) and the joints
    read as missing for being at exactly (0, 0) (n, K) of poses; `cut`: (n, 1) each pose's
    confidence threshold.

    A joint at exactly (0, 0) in a pose without confidence is missing: OpenPose and other detectors
    write 0, 0 (with confidence 0) for a joint they did not find, and without the confidence it would
    be lifted as a joint in the image's corner. With a confidence, the threshold decides."""
    points = np.stack([p.points for p in poses])  # the wire's dtype: float32 stays float32
    ones = np.ones(len(fmt.joint_names))
    confidence = np.stack([ones if p.confidence is None else p.confidence for p in poses])
    present = np.stack([p.present for p in poses]).astype(bool)
    unsure = np.array([[p.confidence is None] for p in poses])  # (n, 1)
    zeroed = present & unsure & (points == 0).all(axis=-1)  # (n, K)
    with np.errstate(invalid="ignore"):  # a NaN confidence is reported, not used
        visible = present & ~zeroed & (confidence >= cut)
    return points, confidence, visible, zeroed


def _clean(index: npt.NDArray[np.intp], found: list[Violation]) -> BoolArray:
    """(n,) True for the poses (request indices `index`) that have none of the violations `found`."""
    return ~np.isin(index, [v.pose or 0 for v in found])  # violations of one pose name it


@dataclass(frozen=True)
class _Part:
    """The valid poses of one format: their request indices and their converted model input."""

    index: npt.NDArray[np.intp]
    # keypoints_2d, visible, derived, imputed, format_index, nose_height, zeroed
    columns: tuple[np.ndarray, ...]


def _prepare_format(
    fmt: KeypointFormat,
    index: npt.NDArray[np.intp],
    poses: Sequence[PoseInput],
    cut: np.ndarray,
    limits: Limits,
) -> tuple[_Part, list[Violation]]:
    """Check and convert the poses of one format; a pose with bad values is not checked further."""
    points, confidence, visible, zeroed = _stack(fmt, poses, cut)
    found = _value_violations(fmt, index, points, visible & _used(fmt), confidence, limits)
    if found and not (ok := _clean(index, found)).all():
        points, visible, index, zeroed = points[ok], visible[ok], index[ok], zeroed[ok]
    converted = to_model_joints(fmt, points, visible)
    counts = (zeroed & _used(fmt)).sum(axis=1).astype(np.int16)  # (n,) only joints the model reads
    model = _model_violations(index, converted[0], converted[1], limits, counts)
    if model and not (ok := _clean(index, model)).all():
        points, visible, index, counts = points[ok], visible[ok], index[ok], counts[ok]
        converted = (converted[0][ok], converted[1][ok], converted[2][ok], converted[3][ok])
    # The geometry a format mix-up shows, kept for the reply's warnings (repnet.core.lookalike).
    height = (
        nose_height(points, visible) if lookalike_of(fmt.name) else np.full(len(index), np.nan, np.float32)
    )
    format_index = np.full(len(index), FORMAT_NAMES.index(fmt.name), np.int8)
    return _Part(index, (*converted, format_index, height, counts)), found + model


def prepare_poses(poses: Sequence[PoseInput], limits: Limits, threshold: float | None = None) -> Prepared:
    """Check each pose against every pose rule and convert the valid ones to the model's joints.

    `threshold`: the request's confidence threshold (see check_request), for the poses without
    their own; None: the server default. Broken rules are returned per pose, never raised.
    """
    found: list[list[Violation]] = [[] for _ in poses]
    groups: dict[str, list[int]] = {}
    for i, pose in enumerate(poses):
        if shape := _shape_violations(pose, i):
            found[i] = shape
        else:
            groups.setdefault(pose.format, []).append(i)
    default = limits.confidence_threshold if threshold is None else threshold
    parts: list[_Part] = []
    for name, members in groups.items():
        group = [poses[i] for i in members]
        cut = np.array(
            [[default if p.confidence_threshold is None else p.confidence_threshold] for p in group]
        )
        part, broken = _prepare_format(FORMATS[name], np.array(members, np.intp), group, cut, limits)
        parts.append(part)
        for v in broken:
            found[v.pose or 0].append(v)
    rows, (points, visible, derived, imputed, format_index, height, zeroed) = _join(parts)
    camera = np.array([poses[i].intrinsics or (np.nan,) * 4 for i in rows.tolist()], np.float32)
    camera = camera.reshape(len(rows), 4)
    sizes = np.array([poses[i].person_height_m or np.nan for i in rows.tolist()], np.float32)
    inputs = ModelInput(points, visible, derived, imputed, format_index, height, camera, zeroed, sizes)
    return Prepared(inputs, tuple(tuple(sorted(f, key=lambda v: v.joint or -1)) for f in found))


def _join(parts: list[_Part]) -> tuple[npt.NDArray[np.intp], tuple[np.ndarray, ...]]:
    """The request indices and columns of every format's valid poses, in request order."""
    if len(parts) == 1:  # one format: already in order
        return parts[0].index, parts[0].columns
    if not parts:  # no valid pose
        flags = np.zeros((0, len(MODEL_JOINTS)), bool)
        points = np.zeros((0, len(MODEL_JOINTS), 2), np.float32)
        return np.zeros(0, np.intp), (
            points,
            flags,
            flags,
            flags,
            np.zeros(0, np.int8),
            np.zeros(0, np.float32),
            np.zeros(0, np.int16),
        )
    index = np.concatenate([p.index for p in parts])
    order = np.argsort(index, kind="stable")
    joined = tuple(np.concatenate(c)[order] for c in zip(*(p.columns for p in parts), strict=True))
    return index[order], joined
