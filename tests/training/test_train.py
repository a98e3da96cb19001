"""A few training steps on tiny synthetic data: losses fall, checkpoints resume."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from training import train
from training.config import RepNetConfig, TrainConfig

TINY = RepNetConfig(width=64, critic_width=64, kcs_width=16)


def _config(data_dir: Path, out: Path, iterations: int) -> TrainConfig:
    return TrainConfig(
        data_dir=str(data_dir),
        out_dir=str(out),
        inputs="gt+sh",
        iterations=iterations,
        batch_size=64,
        critic_steps=2,
        lr=1e-3,
        lr_decay=1.0,
        val_size=200,
        val_every=20,
        log_every=10,
        checkpoint_every=20,
        threads=1,
    )


def _history(out: Path) -> list[dict[str, float]]:
    return [json.loads(line) for line in (out / "history.jsonl").read_text().splitlines()]


def test_training_steps_reduce_reprojection_and_camera_losses(synthetic_h36m: Path, tmp_path: Path) -> None:
    best = train.train(_config(synthetic_h36m, tmp_path, 80), TINY)
    history = _history(tmp_path)
    assert history[-1]["rep"] < 0.6 * history[0]["rep"]
    assert history[-1]["cam"] < history[0]["cam"]
    assert "val_gt_pa_mpjpe" in history[-1] and "val_sh_mpjpe" in history[-1]
    state = torch.load(best, weights_only=False)
    assert state["model_config"]["width"] == 64


def test_resume_continues_from_the_checkpoint(synthetic_h36m: Path, tmp_path: Path) -> None:
    train.train(_config(synthetic_h36m, tmp_path, 20), TINY)
    train.train(_config(synthetic_h36m, tmp_path, 40), TINY, resume=tmp_path / "last.pt")
    steps = [record["step"] for record in _history(tmp_path)]
    assert steps == [10, 20, 30, 40]
    assert torch.load(tmp_path / "last.pt", weights_only=False)["step"] == 40


def test_visibility_augmentation_hides_joints_but_never_the_root() -> None:
    config = TrainConfig(mask_prob=1.0, mask_max=3, spine_mask_prob=0.0)
    gen = torch.Generator().manual_seed(0)
    visible = train.augment_visibility(torch.ones(500, 17), config, gen)
    hidden = (visible == 0).sum(dim=1)
    assert hidden.min() >= 1 and hidden.max() <= 3
    assert torch.all(visible[:, 0] == 1)
