"""Read a training checkpoint, or recover one from an exported model.

An exported graph (repnet.train.export) holds the generator's weights as ONNX initializers under their
torch names (``generator.*``) and, with a plausibility output, the critic's (``plausibility.critic.*``);
its metadata holds the model's shape and training command. That is enough to continue training a
shipped model, or to reuse its critic, when the run's own checkpoints are gone.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
from pathlib import Path
from typing import Any

import torch

from repnet.train.config import RepNetConfig, TrainConfig

GENERATOR_PREFIX = "generator."
CRITIC_PREFIX = "critic."  # the "critic" output's; a critic-scored plausibility keeps it at SCORE_PREFIX
SCORE_PREFIX = "plausibility.score."
LEGACY_CRITIC_PREFIX = "plausibility.critic."  # models exported before the pose density
# What a resumed run may change from the configuration stored in its checkpoint: where it writes and
# reads, how often it logs and saves, when it stops, and how fast it runs. None of them changes
# what is computed: the weights, the random draws and the schedule go on as stored. (threads,
# device and compile can change the last bits of float results; init_from is read only at step 0,
# so a resumed run ignores it.)
RESUME_MAY_CHANGE = frozenset(
    {
        "max_minutes",
        "stop_step",
        "threads",
        "device",
        "compile",
        "checkpoint_every",
        "checkpoint_minutes",
        "log_every",
        "out_dir",
        "data_dir",
        "init_from",
    }
)
# What --extend lets change besides: the length of the schedule and of the warm start within it,
# as when a finished 60,000-step run goes on to 120,000 steps of a longer cosine (and a warm start
# that spanned the whole run spans the longer one).
EXTEND_MAY_CHANGE = frozenset({"iterations", "warm_start_steps"})


class ConfigChanged(ValueError):
    """A resumed run was given a configuration that differs from its checkpoint's."""


# What an export's training_data says before the actions its run left out (metadata.training_data).
EXCLUDED_ACTIONS = " without the actions "
# How an export whose critic came from another run names the two commands in its train_command.
GENERATOR_LABEL, CRITIC_COMMAND = "generator: ", "; critic: "


def join_commands(generator_command: str, critic_command: str) -> str:
    """The train_command of a model whose generator and critic come from different runs; from_onnx
    splits it again."""
    return f"{GENERATOR_LABEL}{generator_command}{CRITIC_COMMAND}{critic_command}"


def load(path: str | Path) -> dict[str, Any]:
    """The state of a checkpoint written by repnet.train.train, or the state recovered from an
    exported ``.onnx`` (from_onnx)."""
    path = Path(path)
    if path.suffix == ".onnx":
        return from_onnx(path)
    return read_state(path)


class UnsafeCheckpoint(ValueError):
    """A checkpoint file holds more than tensors and plain values: it could run code when read."""


