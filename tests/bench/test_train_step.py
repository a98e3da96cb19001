"""bench.train_step: the FLOP count of a step and the figures it prints."""

from __future__ import annotations

import pytest
import torch

from bench import train_step
from repnet.train.config import RepNetConfig, TrainConfig

TINY = RepNetConfig(width=32, critic_width=16, kcs_width=16)


def test_matmul_flops_count_a_known_product() -> None:
    a, b = torch.randn(8, 5), torch.randn(5, 3)
    with train_step.MatmulFlops() as counter:
        a @ b
        torch.bmm(torch.randn(2, 4, 6), torch.randn(2, 6, 7))
    assert counter.flops == 2 * 8 * 5 * 3 + 2 * 2 * 4 * 6 * 7


def test_measure_reports_samples_and_flops_of_a_step_with_the_gradient_penalty() -> None:
    recipe = train_step.Recipe("tiny 1:1", TrainConfig(batch_size=16, critic_steps=1), TINY)
    row = train_step.measure(recipe, seconds=0.05)
    assert row["samples_per_s"] > 0 and row["ms_per_step"] > 0
    # One generator step (forward and backward) alone costs more than 6 x the generator's MACs per
    # sample; the critic step with its double backward adds to it.
    generator_macs = 51 * 32 + 4 * 32 * 32 + 32 * 51 + 51 * 32 + 4 * 32 * 32 + 32 * 6
    assert float(row["gflop_per_step"]) * 1e9 > 16 * 2 * generator_macs


def test_profile_prints_the_ops_of_the_step(capsys: pytest.CaptureFixture[str]) -> None:
    recipe = train_step.Recipe("tiny warm start", TrainConfig(batch_size=16, warm_start_steps=10**9), TINY)
    train_step.profile(recipe, steps=2)
    out = capsys.readouterr().out
    assert "profile of 2 steps: tiny warm start" in out
    assert "aten::addmm" in out or "aten::mm" in out


def test_only_must_match_a_recipe() -> None:
    with pytest.raises(SystemExit):
        train_step.main(["--only", "no such recipe"])
