"""Format mix-up warnings: coco17 keypoints sent as h36m17 and back, on the bundled model."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.engine import result_columns
from service.formats import FORMATS, from_model_joints, lookalike_of, nose_height
from service.keypoints import Limits, PoseInput, prepare_poses
from service.lifter import Lifter
from service.lookalike import (
    PLAUSIBILITY_FLOOR,
    PLAUSIBILITY_WEIGHT,
    format_warnings,
    mixup_scores,
)
from tests.conftest import POSE_3D, project

YAWS = (-80.0, -30.0, 0.0, 25.0, 60.0, 90.0, 150.0)
NOSE_3D = POSE_3D[9]  # Human3.6M's neck/nose joint


def coco_pose(yaw: float, face: bool) -> tuple[np.ndarray, np.ndarray]:
    """(17, 2) COCO keypoints of the test person turned by `yaw`; eyes and ears placed around the
    nose when `face`, else missing (as from_model_joints leaves them)."""
    h36m = project(POSE_3D, yaw)
    points, present = from_model_joints(FORMATS["coco17"], h36m[None].astype(np.float32))
    points, present = points[0].astype(np.float64), present[0].copy()
    if face:  # left_eye, right_eye, left_ear, right_ear in the template frame (mm)
        offsets = np.array([[35, -35, -20], [-35, -35, -20], [75, -20, 60], [-75, -20, 60]], float)
        face_3d = np.vstack([POSE_3D, NOSE_3D + offsets])  # project() takes any number of joints
        points[1:5] = project(face_3d, yaw)[17:]
        present[1:5] = True
    return points, present


def h36m_pose(yaw: float) -> tuple[np.ndarray, np.ndarray]:
    return project(POSE_3D, yaw), np.ones(17, bool)


def warnings_of(lifter: Lifter, poses: list[PoseInput]) -> list[list[str]]:
    inputs = prepare_poses(poses, Limits(max_request_poses=64))
    return format_warnings(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible))


@pytest.mark.parametrize("face", [False, True], ids=["no_face", "face"])
def test_coco_keypoints_sent_as_h36m17_are_warned_about(trained: Lifter, face: bool) -> None:
    poses = [PoseInput(*coco_pose(yaw, face), None, "h36m17") for yaw in YAWS]
    for yaw, warnings in zip(YAWS, warnings_of(trained, poses), strict=True):
        assert len(warnings) == 1, yaw
        assert warnings[0].startswith("format: these keypoints look like coco17, not h36m17")
        assert 'send format "coco17"' in warnings[0]


def test_h36m_keypoints_sent_as_coco17_are_warned_about(trained: Lifter) -> None:
    poses = [PoseInput(*h36m_pose(yaw), None, "coco17") for yaw in YAWS]
    for yaw, warnings in zip(YAWS, warnings_of(trained, poses), strict=True):
        assert len(warnings) == 1 and "look like h36m17, not coco17" in warnings[0], yaw


def test_correctly_labelled_poses_get_no_warning(trained: Lifter) -> None:
    poses = [PoseInput(*h36m_pose(yaw), None, "h36m17") for yaw in YAWS]
    poses += [PoseInput(*coco_pose(yaw, face), None, "coco17") for yaw in YAWS for face in (False, True)]
    assert warnings_of(trained, poses) == [[]] * len(poses)


def test_mixed_batch_warns_only_the_mislabelled_poses(trained: Lifter) -> None:
    poses = [
        PoseInput(*h36m_pose(10.0), None, "h36m17"),
        PoseInput(*coco_pose(10.0, True), None, "h36m17"),
        PoseInput(*coco_pose(10.0, True), None, "coco17"),
        PoseInput(*h36m_pose(10.0), None, "coco17"),
        PoseInput(project(POSE_3D, 10.0)[[3, 2, 1, 4, 5, 6, 0, 8, 9, 10, 16, 15, 14, 11, 12, 13]],
                  np.ones(16, bool), None, "mpii16"),
    ]  # fmt: skip
    flagged = [bool(w) for w in warnings_of(trained, poses)]
    assert flagged == [False, True, False, True, False]


def test_only_formats_of_the_same_joint_count_are_lookalikes() -> None:
    assert lookalike_of("h36m17") == "coco17" and lookalike_of("coco17") == "h36m17"
    assert lookalike_of("mpii16") is None and lookalike_of("body25") is None
    assert lookalike_of("mediapipe33") is None


def test_nose_height_reads_joint_0_against_the_coco_torso() -> None:
    coco, present = coco_pose(0.0, False)
    h36m, all_present = h36m_pose(0.0)
    heights = nose_height(np.stack([coco, h36m]), np.stack([present, all_present]))
    assert heights[0] > 0.2 and heights[1] < -0.3  # a nose above the shoulders; a pelvis below
    present[5] = False  # a shoulder missing: no reading
    assert np.isnan(nose_height(coco[None], present[None])[0])


def test_an_implausible_pose_adds_to_the_score(lifter: Lifter) -> None:
    poses = [PoseInput(*h36m_pose(0.0), None, "h36m17"), PoseInput(*coco_pose(0.0, True), None, "h36m17")]
    inputs = prepare_poses(poses, Limits())
    prediction = lifter.lift(inputs.keypoints_2d, inputs.visible)
    base = mixup_scores(inputs, replace(prediction, plausibility=None))
    low = np.full(2, PLAUSIBILITY_FLOOR / 2, np.float32)
    high = np.full(2, 0.5, np.float32)
    with_low = mixup_scores(inputs, replace(prediction, plausibility=low))
    np.testing.assert_allclose(with_low, base + PLAUSIBILITY_WEIGHT)
    np.testing.assert_allclose(mixup_scores(inputs, replace(prediction, plausibility=high)), base)


def test_reply_columns_carry_the_warnings(trained: Lifter) -> None:
    poses = [PoseInput(*coco_pose(0.0, True), None, "h36m17"), PoseInput(*h36m_pose(0.0), None, "h36m17")]
    inputs = prepare_poses(poses, Limits())
    columns = result_columns(inputs, trained.lift(inputs.keypoints_2d, inputs.visible))
    assert len(columns["warnings"][0]) == 1 and columns["warnings"][1] == []
