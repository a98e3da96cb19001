"""Known values of the reprojection, camera and Wasserstein losses."""

from __future__ import annotations

import torch

from tests.training.conftest import STANDING
from training.camera import camera_scale, masked_centre, project_weak_perspective
from training.losses import camera_loss, critic_loss, gradient_penalty, reprojection_loss


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


def test_reprojection_loss_ignores_missing_joints() -> None:
    pose = torch.tensor(STANDING, dtype=torch.float32).unsqueeze(0) / 1000
    camera = (3.0 * _rotation(0.8)[:2]).unsqueeze(0)
    visible = torch.ones(1, 17)
    visible[0, [3, 13]] = 0
    w = masked_centre(project_weak_perspective(camera, pose), visible)
    moved = pose.clone()
    moved[0, [3, 13]] += 0.5  # hallucinated joints may go anywhere
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
