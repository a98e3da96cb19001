"""Real detector errors on synthetic 2D: scaled by the pose's size, with the detector's hidden joints,
in the asked share of poses, and nothing drawn when that share is 0; graded bone rescaling."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from repnet.train import data
from repnet.train.augment import with_detector_errors
from repnet.train.config import TrainConfig


def _pool(errors: np.ndarray, seen: np.ndarray) -> data.TrainingPool:
    empty = np.zeros((1, 17, 3), np.float32)
    return data.TrainingPool(empty, np.zeros((1, 17, 2), np.float32), np.ones((1, 17), np.float32),
                             detector_errors=errors, detector_visible=seen)  # fmt: skip


def test_detector_errors_move_joints_by_the_poses_size_and_hide_what_the_detector_missed() -> None:
    errors = np.zeros((1, 17, 2), np.float32)
    errors[0, 13] = [0.5, 0.0]  # the left wrist half a spread to the right
    seen = np.ones((1, 17), np.float32)
    seen[0, 7] = 0.0  # no spine
    rng = np.random.default_rng(0)
    pixels = torch.from_numpy(rng.normal(500, 80, (6, 17, 2)).astype(np.float32))
    pixels[3:] = pixels[:3] * 2.0  # the same poses twice as large
    config = TrainConfig(detector_error_prob=1.0, detector_error_min=1.0, detector_error_max=1.0)
    moved, visible = with_detector_errors(
        pixels, torch.ones(6, 17), _pool(errors, seen), config, torch.Generator()
    )
    shift = (moved - pixels)[:, 13, 0].numpy()
    spread = (pixels - pixels.mean(dim=1, keepdim=True)).pow(2).mean(dim=(1, 2)).sqrt().numpy()
    np.testing.assert_allclose(shift, 0.5 * spread, rtol=1e-5)
    np.testing.assert_allclose(shift[3:], 2 * shift[:3], rtol=1e-5)
    assert torch.equal((moved - pixels)[:, [j for j in range(17) if j != 13]], torch.zeros(6, 16, 2))
    assert (visible[:, 7] == 0).all() and (visible[:, :7] == 1).all()


@pytest.mark.parametrize("share", [0.0, 0.5])
def test_only_the_asked_share_of_poses_changes_and_none_draws_nothing(share: float) -> None:
    pool = _pool(np.full((4, 17, 2), 0.1, np.float32), np.ones((4, 17), np.float32))
    pixels = torch.randn(4000, 17, 2) * 50 + 500
    generator = torch.Generator().manual_seed(1)
    config = dataclasses.replace(TrainConfig(), detector_error_prob=share)
    moved, _ = with_detector_errors(pixels, torch.ones(4000, 17), pool, config, generator)
    changed = (moved != pixels).any(dim=(1, 2)).float().mean().item()
    assert abs(changed - share) < 0.03
    if share == 0.0:  # the generator is untouched: runs without detector errors stay bit for bit
        assert torch.equal(generator.get_state(), torch.Generator().manual_seed(1).get_state())
