"""Keypoint formats of 2D detectors and their declarative mapping onto the model's 17 joints."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt

from repnet.core import skeleton

FloatArray = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]

# The model's joint order (Human3.6M 17) and each joint's parent (-1: the root), as the ONNX
# `joint_names` and `parents` metadata repeat them: the skeleton's (core.skeleton).
MODEL_JOINTS: tuple[str, ...] = skeleton.JOINT_NAMES
MODEL_PARENTS: tuple[int, ...] = skeleton.PARENTS


@dataclass(frozen=True)
class KeypointFormat:
    """A detector's joint list and, for each model joint, the source joints that give it."""

    name: str  # "h36m17", "coco17", "body25", ...: the keys of FORMATS
    joint_names: tuple[str, ...]  # source joints, in the detector's order
    # For each of the 17 model joints: () none (imputed by the model), (i,) a joint,
    # (i, k) the midpoint of two joints.
    sources: tuple[tuple[int, ...], ...]
    description: str = ""

    def __post_init__(self) -> None:
        if len(self.sources) != len(MODEL_JOINTS):
            raise ValueError(f"{self.name}: expected {len(MODEL_JOINTS)} sources, got {len(self.sources)}")
        for src in self.sources:
            if len(src) > 2 or any(not 0 <= i < len(self.joint_names) for i in src):
                raise ValueError(f"{self.name}: bad source {src} for {len(self.joint_names)} joints")


def _table(joint_names: tuple[str, ...], spec: dict[str, tuple[str, ...]]) -> tuple[tuple[int, ...], ...]:
    """Turn {model joint: source joint names} into index tuples in model joint order."""
    if unknown := set(spec) - set(MODEL_JOINTS):
        raise ValueError(f"unknown model joints {sorted(unknown)}")
    index = {name: i for i, name in enumerate(joint_names)}
    return tuple(tuple(index[s] for s in spec.get(joint, ())) for joint in MODEL_JOINTS)


def _format(
    name: str, description: str, joint_names: tuple[str, ...], spec: dict[str, tuple[str, ...]]
) -> KeypointFormat:
    return KeypointFormat(name, joint_names, _table(joint_names, spec), description)


# Human3.6M 'neck' (9) is the neck/nose joint and 'head' (10) the top of the head; detectors that
# only see the face map their nose onto 9 and have no head top, so 10 is imputed. No detector has
# the mid-torso 'spine' (7): it is imputed too, as in 3d-pose-baseline's Stacked-Hourglass inputs.
_LIMBS = {
    "right_hip": ("right_hip",),
    "right_knee": ("right_knee",),
    "right_ankle": ("right_ankle",),
    "left_hip": ("left_hip",),
    "left_knee": ("left_knee",),
    "left_ankle": ("left_ankle",),
    "left_shoulder": ("left_shoulder",),
    "left_elbow": ("left_elbow",),
    "left_wrist": ("left_wrist",),
    "right_shoulder": ("right_shoulder",),
    "right_elbow": ("right_elbow",),
    "right_wrist": ("right_wrist",),
}

# Detectors with hips and shoulders but no pelvis, thorax or head top: the midpoints stand in for them.
_COCO_TORSO = {
    "pelvis": ("left_hip", "right_hip"),
    "thorax": ("left_shoulder", "right_shoulder"),
    "neck": ("nose",),
}

H36M17 = _format(
    "h36m17",
    "Human3.6M 17 joints, the model's own order",
    MODEL_JOINTS,
    {joint: (joint,) for joint in MODEL_JOINTS},
)

MPII16 = _format(
    "mpii16",
    "MPII 16 joints (Stacked Hourglass and other MPII-trained detectors)",
    (
        "right_ankle",
        "right_knee",
        "right_hip",
        "left_hip",
        "left_knee",
        "left_ankle",
        "pelvis",
        "thorax",
        "upper_neck",
        "head_top",
        "right_wrist",
        "right_elbow",
        "right_shoulder",
        "left_shoulder",
        "left_elbow",
        "left_wrist",
    ),
    {**_LIMBS, "pelvis": ("pelvis",), "thorax": ("thorax",), "neck": ("upper_neck",), "head": ("head_top",)},
)

COCO17 = _format(
    "coco17",
    "COCO 17 keypoints (YOLO-pose, RTMPose, Detectron2, MMPose, ViTPose)",
    (
        "nose",
        "left_eye",
        "right_eye",
        "left_ear",
        "right_ear",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
        "left_hip",
        "right_hip",
        "left_knee",
        "right_knee",
        "left_ankle",
        "right_ankle",
    ),
    {**_LIMBS, **_COCO_TORSO},
)

