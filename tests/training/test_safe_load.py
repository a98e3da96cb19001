"""Checkpoints are read without running code from them: a planted file is refused by every loader."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from repnet.train import checkpoint
from tests.training.conftest import plant


def test_a_planted_checkpoint_is_refused_and_runs_nothing(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    path = plant(tmp_path / "adapt.pt", marker)
    with pytest.raises(checkpoint.UnsafeCheckpoint, match=r"adapt\.pt: refused, it holds more than tensors"):
        checkpoint.read_state(path)
    with pytest.raises(checkpoint.UnsafeCheckpoint):
        checkpoint.load(path)
    assert not marker.exists()
    torch.load(path, weights_only=False)  # what the loaders did before: the code runs
    assert marker.exists()


def test_a_checkpoint_of_tensors_and_plain_values_is_read(tmp_path: Path) -> None:
    state = {"step": 3, "weights": torch.ones(2), "config": {"lr": 1e-4, "name": "x"}, "errors": None}
    torch.save(state, tmp_path / "last.pt")
    read = checkpoint.read_state(tmp_path / "last.pt")
    assert read["step"] == 3 and torch.equal(read["weights"], torch.ones(2)) and read["config"]["name"] == "x"


def test_a_file_that_is_no_dict_is_refused(tmp_path: Path) -> None:
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(checkpoint.UnsafeCheckpoint, match="not a checkpoint"):
        checkpoint.read_state(tmp_path / "list.pt")


def test_every_training_loader_reads_through_the_safe_reader() -> None:
    """No module of training/ calls torch.load itself (checkpoint.read_state is the one reader)."""
    root = Path(checkpoint.__file__).parent
    callers = [
        p.name for p in root.glob("*.py") if "torch.load(" in p.read_text() and p.name != "checkpoint.py"
    ]
    assert callers == []