def read_state(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The state dict a checkpoint file holds, read with torch.load(weights_only=True): tensors,
    numbers, strings and containers of them only, so a file planted in a run folder runs no code
    (pickle would). UnsafeCheckpoint names the file and what it held otherwise."""
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        found = str(err).split("WeightsUnpickler error:")[-1].strip().splitlines()[0]
        raise UnsafeCheckpoint(
            f"{path}: refused, it holds more than tensors and plain values ({found}); a checkpoint is "
            "read without running code from it: delete the file, or start afresh in another folder"
        ) from None
    if not isinstance(state, dict):
        raise UnsafeCheckpoint(f"{path}: not a checkpoint (it holds a {type(state).__name__}, not a dict)")
    return state


def metadata_of(model: Any) -> dict[str, str]:
    """The custom metadata of a loaded ONNX model (onnx.ModelProto)."""
    return {prop.key: prop.value for prop in model.metadata_props}


def set_metadata(model: Any, metadata: dict[str, str]) -> None:
    """Replace a loaded ONNX model's custom metadata with `metadata`."""
    del model.metadata_props[:]
    for key, value in metadata.items():
        model.metadata_props.add(key=key, value=value)


def read_metadata(path: Path) -> dict[str, str]:
    """The custom metadata of the ONNX model at `path`."""
    import onnx

    return metadata_of(onnx.load(str(path), load_external_data=False))


def from_onnx(path: Path) -> dict[str, Any]:
    """A checkpoint-like state from an exported model: generator (and critic, and pose density)
    weights, model config, the training command and lineage, step 0 and no optimiser state, and
    the file's whole custom metadata ("metadata").

    Raises ValueError when the file holds no generator weights (not a repnet.train.export graph).
    """
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    meta = metadata_of(model)
    weights = {
        init.name: torch.from_numpy(numpy_helper.to_array(init).copy()) for init in model.graph.initializer
    }
    generator = _strip(weights, GENERATOR_PREFIX)
    if not generator or "model_config" not in meta:
        raise ValueError(
            f"{path}: no generator weights or model_config metadata (not a repnet.train.export model)"
        )
    command = meta.get("train_command", "")
    generator_command, _, critic_command = command.removeprefix(GENERATOR_LABEL).partition(CRITIC_COMMAND)
    # export writes "...[ without the actions A,B], 2D inputs: gt+sh"; the rest of the run's
    # configuration is not kept.
    described = meta.get("training_data", "")
    inputs = described.partition("2D inputs: ")[2]
    excluded = described.partition(EXCLUDED_ACTIONS)[2].partition(", 2D inputs: ")[0]
    train_config = {"inputs": inputs} if inputs else {}
    if excluded:
        train_config["exclude_actions"] = excluded
    score = _strip(weights, SCORE_PREFIX)
    density = score if "projection" in score else {}  # a repnet.train.density.PoseDensity
    critic = _strip(weights, CRITIC_PREFIX) or _strip(weights, LEGACY_CRITIC_PREFIX)
    if not critic and not density:
        critic = score  # the plausibility is the critic's score
    return {
        "generator": generator,
        "critic": critic,  # empty without a critic
        "density": density,  # empty unless plausibility is the pose density
        "model_config": json.loads(meta["model_config"]),
        "train_config": train_config,
        "step": 0,
        "command": generator_command,
        "critic_command": critic_command or generator_command,
        "lineage": json.loads(meta["lineage"]) if "lineage" in meta else None,
        "metadata": meta,
    }


def _strip(weights: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {name[len(prefix) :]: value for name, value in weights.items() if name.startswith(prefix)}


def resolve_resume(resume: str | Path | None, out_dir: Path) -> Path | None:
    """--resume: a checkpoint path, or "auto" for out_dir/last.pt when it exists (else a fresh start)."""
    if resume is None or str(resume) == "":
        return None
    if str(resume) == "auto":
        last = out_dir / "last.pt"
        return last if last.is_file() else None
    path = Path(resume)
    if not path.is_file():
        raise FileNotFoundError(f"--resume {path}: no such checkpoint")
    return path


def config_changes(
    state: dict[str, Any], config: TrainConfig, model_config: RepNetConfig, extend: bool = False
) -> list[str]:
    """The fields in which `config` and `model_config` differ from the checkpoint's stored ones
    ("lr: 0.001 -> 0.002"), leaving out RESUME_MAY_CHANGE (and with extend EXTEND_MAY_CHANGE). A
    field the checkpoint does not store (added since) counts as its default."""
    allowed = RESUME_MAY_CHANGE | (EXTEND_MAY_CHANGE if extend else frozenset())
    changes = []
    for key, new in (("train_config", config), ("model_config", model_config)):
        stored = state.get(key) or {}
        for field in dataclasses.fields(new):
            old = stored.get(field.name, field.default)
            value = getattr(new, field.name)
            if field.name not in allowed and old != value:
                changes.append(f"{field.name}: {old!r} -> {value!r}")
    return changes


def check_resume(
    path: Path, state: dict[str, Any], config: TrainConfig, model_config: RepNetConfig, extend: bool = False
) -> None:
    """Raise ConfigChanged when resuming `state` (read from `path`) with these configurations would
    silently train something other than the stored run (config_changes); with extend, the schedule
    may be lengthened, never shortened below the checkpoint's step."""
    changes = config_changes(state, config, model_config, extend)
    if changes:
        hint = "" if extend else "; to lengthen a finished run's schedule, resume it with --extend"
        raise ConfigChanged(
            f"resuming {path} with a configuration that differs from the checkpoint's in "
            f"{len(changes)} field(s): {'; '.join(changes)}. A resumed run may change only "
            f"{', '.join(sorted(RESUME_MAY_CHANGE))}{hint}"
        )
    if extend and config.iterations < state["step"]:
        raise ConfigChanged(
            f"--extend {path} to {config.iterations} iterations: the checkpoint is at step {state['step']}"
        )
