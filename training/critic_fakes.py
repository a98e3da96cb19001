"""What a critic-only stage judges (TrainConfig.critic_fakes): the fake poses of its next update,
drawn from the Trainer's pool, generator and random generator."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from training.augment import augment_visibility, corrupt_poses, rescale_bones
from training.model import normalize_keypoints

if TYPE_CHECKING:
    from training.trainer import Trainer


def generator(trainer: Trainer) -> torch.Tensor | None:
    """Fakes of the frozen generator: critic_step generates fresh poses for every update."""
    return None


def corrupted(trainer: Trainer) -> torch.Tensor:
    """Real poses with a limb stretched or shrunk, joints swapped or jittered (corrupt_poses)."""
    return corrupt_poses(trainer.real_batch(trainer.config.batch_size), trainer.gen)


def _answers(trainer: Trainer, clean: bool) -> tuple[torch.Tensor | None, torch.Tensor]:
    """The frozen generator's answers to batch_size frames of the pool's 2D (GT projections and
    detections): with N(0, sigma) px noise, sigma ~ U(0, critic_noise_px) per pose, and
    augment_visibility's hidden joints; with clean, also to the same 2D as it is (else None)."""
    config, device, gen = trainer.config, trainer.device, trainer.gen
    n = config.batch_size
    idx = torch.randint(0, trainer.pool.points_2d.shape[0], (n,), generator=gen).numpy()
    pixels = torch.from_numpy(trainer.pool.points_2d[idx]).to(device)
    seen = torch.from_numpy(trainer.pool.visible[idx]).to(device)
    visible = augment_visibility(seen, config, gen)
    sigma = config.critic_noise_px * torch.rand(n, 1, 1, generator=gen, device=device)
    noisy = pixels + sigma * torch.randn(pixels.shape, generator=gen, device=device)
    with torch.no_grad():
        answers, _ = trainer.generate(normalize_keypoints(noisy, visible), visible)
        if not clean:
            return None, answers
        clean_answers, _ = trainer.generate(normalize_keypoints(pixels, seen), seen)
    return clean_answers, answers


def _corrupted_share(trainer: Trainer, n: int) -> torch.Tensor:
    """(n, 1, 1) True for the poses of a batch that are corrupted real ones (critic_corrupted_share)."""
    draw = torch.rand(n, generator=trainer.gen, device=trainer.device)
    return (draw < trainer.config.critic_corrupted_share)[:, None, None]


def lifted(trainer: Trainer) -> torch.Tensor:
    """The generator's answers to noisy 2D (_answers); in a critic_corrupted_share of the batch,
    corrupted real poses instead."""
    _, lifted = _answers(trainer, clean=False)
    broken = corrupted(trainer)
    return torch.where(_corrupted_share(trainer, len(lifted)), broken, lifted)


def paired(trainer: Trainer) -> torch.Tensor:
    """Pairs that differ only in what broke the fake: the generator's answer to a frame's 2D as
    it is (real side) and to the same 2D with noise and hidden joints (fake side, _answers); in a
    critic_corrupted_share of the batch, a real pose and its corrupted copy instead. The critic
    learns what noise does to the generator's answers, not the generator's own signature, which
    both sides share; sets trainer.reals for the next critic step."""
    clean, noisy = _answers(trainer, clean=True)
    assert clean is not None
    real = trainer.real_batch(len(noisy))
    corrupted = corrupt_poses(real, trainer.gen)
    take = _corrupted_share(trainer, len(noisy))
    trainer.reals = torch.where(take, real, clean)
    return torch.where(take, corrupted, noisy)


def graded(trainer: Trainer) -> torch.Tensor:
    """Real poses with every bone 1 + N(0, sigma) times as long, sigma ~ U(0, critic_bone_sigma)
    per pose (rescale_bones); in a critic_corrupted_share of the batch, corrupt_poses instead."""
    n, gen = trainer.config.batch_size, trainer.gen
    real = trainer.real_batch(n)
    sigma = trainer.config.critic_bone_sigma * torch.rand(n, generator=gen, device=trainer.device)
    graded, corrupted = rescale_bones(real, sigma, gen), corrupt_poses(real, gen)
    return torch.where(_corrupted_share(trainer, n), corrupted, graded)


# critic_fakes -> the source of the critic-only stage's fakes.
SOURCES: dict[str, Callable[[Trainer], torch.Tensor | None]] = {
    "generator": generator,
    "corrupted": corrupted,
    "lifted": lifted,
    "paired": paired,
    "graded": graded,
}
