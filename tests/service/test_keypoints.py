"""Input rules and format conversion of repnet.core.keypoints, without a transport."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from repnet.core.errors import InvalidKeypoints
from repnet.core.formats import FORMATS, from_model_joints
from repnet.core.inputs import Limits, ModelInput, PoseInput
from repnet.core.keypoints import check_request, check_threshold, prepare_poses
from repnet.server.app import limits_of
from repnet.server.config import Settings
from tests.conftest import POSE_2D

LIMITS = limits_of(Settings())


def pose(
    points: np.ndarray = POSE_2D,
    present: np.ndarray | None = None,
    confidence: list[float] | None = None,
    format: str = "h36m17",
) -> PoseInput:
    mask = np.ones(len(points), bool) if present is None else present
    return PoseInput(
        points.astype(np.float64), mask, None if confidence is None else np.array(confidence), format
    )


def violations(*poses: PoseInput, limits: Limits = LIMITS) -> list[str]:
    with pytest.raises(InvalidKeypoints) as info:
        prepare_poses(poses, limits).check()
    return [v.message for v in info.value.violations]


def model_input(poses: list[PoseInput], limits: Limits = LIMITS) -> ModelInput:
    return prepare_poses(poses, limits).check()


def test_valid_poses_become_model_input() -> None:
    out = model_input([pose(), pose(POSE_2D + 5)])
    assert out.keypoints_2d.shape == (2, 17, 2) and out.keypoints_2d.dtype == np.float32
    np.testing.assert_allclose(out.keypoints_2d[1], POSE_2D + 5, rtol=1e-6)
    assert out.visible.all() and not out.imputed.any() and not out.derived.any()


def test_missing_and_unconfident_joints_are_imputed_with_zero_coordinates() -> None:
    present = np.ones(17, bool)
    present[3] = False
    points = POSE_2D.copy()
    points[3] = np.nan
    confidence = [0.9] * 17
    confidence[12] = 0.1
    out = model_input([pose(points, present, confidence)], replace(LIMITS, confidence_threshold=0.2))
    assert np.flatnonzero(out.imputed[0]).tolist() == [3, 12]
    assert (out.keypoints_2d[0, [3, 12]] == 0).all() and np.isfinite(out.keypoints_2d).all()


def test_joints_of_unused_detector_points_are_not_checked() -> None:
    points, visible = from_model_joints(FORMATS["coco17"], POSE_2D[None])
    points[0, 1:5] = np.nan  # eyes and ears: the model uses none of them
    visible[0, 1:5] = True
    out = model_input([pose(points[0], visible[0], format="coco17")])
    assert out.derived[0].tolist() == [j in (0, 8) for j in range(17)]


def test_poses_of_several_formats_keep_their_order() -> None:
    mpii, mpii_visible = from_model_joints(FORMATS["mpii16"], (POSE_2D + 40)[None])
    out = model_input([pose(), pose(mpii[0], mpii_visible[0], format="mpii16"), pose(POSE_2D + 80)])
    np.testing.assert_allclose(
        out.keypoints_2d[:, 0], [POSE_2D[0], POSE_2D[0] + 40, POSE_2D[0] + 80], rtol=1e-6
    )
    assert out.imputed[1].tolist() == [j == 7 for j in range(17)] and not out.imputed[[0, 2]].any()


def test_every_broken_rule_is_listed_with_pose_and_joint() -> None:
    bad = POSE_2D.copy()
    bad[10] = [np.inf, 0]
    found = violations(pose(), pose(bad), pose(POSE_2D[:3]), pose(format="vicon"))
    assert found == [
        "poses[1].keypoints[10] (head): coordinates must be finite numbers, got [inf, 0]",
        "poses[2].keypoints: format h36m17 has 17 joints, got 3",
        "poses[3].format: unknown format 'vicon'; expected one of " + ", ".join(FORMATS),
    ]


def test_minimum_visible_joints_is_configurable() -> None:
    present = np.arange(17) < 4
    fewer = replace(LIMITS, min_visible_joints=5)
    assert "4 of 17 model joints" in violations(pose(present=present), limits=fewer)[0]
    assert model_input([pose(present=present)], replace(LIMITS, min_visible_joints=4)).visible.sum() == 4


def test_each_pose_gets_its_own_violations_and_the_valid_ones_their_input() -> None:
    """No retry pose by pose: the valid poses of a request with invalid ones are converted at once,
    and each invalid pose is named by its own violations (relative to the pose), whatever rule
    another pose of its format broke."""
    bad = POSE_2D.copy()
    bad[10] = [np.nan, 0]
    prepared = prepare_poses(
        [pose(), pose(bad), pose(present=np.arange(17) < 3), pose(format="vicon"), pose(POSE_2D + 9)], LIMITS
    )
    assert [[v.field for v in found] for found in prepared.violations] == [
        [],
        ["keypoints[10]"],
        ["keypoints"],
        ["format"],
        [],
    ]
    assert [v.code for found in prepared.violations for v in found] == ["non_finite", "too_few_visible",
                                                                         "unknown_format"]  # fmt: skip
    np.testing.assert_allclose(prepared.inputs.keypoints_2d, np.stack([POSE_2D, POSE_2D + 9]), rtol=1e-6)
    alone = prepare_poses([pose(POSE_2D + 9)], LIMITS).inputs
    np.testing.assert_array_equal(prepared.inputs.keypoints_2d[1], alone.keypoints_2d[0])


def test_a_pose_may_bring_its_own_confidence_threshold() -> None:
    confidence = [0.5] * 17
    sure, unsure = (replace(pose(confidence=confidence), confidence_threshold=t) for t in (0.4, 0.6))
    prepared = prepare_poses([sure, unsure, pose(confidence=confidence)], LIMITS, threshold=0.6)
    assert prepared.inputs.visible[0].all()  # its own threshold wins over the request's
    assert [v.code for v in prepared.violations[1]] == ["too_few_visible"]
    assert [v.code for v in prepared.violations[2]] == ["too_few_visible"]


def test_request_rules_name_the_batch() -> None:
    with pytest.raises(InvalidKeypoints, match=r"^poses: the batch is empty"):
        check_request(0, None, LIMITS)
    with pytest.raises(InvalidKeypoints, match=r"^poses: 17 poses in one request, the limit is 16$"):
        check_request(17, None, replace(LIMITS, max_request_poses=16))


@pytest.mark.parametrize("threshold", [-0.1, 1.01, float("nan")])
def test_threshold_outside_unit_interval_is_rejected(threshold: float) -> None:
    with pytest.raises(InvalidKeypoints, match="confidence_threshold: must be a number in"):
        check_threshold(threshold, LIMITS)


def test_long_lists_of_violations_are_cut_in_the_message() -> None:
    points = np.full((17, 2), np.nan)
    with pytest.raises(InvalidKeypoints) as info:
        prepare_poses([pose(points)], LIMITS).check()
    assert len(info.value.violations) == 17 and str(info.value).endswith("; and 7 more")


@pytest.mark.parametrize("name", ["mpii16", "coco18", "halpe26", "mediapipe33", "wholebody133"])
def test_a_pose_sent_without_its_format_is_told_which_format_it_looks_like(name: str) -> None:
    points, present = from_model_joints(FORMATS[name], POSE_2D[None])
    (message,) = violations(pose(np.nan_to_num(points[0]), present[0]))
    count = len(FORMATS[name].joint_names)
    assert f"got {count}; {count} joints: this looks like {name} ({FORMATS[name].description})" in message
    assert message.endswith(f'send format "{name}"')


@pytest.mark.parametrize("name", ["body25", "body25b"])
def test_a_25_joint_pose_without_its_format_is_told_both_25_joint_formats(name: str) -> None:
    """BODY_25 and BODY_25B have the same count and nothing in the joints tells them apart: both are named."""
    points, present = from_model_joints(FORMATS[name], POSE_2D[None])
    (message,) = violations(pose(np.nan_to_num(points[0]), present[0]))
    assert "25 joints: this looks like body25 (OpenPose BODY_25) or body25b (OpenPose BODY_25B" in message
    assert message.endswith('send format "body25" or "body25b"')
    (message,) = violations(pose(np.nan_to_num(points[0]), present[0], format="mpii16"))
    assert "format mpii16 has 16 joints, got 25; 25 joints: this looks like body25 (" in message


def test_a_correctly_labelled_pose_gets_no_hint_and_a_17_joint_mix_up_is_told_by_geometry() -> None:
    coco, present = from_model_joints(FORMATS["coco17"], POSE_2D[None])
    coco = np.where(present[0][:, None], coco[0], POSE_2D[:17])  # eyes and ears: anywhere near the head
    coco[:5] = POSE_2D[9] + np.array([[0, 0], [-8, -6], [8, -6], [-15, 0], [15, 0]])  # the face
    assert "looks like coco17" in violations(pose(coco, format="mpii16"))[0]
    assert "looks like h36m17" in violations(pose(POSE_2D, format="mpii16"))[0]
    assert model_input([pose(coco, format="coco17"), pose(POSE_2D)]).keypoints_2d.shape == (2, 17, 2)


@pytest.mark.parametrize(("given", "means"), [("openpose", "body25"), ("BODY_25", "body25"),
                                              ("MediaPipe", "mediapipe33"), ("yolo", "coco17"),
                                              ("OpenPose-COCO", "coco18"), ("BODY_25B", "body25b"),
                                              ("AlphaPose", "halpe26"), ("COCO-WholeBody", "wholebody133"),
                                              ("RTMW", "wholebody133")])  # fmt: skip
def test_a_format_alias_names_the_format_it_means(given: str, means: str) -> None:
    (message,) = violations(pose(format=given))
    assert f"unknown format {given!r}" in message and f'send format "{means}"' in message


def test_exact_zero_joints_without_confidence_are_missing_and_counted() -> None:
    points = POSE_2D.copy()
    points[[3, 13]] = 0.0  # OpenPose's 0, 0 for a joint it did not find
    got = model_input([pose(points), pose(points, confidence=[1.0] * 17)])
    assert got.visible[0].tolist() == [j not in (3, 13) for j in range(17)]
    assert got.visible[1].all()  # with a confidence, the threshold decides
    assert got.zeroed.tolist() == [2, 0]
    same = model_input([pose(POSE_2D, present=np.array([j not in (3, 13) for j in range(17)]))])
    np.testing.assert_array_equal(got.keypoints_2d[0], same.keypoints_2d[0])