# OpenPose's Neck and MidHip are detector outputs (trained as the shoulder and hip midpoints).
BODY25 = _format(
    "body25",
    "OpenPose BODY_25",
    (
        "nose",
        "neck",
        "right_shoulder",
        "right_elbow",
        "right_wrist",
        "left_shoulder",
        "left_elbow",
        "left_wrist",
        "mid_hip",
        "right_hip",
        "right_knee",
        "right_ankle",
        "left_hip",
        "left_knee",
        "left_ankle",
        "right_eye",
        "left_eye",
        "right_ear",
        "left_ear",
        "left_big_toe",
        "left_small_toe",
        "left_heel",
        "right_big_toe",
        "right_small_toe",
        "right_heel",
    ),
    {**_LIMBS, "pelvis": ("mid_hip",), "thorax": ("neck",), "neck": ("nose",)},
)

MEDIAPIPE33 = _format(
    "mediapipe33",
    "MediaPipe Pose / BlazePose 33 landmarks (x, y in pixels)",
    (
        "nose",
        "left_eye_inner",
        "left_eye",
        "left_eye_outer",
        "right_eye_inner",
        "right_eye",
        "right_eye_outer",
        "left_ear",
        "right_ear",
        "mouth_left",
        "mouth_right",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
        "left_pinky",
        "right_pinky",
        "left_index",
        "right_index",
        "left_thumb",
        "right_thumb",
        "left_hip",
        "right_hip",
        "left_knee",
        "right_knee",
        "left_ankle",
        "right_ankle",
        "left_heel",
        "right_heel",
        "left_foot_index",
        "right_foot_index",
    ),
    {**_LIMBS, **_COCO_TORSO},
)

# OpenPose's --model_pose COCO: BODY_25's joints without MidHip and the feet, in the same order
# (OpenPose src/openpose/pose/poseParameters.cpp, POSE_COCO_BODY_PARTS; the same in tf-pose-estimation's
# tf_pose/common.py and Lightweight OpenPose's modules/pose.py). Its Neck is a detector output as in
# BODY_25. (trt_pose's 18 are COCO's 17 then the neck: not this order.)
COCO18 = _format(
    "coco18",
    "OpenPose COCO 18 keypoints (--model_pose COCO, tf-pose-estimation, Lightweight OpenPose)",
    tuple(joint for joint in BODY25.joint_names[:19] if joint != "mid_hip"),
    {**_LIMBS, "pelvis": ("left_hip", "right_hip"), "thorax": ("neck",), "neck": ("nose",)},
)

# The six foot points of BODY_25, BODY_25B and COCO-WholeBody, in that shared order.
_FEET = BODY25.joint_names[19:]

# OpenPose's experimental BODY_25B: COCO's 17, then UpperNeck, HeadTop and the feet (OpenPose
# experimental_models/README.md; src/openpose/pose/poseParameters.cpp, POSE_BODY_25B_BODY_PARTS).
# UpperNeck is MPII's upper neck, used as mpii16 uses it; the head top gives Human3.6M's head. With
# those two the model imputes the thorax better than mid-shoulders give it (bench.format_accuracy,
# S9/S11 every 10th frame: PA-MPJPE 37.9 against 38.1 mm, MPJPE 68.6 against 75.5 mm).
BODY25B = _format(
    "body25b",
    "OpenPose BODY_25B, the experimental model with upper neck and head top",
    (*COCO17.joint_names, "upper_neck", "head_top", *_FEET),
    {**_LIMBS, "pelvis": ("left_hip", "right_hip"), "neck": ("upper_neck",), "head": ("head_top",)},
)

# Halpe-FullBody's 26 body keypoints: COCO's 17, then Head (the top of the head), Neck, Hip (the
# mid-hip) and the feet in their own order (Fang-Haoshu/Halpe-FullBody README, "Keypoints format").
# Neck and Hip are trained points, read as BODY_25's Neck and MidHip are.
HALPE26 = _format(
    "halpe26",
    "Halpe 26 body keypoints (AlphaPose halpe26, RTMPose body7 / halpe26, Pose2Sim)",
    (
        *COCO17.joint_names,
        "head",
        "neck",
        "hip",
        "left_big_toe",
        "right_big_toe",
        "left_small_toe",
        "right_small_toe",
        "left_heel",
        "right_heel",
    ),
    {**_LIMBS, "pelvis": ("hip",), "thorax": ("neck",), "neck": ("nose",), "head": ("head",)},
)

# COCO-WholeBody's 133: COCO's 17 body keypoints, 6 foot, 68 face and 21 per hand (jin-s13/COCO-WholeBody
# README; mmpose configs/_base_/datasets/coco_wholebody.py). Only the body is read, as coco17: no
# face, hand or foot point is a Human3.6M joint (the ankles are the body's own).
WHOLEBODY133 = _format(
    "wholebody133",
    "COCO-WholeBody 133 keypoints (RTMW, DWPose, RTMPose wholebody); the body's 17 are read as coco17, "
    "the face, hands and feet are ignored",
    (
        *COCO17.joint_names,
        *_FEET,
        *(f"face_{i}" for i in range(68)),
        *(f"left_hand_{i}" for i in range(21)),
        *(f"right_hand_{i}" for i in range(21)),
    ),
    {**_LIMBS, **_COCO_TORSO},
)

