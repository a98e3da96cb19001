"""repnet.train.checkpoint: a shipped ONNX model gives back the weights it was exported from."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from repnet.train import checkpoint, export, metadata, train, validate
from repnet.train import plausibility as plausibility_of
from repnet.train.config import RepNetConfig
from repnet.train.model import Critic, Plausibility, RepNet
from tests.training.conftest import tiny_config

TINY = RepNetConfig(width=32, critic_width=16, kcs_width=8)


def _exported(tmp_path: Path, plausibility: bool, mirror_average: bool) -> tuple[RepNet, Critic, Path]:
    torch.manual_seed(0)
    generator, critic = RepNet(TINY).eval(), Critic(TINY).eval()
    table = torch.linspace(-1, 1, 11)
    path = tmp_path / f"model_{plausibility}_{mirror_average}.onnx"
    meta = metadata.build_metadata(
        TINY,
        "tiny",
        "generator: python -m repnet.train.train --a; critic: python -m repnet.train.train --b",
        "Human3.6M S1 S5 S6 S7 S8, 2D inputs: gt+sh",
        plausibility=plausibility_of.metadata("critic", table.numpy(), None) if plausibility else None,
        mirror_average=mirror_average,
    )
    export.export_onnx(
        generator, path, meta, Plausibility(critic, table) if plausibility else None, mirror_average
    )
    return generator, critic, path


@pytest.mark.parametrize("mirror_average", [False, True])
def test_an_exported_model_gives_back_every_weight_of_its_generator_and_critic(
    tmp_path: Path, mirror_average: bool
) -> None:
    generator, critic, path = _exported(tmp_path, plausibility=True, mirror_average=mirror_average)
    state = checkpoint.load(path)
    assert state["model_config"] == dataclasses.asdict(TINY)
    assert state["generator"].keys() == generator.state_dict().keys()
    for name, value in generator.state_dict().items():
        assert torch.equal(state["generator"][name], value), name
    assert state["critic"].keys() == critic.state_dict().keys()
    for name, value in critic.state_dict().items():
        assert torch.equal(state["critic"][name], value), name
    assert state["command"] == "python -m repnet.train.train --a"
    assert state["critic_command"] == "python -m repnet.train.train --b"
    assert state["train_config"] == {"inputs": "gt+sh"}
    # The rebuilt generator answers as the one exported (export's own parity check).
    rebuilt, _ = export.load_generator(path)
    points = (np.random.default_rng(0).normal(0, 100, (8, 17, 2)) + 500).astype(np.float32)
    assert export.check_parity(rebuilt, path, points, np.ones((8, 17), np.float32), mirror_average) <= 1e-3


def test_a_model_without_plausibility_has_no_critic_and_other_onnx_files_are_refused(
    synthetic_h36m: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, _, path = _exported(tmp_path, plausibility=False, mirror_average=False)
    assert checkpoint.load(path)["critic"] == {}
    args = ["--checkpoint", str(path), "--critic-checkpoint", str(path), "--output", str(tmp_path / "x.onnx")]
    with pytest.raises(SystemExit):
        export.main([*args, "--data-dir", str(synthetic_h36m)])
    assert "holds no critic" in capsys.readouterr().err
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "other",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])],
    )
    other = tmp_path / "other.onnx"
    onnx.save(helper.make_model(graph), str(other))
    with pytest.raises(ValueError, match="not a repnet.train.export model"):
        checkpoint.load(other)


def test_training_starts_from_a_shipped_model_and_export_reuses_its_critic(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    """--init-from model.onnx: the run starts from the shipped generator (and critic); export's
    --critic-checkpoint model.onnx puts that critic in the new model with its command."""
    generator, critic, shipped = _exported(tmp_path, plausibility=True, mirror_average=True)
    config = dataclasses.replace(
        tiny_config(synthetic_h36m, tmp_path / "arm", 1), inputs="gt", batch_size=16, init_from=str(shipped)
    )
    train.train(config, TINY, command="run arm")
    after = torch.load(tmp_path / "arm" / "last.pt", weights_only=False)
    assert after["step"] == 1 and after["opt_g"]["state"][0]["step"] == 1
    for name, value in generator.state_dict().items():  # one Adam step away from the shipped weights
        assert torch.allclose(value, after["generator"][name], atol=2e-3), name
        assert not torch.equal(value, after["generator"][name]) or "bias" in name or value.dim() < 2
    for name, value in critic.state_dict().items():
        assert torch.allclose(value, after["critic"][name], atol=2e-2), name
    # The validation figures of a shipped model: scored from the ONNX file as from a checkpoint.
    figures = validate.score(shipped, (False,), str(synthetic_h36m), val_size=50, hidden_joints=(2,))["plain"]
    assert set(figures) >= {"gt", "sh", "gt_hidden2"} and figures["gt"]["pa_mpjpe"] > 0
    assert figures["gt_hidden2"]["pa_mpjpe"] != figures["gt"]["pa_mpjpe"]  # the joints were hidden
    out = tmp_path / "next.onnx"
    export.main(
        [
            "--checkpoint",
            str(tmp_path / "arm" / "last.pt"),
            "--critic-checkpoint",
            str(shipped),
            "--output",
            str(out),
            "--data-dir",
            str(synthetic_h36m),
        ]
    )
    state = checkpoint.load(out)
    for name, value in critic.state_dict().items():
        assert torch.equal(state["critic"][name], value), name
    meta_command = state["command"] + checkpoint.CRITIC_COMMAND + state["critic_command"]
    assert meta_command == "run arm; critic: python -m repnet.train.train --b"
    assert json.loads(json.dumps(state["model_config"])) == dataclasses.asdict(TINY)
