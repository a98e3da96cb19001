"""Input rules and format conversion of service.keypoints, without a transport."""

from __future__ import annotations

import numpy as np
import pytest

from service.errors import InvalidKeypoints
from service.formats import FORMATS, from_model_joints
from service.keypoints import Limits, PoseInput, check_threshold, prepare_poses
from tests.conftest import POSE_2D


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


def violations(*poses: PoseInput, limits: Limits | None = None) -> list[str]:
    with pytest.raises(InvalidKeypoints) as info:
        prepare_poses(poses, limits or Limits())
    return [v.message for v in info.value.violations]


def test_valid_poses_become_model_input() -> None:
    out = prepare_poses([pose(), pose(POSE_2D + 5)], Limits())
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
    out = prepare_poses([pose(points, present, confidence)], Limits(confidence_threshold=0.2))
    assert np.flatnonzero(out.imputed[0]).tolist() == [3, 12]
    assert (out.keypoints_2d[0, [3, 12]] == 0).all() and np.isfinite(out.keypoints_2d).all()


def test_joints_of_unused_detector_points_are_not_checked() -> None:
    points, visible = from_model_joints(FORMATS["coco17"], POSE_2D[None])
    points[0, 1:5] = np.nan  # eyes and ears: the model uses none of them
    visible[0, 1:5] = True
    out = prepare_poses([pose(points[0], visible[0], format="coco17")], Limits())
    assert out.derived[0].tolist() == [j in (0, 8) for j in range(17)]


def test_poses_of_several_formats_keep_their_order() -> None:
    mpii, mpii_visible = from_model_joints(FORMATS["mpii16"], (POSE_2D + 40)[None])
    out = prepare_poses(
        [pose(), pose(mpii[0], mpii_visible[0], format="mpii16"), pose(POSE_2D + 80)], Limits()
    )
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
    assert "4 of 17 model joints" in violations(pose(present=present), limits=Limits(min_visible_joints=5))[0]
    assert prepare_poses([pose(present=present)], Limits(min_visible_joints=4)).visible.sum() == 4


def test_stream_frames_are_named_pose() -> None:
    with pytest.raises(InvalidKeypoints, match=r"^pose.keypoints: format h36m17 has 17 joints, got 2$"):
        prepare_poses([pose(POSE_2D[:2])], Limits(), prefix="pose")


@pytest.mark.parametrize("threshold", [-0.1, 1.01, float("nan")])
def test_threshold_outside_unit_interval_is_rejected(threshold: float) -> None:
    with pytest.raises(InvalidKeypoints, match="confidence_threshold: must be a number in"):
        check_threshold(threshold, Limits())


def test_long_lists_of_violations_are_cut_in_the_message() -> None:
    points = np.full((17, 2), np.nan)
    with pytest.raises(InvalidKeypoints) as info:
        prepare_poses([pose(points)], Limits())
    assert len(info.value.violations) == 17 and str(info.value).endswith("; and 7 more")