# New formats go last: ModelInput.format_index counts in this order.
FORMATS: dict[str, KeypointFormat] = {
    f.name: f for f in (H36M17, MPII16, COCO17, BODY25, MEDIAPIPE33, COCO18, BODY25B, HALPE26, WHOLEBODY133)
}
DEFAULT_FORMAT = H36M17.name  # what a pose without a format is read as, on every transport and client
FORMAT_NAMES: tuple[str, ...] = tuple(FORMATS)  # ModelInput.format_index points into this
# Detector files' formats by joint count: OpenPose's people, and COCO-style keypoint lists (COCO-17,
# Halpe-26 / AlphaPose, COCO-WholeBody); a COCO-WholeBody annotation's parts, in its joints' order.
OPENPOSE_FORMATS = {len(f.joint_names): f.name for f in (COCO18, BODY25)}
FORMAT_BY_COUNT = {len(f.joint_names): f.name for f in (COCO17, HALPE26, WHOLEBODY133)}
WHOLEBODY_PARTS = ("keypoints", "foot_kpts", "face_kpts", "lefthand_kpts", "righthand_kpts")


def _check_points(fmt: KeypointFormat, points: np.ndarray, visible: np.ndarray, num: int) -> None:
    if points.ndim != 3 or points.shape[1:] != (num, 2):
        raise ValueError(f"expected {fmt.name} points of shape (N, {num}, 2), got {points.shape}")
    if visible.shape != points.shape[:2]:
        raise ValueError(f"expected visible of shape {points.shape[:2]}, got {visible.shape}")


@cache
def _gather(fmt: KeypointFormat) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per model joint: first and second source index (equal for one source), has a source, is a midpoint."""
    first = np.array([src[0] if src else 0 for src in fmt.sources])
    second = np.array([src[-1] if src else 0 for src in fmt.sources])
    has_source = np.array([bool(src) for src in fmt.sources])
    midpoint = np.array([len(src) == 2 for src in fmt.sources])
    return first, second, has_source, midpoint


def to_model_joints(
    fmt: KeypointFormat, points: np.ndarray, visible: np.ndarray
) -> tuple[FloatArray, BoolArray, BoolArray, BoolArray]:
    """Map a detector's keypoints onto the model's joints.

    points (N, K, 2) pixels, visible (N, K) bool -> points (N, 17, 2) float32, visible (N, 17),
    derived (N, 17: the joint is a midpoint), imputed (N, 17: no visible source, the model fills
    it in). A derived joint is visible only if all its sources are; joints that are not visible
    get coordinates 0 so the model input stays finite.
    """
    _check_points(fmt, points, visible, len(fmt.joint_names))
    first, second, has_source, midpoint = _gather(fmt)
    src_visible = visible.astype(bool)
    out_visible = src_visible[:, first] & src_visible[:, second] & has_source  # (N, 17)
    # Missing joints may hold NaN or inf: their sums are replaced by 0, never read. The sum is taken
    # in the wire's precision (float32 from gRPC stays float32) and cast to float32 once.
    with np.errstate(invalid="ignore", over="ignore"):
        pairs = points[:, first] + points[:, second]  # (N, 17, 2); a single source: 2 p
        out = np.where(out_visible[..., None], pairs / 2, 0.0).astype(np.float32, copy=False)  # (N, 17, 2)
    derived = np.broadcast_to(midpoint, out_visible.shape).copy()
    return out, out_visible, derived, ~out_visible


def from_model_joints(
    fmt: KeypointFormat, points17: np.ndarray, visible17: np.ndarray | None = None
) -> tuple[FloatArray, BoolArray]:
    """Build a detector's keypoints from the model's 17 joints (for tests and evaluation).

    points17 (N, 17, 2) -> points (N, K, 2) float32, visible (N, K). A source joint is filled
    only when a model joint maps to it alone; joints the model has no counterpart for (eyes,
    ears, toes) are NaN and not visible.
    """
    if visible17 is None:
        visible17 = np.ones(points17.shape[:2], dtype=bool)
    _check_points(H36M17, points17, visible17, len(MODEL_JOINTS))
    n = points17.shape[0]
    out = np.full((n, len(fmt.joint_names), 2), np.nan, dtype=np.float32)  # (N, K, 2)
    out_visible = np.zeros((n, len(fmt.joint_names)), dtype=bool)
    for j, src in enumerate(fmt.sources):
        if len(src) == 1:
            ok = visible17[:, j].astype(bool)
            out[ok, src[0]] = points17[ok, j]
            out_visible[:, src[0]] = ok
    return out, out_visible
