"""Known values of the reprojection, camera and Wasserstein losses."""

from __future__ import annotations

import pytest
import torch

from repnet.core import skeleton
from repnet.train.camera import camera_scale, masked_centre, project_weak_perspective
from repnet.train.losses import (
    bone_lengths,
    bone_loss,
    camera_loss,
    critic_loss,
    gradient_penalty,
    reprojection_loss,
)
from tests.training.conftest import STANDING


def _rotation(angle: float) -> torch.Tensor:
    c, s = torch.cos(torch.tensor(angle)), torch.sin(torch.tensor(angle))
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_camera_loss_is_zero_for_scaled_orthographic_camera() -> None:
    camera = (2.7 * _rotation(0.4)[:2]).unsqueeze(0)
    assert camera_loss(camera).item() < 1e-5
    torch.testing.assert_close(camera_scale(camera), torch.tensor([2.7]))


def test_camera_loss_is_positive_for_skewed_camera() -> None:
    camera = torch.tensor([[[1.0, 0.0, 0.0], [0.5, 2.0, 0.0]]])
    # K K^T = [[1, .5], [.5, 4.25]], trace 5.25: (2/5.25) K K^T - I by hand.
    kkt = torch.tensor([[1.0, 0.5], [0.5, 4.25]]) * (2 / 5.25) - torch.eye(2)
    torch.testing.assert_close(camera_loss(camera), kkt.norm())


def test_reprojection_loss_is_zero_for_exact_projection_with_any_translation() -> None:
    pose = torch.tensor(STANDING, dtype=torch.float32).unsqueeze(0) / 1000
    camera = (3.0 * _rotation(0.8)[:2]).unsqueeze(0)
    visible = torch.ones(1, 17)
    w = masked_centre(project_weak_perspective(camera, pose) + torch.tensor([5.0, -2.0]), visible)
    assert reprojection_loss(w, visible, pose, camera).item() < 1e-4


def _two_joints_missing() -> tuple[torch.Tensor, ...]:
    """A pose, its camera, a mask hiding joints 3 and 13, the observed W, and the pose with the
    hidden joints moved anywhere (as a generator may hallucinate them)."""
    pose = torch.tensor(STANDING, dtype=torch.float32).unsqueeze(0) / 1000
    camera = (3.0 * _rotation(0.8)[:2]).unsqueeze(0)
    visible = torch.ones(1, 17)
    visible[0, [3, 13]] = 0
    w = masked_centre(project_weak_perspective(camera, pose), visible)
    moved = pose.clone()
    moved[0, [3, 13]] += 0.5
    return pose, camera, visible, w, moved


def test_reprojection_loss_ignores_missing_joints() -> None:
    _, camera, visible, w, moved = _two_joints_missing()
    assert reprojection_loss(w, visible, moved, camera).item() < 1e-4
    moved[0, 5] += 0.5
    assert reprojection_loss(w, visible, moved, camera).item() > 0.1


def test_gradient_penalty_is_zero_for_a_unit_slope_critic() -> None:
    direction = torch.randn(17, 3)
    direction /= direction.norm()

    def critic(x: torch.Tensor) -> torch.Tensor:
        return (x * direction).sum(dim=(1, 2))

    real, fake = torch.randn(8, 17, 3), torch.randn(8, 17, 3)
    assert gradient_penalty(critic, real, fake).item() < 1e-10
    loss, wasserstein = critic_loss(critic, real, fake, 10.0)
    torch.testing.assert_close(loss, -wasserstein, atol=1e-5, rtol=0)


def test_l1_camera_loss_is_zero_for_scaled_orthographic_camera_and_sums_entries() -> None:
    camera = (0.6 * _rotation(-1.1)[:2]).unsqueeze(0)
    assert camera_loss(camera, "l1").item() < 1e-5
    skewed = torch.tensor([[[1.0, 0.0, 0.0], [0.5, 2.0, 0.0]]])
    residual = torch.tensor([[1.0, 0.5], [0.5, 4.25]]) * (2 / 5.25) - torch.eye(2)
    torch.testing.assert_close(camera_loss(skewed, "l1"), residual.abs().sum())


def test_l1_reprojection_is_weighted_over_2j_and_ignores_missing_joints() -> None:
    pose, camera, visible, w, moved = _two_joints_missing()
    assert reprojection_loss(w, visible, moved, camera, "l1").item() < 1e-5
    # One visible joint (the left knee, weight 1) off by d in x: centring moves the 15 visible
    # joints by d / 15, so the knee is off by 14 d / 15 and every other visible joint by d / 15,
    # each weighted (the pelvis by 0); the sum is divided by 2J.
    shifted = w.clone()
    shifted[0, 5, 0] += 0.3
    weights = torch.tensor(skeleton.REPROJECTION_WEIGHTS)
    shift_share = 0.3 / 15 * float((weights * visible[0])[[j for j in range(17) if j != 5]].sum())
    expected = (0.3 * 14 / 15 + shift_share) / (2 * 17)
    got = reprojection_loss(masked_centre(shifted, visible), visible, pose, camera, "l1").item()
    assert abs(got - expected) < 1e-5


def test_pose_weights_follow_the_authors_code() -> None:
    weights = dict(zip(skeleton.JOINT_NAMES, skeleton.REPROJECTION_WEIGHTS, strict=True))
    assert weights["pelvis"] == 0.0 and weights["neck"] == weights["head"] == 0.1
    assert all(w == 1.0 for name, w in weights.items() if name not in ("pelvis", "neck", "head"))


def test_unknown_norms_are_refused() -> None:
    camera = torch.ones(1, 2, 3)
    with pytest.raises(ValueError, match="camera norm"):
        camera_loss(camera, "l2")
    with pytest.raises(ValueError, match="reprojection norm"):
        reprojection_loss(torch.zeros(1, 17, 2), torch.ones(1, 17), torch.zeros(1, 17, 3), camera, "huber")


def test_bone_loss_is_zero_at_the_mean_skeleton_and_grows_with_a_stretched_limb() -> None:
    pose = torch.tensor(STANDING, dtype=torch.float32).unsqueeze(0) / 1000
    lengths = bone_lengths(pose)[0]
    assert lengths.shape == (skeleton.NUM_BONES,)
    torch.testing.assert_close(lengths[skeleton.BONES.index((4, 5))], (pose[0, 5] - pose[0, 4]).norm())
    assert bone_loss(pose, lengths).item() < 1e-5
    stretched = pose.clone()
    stretched[0, 6] += 0.3 * (pose[0, 6] - pose[0, 5])  # the left shin 30 % longer
    shin = (pose[0, 6] - pose[0, 5]).norm().item()
    assert abs(bone_loss(stretched, lengths).item() - 0.3 * shin / skeleton.NUM_BONES) < 1e-5


def test_the_losses_assert_their_shapes() -> None:
    camera = torch.zeros(2, 2, 3)
    with pytest.raises(AssertionError, match=r"pose X \(N, J, 3\)"):
        reprojection_loss(torch.zeros(2, 17, 2), torch.ones(2, 17), torch.zeros(2, 16, 3), camera)
    with pytest.raises(AssertionError, match=r"camera K \(N, 2, 3\)"):
        camera_loss(torch.zeros(2, 3, 2))
    with pytest.raises(AssertionError, match="fake poses"):
        critic_loss(lambda x: x.sum(dim=(1, 2)), torch.zeros(4, 17, 3), torch.zeros(3, 17, 3), 10.0)
