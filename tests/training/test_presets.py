"""The presets: repnet-h36m-v6 is, flag for flag, the chain as run (v6_commands_as_run.sh)."""

from __future__ import annotations

import dataclasses
import re
import shlex
from pathlib import Path
from typing import Any

import pytest

from repnet.train import presets
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.plausibility import DensityConfig
from repnet.train.presets import Preset, Stage, StageRef

AS_RUN = Path(__file__).with_name("v6_commands_as_run.sh")
# Flags of the commands as run that say where and how fast a run ran, not what it computed.
RUNTIME = {"out_dir", "threads", "max_minutes", "resume", "init_from"}
# The run folders and shipped files of the commands as run, by the preset's names for them: v4
# was exported from stretch 3's best.pt, v5 from stretch 5's last.pt.
SOURCES = {
    "long512x3": "stretch1",
    "long512x3b": "stretch2",
    "s3_mirror": "stretch3",
    "s4_p3": "stretch4",
    "s4b_p4": "stretch5",
    "s5_mask25": "stretch6",
    "s5_r2_limbs": "stretch7",
    "repnet-h36m-v4.onnx": "stretch3/best",
    "repnet-h36m-v5.onnx": "stretch5/last",
}


def _commands_as_run() -> dict[str, list[str]]:
    """{stage name: the argv of its first `python -m repnet.train.train` in the commands as run}."""
    lines = AS_RUN.read_text().replace("\\\n", " ").splitlines()
    commands: dict[str, list[str]] = {}
    label = None
    for line in lines:
        stretch = re.search(r"^# .*\bstretch (\d)\b", line)
        if stretch or line.startswith("# v2's critic"):
            label = f"stretch{stretch[1]}" if stretch else "critic"
        elif label and line.startswith("python -m repnet.train.train") and label not in commands:
            commands[label] = shlex.split(line)[3:]
    return commands


def _flags(argv: list[str]) -> dict[str, str]:
    names = [word for word in argv if word.startswith("--")]
    return {name[2:].replace("-", "_"): argv[argv.index(name) + 1] for name in names}


def _value(cls: type, name: str, text: str) -> Any:
    kind = type(next(f.default for f in dataclasses.fields(cls) if f.name == name))
    return text.lower() == "true" if kind is bool else kind(text)


def _source(path: str) -> str:
    folder, _, file = path.rpartition("/")
    name = SOURCES.get(file) or f"{SOURCES[folder.rpartition('/')[2]]}/{file.removesuffix('.pt')}"
    return name


def test_every_stage_of_v6_has_every_flag_of_its_command_as_run_and_defaults_elsewhere() -> None:
    commands = _commands_as_run()
    preset = presets.get("repnet-h36m-v6")
    assert set(commands) == {stage.name for stage in preset.all_stages}
    train_fields = {f.name for f in dataclasses.fields(TrainConfig)}
    model_fields = {f.name for f in dataclasses.fields(RepNetConfig)}
    # What the preset sets that no command says: stretch 5 stopped at step 40,300 on its wall-time
    # limit (--max-minutes 42), and the critic is fresh (the run as shipped resumed another run's).
    beyond = {"stretch5": {"stop_step": 40_300}}
    for stage in preset.all_stages:
        flags = _flags(commands[stage.name])
        assert set(flags) - RUNTIME <= train_fields | model_fields, stage.name
        for name in train_fields - RUNTIME:
            expected = _value(TrainConfig, name, flags[name]) if name in flags else None
            if expected is None:
                expected = beyond.get(stage.name, {}).get(name, getattr(TrainConfig(), name))
            assert getattr(stage.train, name) == expected, (stage.name, name)
        for name in model_fields & set(flags):
            assert getattr(stage.model, name) == _value(RepNetConfig, name, flags[name]), (stage.name, name)
        if "init_from" in flags:
            assert str(stage.init_from) == _source(flags["init_from"]) + ".pt", stage.name
        else:
            assert stage.init_from is None, stage.name
    assert preset.stage("stretch2").extends == "stretch1"  # cp last.pt, --iterations 120000 --resume auto
    assert preset.critic.init_from is None and preset.critic.extends is None
    assert (preset.critic.model.critic_width, preset.critic.model.kcs_width) == (100, 1000)  # as shipped
    assert preset.export_from == StageRef("stretch7", "last") and preset.mirror_average


def test_a_stage_stops_on_a_step_and_a_preset_keeps_its_stages_in_order() -> None:
    config = TrainConfig(iterations=10)
    with pytest.raises(ValueError, match="never on wall time"):
        Stage("a", dataclasses.replace(config, max_minutes=5.0), RepNetConfig())
    with pytest.raises(ValueError, match="not both"):
        Stage("a", config, RepNetConfig(), init_from=StageRef("b", "last"), extends="b")
    critic = Stage("critic", dataclasses.replace(config, critic_only=True), RepNetConfig())
    late = (Stage("a", config, RepNetConfig(), extends="b"), Stage("b", config, RepNetConfig()))
    with pytest.raises(ValueError, match="starts from"):
        Preset("p", "", late, critic, StageRef("a", "last"), False)
    with pytest.raises(ValueError, match="not critic_only"):
        Preset("p", "", late[1:], Stage("c", config, RepNetConfig()), StageRef("b", "last"), False)
    assert Stage("s", dataclasses.replace(config, stop_step=4), RepNetConfig()).stop == 4
    with pytest.raises(KeyError, match="repnet-h36m-v6"):
        presets.get("v8")


def test_v7_is_v6_with_the_pose_density_as_its_plausibility() -> None:
    """The bundled v7 is made from v6's stages (or from a file holding them: --seed-stage)."""
    v6, v7 = presets.get("repnet-h36m-v6"), presets.get("repnet-h36m-v7")
    assert v7.stages == v6.stages and v7.critic == v6.critic and v7.export_from == v6.export_from
    assert (v6.plausibility, v7.plausibility) == ("critic", "density") and v7.mirror_average
    assert v7.density == DensityConfig(frame_step=5, components=64, dims=32, seed=0)


def test_the_tiny_preset_has_every_kind_of_stage() -> None:
    tiny = presets.get("tiny")
    assert any(stage.extends for stage in tiny.stages)
    assert any(stage.init_from and stage.init_from.checkpoint == "best" for stage in tiny.stages)
    assert any(stage.stop < stage.train.iterations for stage in tiny.stages)
    assert tiny.critic.train.critic_fakes == "corrupted" and tiny.mirror_average


def test_the_nositting_preset_leaves_sitting_out_of_every_stage_and_trains_from_scratch() -> None:
    """A parent for bench.adapt_h36m --shift no-sitting: the export's density leaves out what the
    generator's run left out (repnet.train.export), so every stage names the actions."""
    preset = presets.get("repnet-h36m-nositting")
    assert {stage.train.exclude_actions for stage in preset.all_stages} == {"Sitting,SittingDown"}
    assert all(stage.parents() == () for stage in preset.all_stages)
    warm = preset.stage(preset.export_from.stage).train
    assert warm.warm_start_steps == warm.iterations and preset.plausibility == "density"
    assert preset.critic.train.critic_fakes == "corrupted" and preset.mirror_average
