"""Format mix-up warnings: coco17 keypoints sent as h36m17 and back, on the bundled model."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.core.format_hints import lookalike_of, nose_height
from repnet.core.formats import FORMATS, from_model_joints
from repnet.core.inputs import ModelInput, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.core.lookalike import PLAUSIBILITY_FLOOR, PLAUSIBILITY_WEIGHT, mixup_scores
from repnet.runtime.lifter import Lifter
from repnet.runtime.replies import Replies, build_replies
from repnet.server.app import limits_of
from repnet.server.config import Settings
from tests.conftest import POSE_3D, project

LIMITS = limits_of(Settings())

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


def replies_of(lifter: Lifter, poses: list[PoseInput]) -> tuple[ModelInput, Replies]:
    inputs = prepare_poses(poses, LIMITS).check()
    return inputs, build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible))


def warnings_of(lifter: Lifter, poses: list[PoseInput]) -> list[list[str]]:
    return list(replies_of(lifter, poses)[1].columns["warnings"])


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
    inputs, replies = replies_of(lifter, poses)
    error = replies.columns["reprojection_error_px"]
    base = mixup_scores(inputs, error, None)
    low = np.full(2, PLAUSIBILITY_FLOOR / 2, np.float32)
    high = np.full(2, 0.5, np.float32)
    np.testing.assert_allclose(mixup_scores(inputs, error, low), base + PLAUSIBILITY_WEIGHT)
    np.testing.assert_allclose(mixup_scores(inputs, error, high), base)


def test_replies_carry_the_warnings(trained: Lifter) -> None:
    poses = [PoseInput(*coco_pose(0.0, True), None, "h36m17"), PoseInput(*h36m_pose(0.0), None, "h36m17")]
    rows = replies_of(trained, poses)[1].to_json()
    assert len(rows[0]["warnings"]) == 1 and rows[1]["warnings"] == []
