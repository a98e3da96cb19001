"""repnet.train.rebase: temporal models move to another single-frame model only when it answers as the old."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import onnx
import pytest
import torch

from repnet.train import export, lineage, metadata, rebase
from repnet.train.config import RepNetConfig
from repnet.train.model import Critic, Plausibility, RepNet

TINY = RepNetConfig(width=32, critic_width=16, kcs_width=8)


def _export(generator: RepNet, path: Path, model_id: str, seed: int) -> Path:
    """A tiny model with a plausibility output whose critic is drawn from `seed`."""
    torch.manual_seed(seed)
    critic = Critic(TINY).eval()
    plausibility = Plausibility(critic, torch.linspace(-1.0, 1.0, 11))
    export.export_onnx(generator, path, metadata.build_metadata(TINY, model_id), plausibility)
    return path


def _temporal_over(base: Path, path: Path) -> Path:
    """A stand-in temporal model: any ONNX file whose metadata names its base model."""
    model = onnx.load(str(base))
    model.metadata_props.add(key="base_model_sha256", value=lineage.file_sha256(base))
    model.metadata_props.add(key="base_model_id", value="old")
    model.metadata_props.add(key="lineage", value=json.dumps({"preset": "p"}))
    onnx.save(model, str(path))
    return path


def test_temporal_models_move_to_a_model_with_the_same_generator_and_only_then(tmp_path: Path) -> None:
    torch.manual_seed(0)
    generator = RepNet(TINY).eval()
    old = _export(generator, tmp_path / "old.onnx", "old", seed=1)
    new = _export(generator, tmp_path / "new.onnx", "new", seed=2)  # another critic, the same generator
    torch.manual_seed(3)
    other = _export(RepNet(TINY).eval(), tmp_path / "other.onnx", "other", seed=1)
    temporal = _temporal_over(old, tmp_path / "temporal.onnx")
    before = onnx.load(str(temporal))

    rebase.check_same_generator(old, new)
    with pytest.raises(rebase.NotTheSameGenerator, match="generator weights"):
        rebase.check_same_generator(old, other)
    rebase.rebase(temporal, old, new)

    after = onnx.load(str(temporal))
    meta = {p.key: p.value for p in after.metadata_props}
    assert meta["base_model_sha256"] == lineage.file_sha256(new) and meta["base_model_id"] == "new"
    moved = json.loads(meta["lineage"])
    assert moved["preset"] == "p" and moved["rebased"][0]["from"]["sha256"] == lineage.file_sha256(old)
    assert after.graph == before.graph  # the network itself is untouched
    with pytest.raises(ValueError, match="not old.onnx"):  # it is no longer over the old model
        rebase.rebase(temporal, old, new)


def test_a_generator_whose_answers_differ_is_refused(tmp_path: Path) -> None:
    torch.manual_seed(0)
    generator = RepNet(TINY).eval()
    old = _export(generator, tmp_path / "old.onnx", "old", seed=1)
    shutil.copy(old, tmp_path / "same.onnx")
    rebase.check_same_generator(old, tmp_path / "same.onnx")
    with torch.no_grad():
        generator.pose_branch[-1].bias[4] += 1e-3  # one weight, a little
    changed = _export(generator, tmp_path / "changed.onnx", "changed", seed=1)
    with pytest.raises(rebase.NotTheSameGenerator):
        rebase.check_same_generator(old, changed)
