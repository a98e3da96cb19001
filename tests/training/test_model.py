"""Shapes and invariances of the RepNet generator, the critic and the KCS layer."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from repnet.core import skeleton
from repnet.train.config import RepNetConfig
from repnet.train.model import KCS, Critic, LiftingGraph, RepNet, normalize_keypoints
from tests.training.conftest import STANDING

TINY = RepNetConfig(width=32, critic_width=32, kcs_width=8)


def test_generator_shapes_and_root_at_origin() -> None:
    torch.manual_seed(0)
    pose, camera = RepNet(TINY)(torch.randn(5, 17, 2), torch.ones(5, 17))
    assert pose.shape == (5, 17, 3)
    assert camera.shape == (5, 2, 3)
    assert torch.all(pose[:, skeleton.ROOT] == 0)


def test_critic_scores_one_value_per_pose() -> None:
    assert Critic(TINY)(torch.randn(7, 17, 3)).shape == (7,)


def test_kcs_diagonal_holds_squared_bone_lengths() -> None:
    pose = torch.from_numpy(STANDING).float().unsqueeze(0)
    psi = KCS()(pose)[0]
    expected = [np.sum((STANDING[c] - STANDING[p]) ** 2) for p, c in skeleton.BONES]
    np.testing.assert_allclose(psi.diagonal().numpy(), expected, rtol=1e-5)
    assert psi.shape == (skeleton.NUM_BONES, skeleton.NUM_BONES)


def test_kcs_is_the_gram_matrix_of_the_bone_vectors() -> None:
    rng = np.random.default_rng(0)
    poses = STANDING[None] + rng.normal(0, 30, (3, 17, 3))
    psi = KCS()(torch.from_numpy(poses).float()).numpy()
    bones = np.stack([poses[:, c] - poses[:, p] for p, c in skeleton.BONES], axis=1)  # (N, B, 3)
    np.testing.assert_allclose(psi, bones @ bones.transpose(0, 2, 1), rtol=1e-4, atol=1e-2)  # Psi = B^T B


def test_normalize_keypoints_is_centred_unit_std_and_zero_for_missing() -> None:
    points = torch.tensor(STANDING[None, :, :2] * 0.3 + 500.0, dtype=torch.float32)
    visible = torch.ones(1, 17)
    visible[0, 3] = 0
    points[0, 3] = float("nan")
    out = normalize_keypoints(points, visible)
    vis = out[0, visible[0] > 0]
    torch.testing.assert_close(vis.mean(dim=0), torch.zeros(2), atol=1e-5, rtol=0)
    torch.testing.assert_close(vis.pow(2).mean(), torch.tensor(1.0), atol=1e-5, rtol=0)
    assert torch.all(out[0, 3] == 0)


def test_normalisation_removes_image_translation_and_scale() -> None:
    torch.manual_seed(0)
    graph = LiftingGraph(RepNet(TINY)).eval()
    points = torch.tensor(STANDING[None, :, :2] * 0.3 + 400.0, dtype=torch.float32)
    visible = torch.ones(1, 17)
    pose_a, _ = graph(points, visible)
    pose_b, _ = graph(points * 2.5 + 100.0, visible)
    torch.testing.assert_close(pose_a, pose_b, atol=1e-3, rtol=1e-4)


def test_masked_joint_values_cannot_change_the_output() -> None:
    torch.manual_seed(0)
    graph = LiftingGraph(RepNet(TINY)).eval()
    points = torch.tensor(STANDING[None, :, :2] * 0.3 + 400.0, dtype=torch.float32).repeat(3, 1, 1)
    visibility = torch.ones(3, 17)
    visibility[:, [7, 13]] = 0
    points[1, [7, 13]] = torch.tensor([[1e6, -1e6], [3.0, 4.0]])
    points[2, [7, 13]] = float("nan")
    pose, camera = graph(points, visibility)
    for i in (1, 2):  # equal up to float rounding (mm, and K in 1/mm)
        torch.testing.assert_close(pose[i], pose[0], atol=1e-3, rtol=1e-5)
        torch.testing.assert_close(camera[i], camera[0], atol=1e-7, rtol=1e-5)


def test_shared_trunk_feeds_both_branches_and_exports_the_same_contract() -> None:
    torch.manual_seed(0)
    config = dataclasses.replace(TINY, shared_trunk=True)
    generator = RepNet(config)
    names = {name.split(".")[0] for name, _ in generator.named_parameters()}
    assert names == {"trunk", "pose_branch", "camera_branch"}
    # The camera branch starts from the trunk's features, not from the input.
    assert generator.camera_branch[0].fc1.in_features == config.width
    pose, camera = LiftingGraph(generator).eval()(torch.randn(4, 17, 2) * 50 + 300, torch.ones(4, 17))
    assert pose.shape == (4, 17, 3) and camera.shape == (4, 2, 3)
    assert torch.all(pose[:, skeleton.ROOT] == 0)
    # A change of the trunk's weights moves both outputs.
    with torch.no_grad():
        generator.trunk[0].bias.add_(0.5)
    pose2, camera2 = LiftingGraph(generator).eval()(torch.randn(4, 17, 2) * 50 + 300, torch.ones(4, 17))
    assert not torch.allclose(pose, pose2) and not torch.allclose(camera, camera2)


def test_separate_branches_have_no_trunk_parameters() -> None:
    names = {name.split(".")[0] for name, _ in RepNet(TINY).named_parameters()}
    assert names == {"pose_branch", "camera_branch"}


def _mirrored_pixels(points: torch.Tensor, visible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The image flipped about x = 640, left and right joints swapped."""
    swap = list(skeleton.MIRROR)
    flipped = points[:, swap].clone()
    flipped[..., 0] = 1280.0 - flipped[..., 0]
    return flipped, visible[:, swap]


def test_mirror_average_answers_a_mirrored_input_with_the_mirrored_pose_and_camera() -> None:
    torch.manual_seed(0)
    generator = RepNet(TINY).eval()
    points = torch.tensor(STANDING[None, :, :2] * 0.3 + 400.0, dtype=torch.float32).repeat(3, 1, 1)
    points = points + torch.randn(points.shape) * 8
    visible = torch.ones(3, 17)
    visible[1, [3, 13]] = 0
    mirrored = _mirrored_pixels(points, visible)
    swap = list(skeleton.MIRROR)
    sign_pose = torch.tensor([-1.0, 1.0, 1.0])
    sign_camera = torch.tensor([[1.0, -1.0, -1.0], [-1.0, 1.0, 1.0]])
    averaged = LiftingGraph(generator, mirror_average=True).eval()
    pose, camera = averaged(points, visible)
    pose_m, camera_m = averaged(*mirrored)
    torch.testing.assert_close(pose_m, pose[:, swap] * sign_pose, atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(camera_m, camera * sign_camera, atol=1e-8, rtol=1e-5)
    # Without the average a random generator has no such symmetry; the average lies between
    # its answers to the input and to the mirror image.
    plain = LiftingGraph(generator).eval()
    pose_p, _ = plain(points, visible)
    pose_pm, _ = plain(*mirrored)
    assert not torch.allclose(pose_pm, pose_p[:, swap] * sign_pose, atol=1.0)
    torch.testing.assert_close(pose, (pose_p + pose_pm[:, swap] * sign_pose) / 2, atol=1e-3, rtol=1e-5)
