"""Known values of the weak-perspective camera: W' = K X and the scale s hidden in K."""

from __future__ import annotations

import pytest
import torch

from repnet.train.camera import camera_scale, masked_centre, project_weak_perspective
from tests.training.conftest import STANDING


def test_projection_is_k_times_x_for_every_joint() -> None:
    camera = torch.tensor([[[2.0, 0.0, 1.0], [0.0, -1.0, 3.0]]])
    pose = torch.tensor([[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [-1.0, 1.0, 0.5]]])
    expected = torch.tensor([[[5.0, 7.0], [0.0, 0.0], [-1.5, 0.5]]])
    torch.testing.assert_close(project_weak_perspective(camera, pose), expected)


def test_a_scaled_rotation_has_scale_s_and_k_kt_equal_to_s_squared_i() -> None:
    angle = torch.tensor(0.7)
    c, s = torch.cos(angle), torch.sin(angle)
    rows = torch.stack([torch.stack([c, -s, torch.tensor(0.0)]), torch.stack([s, c, torch.tensor(0.0)])])
    camera = torch.stack([1.5 * rows, 0.2 * rows])  # (2, 2, 3)
    torch.testing.assert_close(camera_scale(camera), torch.tensor([1.5, 0.2]))
    scale = camera_scale(camera)[:, None, None]
    torch.testing.assert_close(camera @ camera.transpose(1, 2), scale**2 * torch.eye(2).expand(2, 2, 2))


def test_masked_centre_centres_on_the_visible_joints_and_zeroes_the_hidden() -> None:
    points = torch.tensor(STANDING[None, :, :2], dtype=torch.float32) + 100.0
    visible = torch.ones(1, 17)
    visible[0, [3, 10]] = 0
    centred = masked_centre(points, visible)
    assert torch.all(centred[0, [3, 10]] == 0)
    torch.testing.assert_close(centred[0, visible[0] > 0].mean(dim=0), torch.zeros(2), atol=1e-4, rtol=0)


def test_the_camera_math_asserts_its_shapes() -> None:
    with pytest.raises(AssertionError, match=r"camera K \(N, 2, 3\)"):
        project_weak_perspective(torch.zeros(1, 3, 3), torch.zeros(1, 17, 3))
    with pytest.raises(AssertionError, match=r"pose X \(N, J, 3\)"):
        project_weak_perspective(torch.zeros(1, 2, 3), torch.zeros(1, 17, 2))
    with pytest.raises(AssertionError, match="visibility"):
        masked_centre(torch.zeros(2, 17, 2), torch.ones(2, 16))
