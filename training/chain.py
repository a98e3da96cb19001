"""Run a preset: its stages in order into OUT/<stage>/, then the export to OUT/<preset>.onnx.

Run again after an interruption, it skips the stages that recorded their completion (done.json)
and resumes the one that was running from its last.pt, bit for bit: the same chain, interrupted
or not, gives the same weights. A stage starts only when the stages it starts from are done.

Each stage is trained by the function it is given, repnet.train.train.train: train's command line
runs presets, so this module does not import it (no import circle).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch

from repnet.train import checkpoint, export, lineage
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.presets import Preset, Stage, StageRef

log = logging.getLogger(__name__)

DONE = "done.json"  # a finished stage's record: its last step, the sha256 of its checkpoints, its config


class TrainFunction(Protocol):
    """repnet.train.train.train's signature."""

    def __call__(
        self,
        config: TrainConfig,
        model_config: RepNetConfig,
        resume: str | Path | None = None,
        command: str = "",
        extend: bool = False,
        preset: str | None = None,
        stage: str | None = None,
    ) -> Path:
        """Train one run (a stage) and return its best checkpoint."""
        ...


class StageNotReady(RuntimeError):
    """A stage was asked to run before the stages it starts from were done."""


@dataclass(frozen=True)
class Runtime:
    """What the command line sets beside a preset: how the stages run, not what they compute."""

    threads: int = 0
    device: str = "auto"
    data_dir: str = ""


def default_out_dir(preset: Preset) -> Path:
    """Where a preset's stages go without --out-dir: ~/.cache/repnet/runs/<preset>/."""
    return lineage.cache_dir() / "runs" / preset.name


def checkpoint_path(out_dir: Path, ref: StageRef) -> Path:
    """The file of a stage's checkpoint: OUT/<stage>/<best|last>.pt."""
    return out_dir / ref.stage / f"{ref.checkpoint}.pt"


def stage_config(stage: Stage, out_dir: Path, runtime: Runtime) -> TrainConfig:
    """The stage's TrainConfig with where it writes and reads and how it runs filled in."""
    init_from = "" if stage.init_from is None else str(checkpoint_path(out_dir, stage.init_from))
    return dataclasses.replace(
        stage.train,
        out_dir=str(out_dir / stage.name),
        data_dir=runtime.data_dir,
        threads=runtime.threads,
        device=runtime.device,
        init_from=init_from,
    )


def is_done(out_dir: Path, stage: Stage, runtime: Runtime) -> bool:
    """Whether the stage recorded its completion; ConfigChanged when it did so with a configuration
    other than the preset's (the preset was edited since: a new out-dir is needed)."""
    done = out_dir / stage.name / DONE
    if not done.is_file():
        return False
    record = json.loads(done.read_text())
    changes = checkpoint.config_changes(record, stage_config(stage, out_dir, runtime), stage.model)
    if changes:
        raise checkpoint.ConfigChanged(
            f"{done}: stage {stage.name} was done with another configuration: {'; '.join(changes)}"
        )
    return True


def run_stage(
    train: TrainFunction, preset: Preset, stage: Stage, out_dir: Path, runtime: Runtime, command: str
) -> None:
    """Train one stage to its stop step: resumed from its own last.pt when there is one, else
    started as the preset says (from scratch, init_from, or extending its parent's last.pt)."""
    if is_done(out_dir, stage, runtime):
        log.info("stage %s: done (%s), skipped", stage.name, out_dir / stage.name / DONE)
        return
    waiting = [parent for parent in stage.parents() if not is_done(out_dir, preset.stage(parent), runtime)]
    if waiting:
        raise StageNotReady(f"stage {stage.name} starts from {', '.join(waiting)}: run that stage first")
    stage_dir = out_dir / stage.name
    config = stage_config(stage, out_dir, runtime)
    resume: Path | str = "auto"
    extend = False
    if not (stage_dir / "last.pt").is_file():
        # A fresh start: what an attempt stopped before its first checkpoint left is redone.
        for stale in ("history.jsonl", "best.pt"):
            (stage_dir / stale).unlink(missing_ok=True)
        if stage.extends:
            resume, extend = out_dir / stage.extends / "last.pt", True
            stage_dir.mkdir(parents=True, exist_ok=True)
            history = out_dir / stage.extends / "history.jsonl"
            if history.is_file():  # one history for the whole schedule, as the run as shipped kept
                shutil.copyfile(history, stage_dir / "history.jsonl")
    log.info("stage %s: %s", stage.name, stage.summary())
    train(config, stage.model, resume, command, extend, preset=preset.name, stage=stage.name)
    state = checkpoint.read_state(stage_dir / "last.pt")
    if state["step"] < stage.stop:
        raise RuntimeError(f"stage {stage.name} stopped at step {state['step']} of {stage.stop}")
    record = {
        "preset": preset.name,
        "stage": stage.name,
        "step": state["step"],
        "last_sha256": lineage.file_sha256(stage_dir / "last.pt"),
        "best_sha256": lineage.file_sha256(stage_dir / "best.pt"),
        "train_config": state["train_config"],
        "model_config": state["model_config"],
    }
    (stage_dir / DONE).write_text(json.dumps(record, indent=1) + "\n")


def seed_stage(preset: Preset, stage: Stage, out_dir: Path, runtime: Runtime, artefact: Path) -> None:
    """Mark `stage` done with the weights of `artefact` (a checkpoint, or an exported .onnx such as a
    shipped model): the chain then goes on from it instead of training the stages before it. Only a
    stage that later stages start from with init_from (fresh optimisers) can be seeded: an artefact
    holds no optimiser state for a stage that extends it. Its done.json says where it came from."""
    if is_done(out_dir, stage, runtime):
        log.info("stage %s: done (%s), not seeded again", stage.name, out_dir / stage.name / DONE)
        return
    if any(other.extends == stage.name for other in preset.all_stages):
        raise ValueError(f"stage {stage.name} is extended by a later stage: it cannot be seeded from a file")
    state = checkpoint.load(artefact)
    model = dataclasses.asdict(stage.model)
    if {**model, **state["model_config"]} != model:
        raise ValueError(
            f"{artefact}: its model ({state['model_config']}) is not stage {stage.name}'s ({model})"
        )
    stage_dir = out_dir / stage.name
    stage_dir.mkdir(parents=True, exist_ok=True)
    seeded = {"path": artefact.name, "sha256": lineage.file_sha256(artefact)}
    record = {"preset": preset.name, "stage": stage.name, "seeded_from": seeded, **lineage.environment()}
    seed = {
        "generator": state["generator"],
        "critic": state["critic"],
        "step": stage.stop,
        "elapsed_s": 0.0,
        "best": float("nan"),
        "command": state.get("command", ""),
        "train_config": dataclasses.asdict(stage_config(stage, out_dir, runtime)),
        "model_config": model,
        "lineage": lineage.stages_of(state, "generator") + [record],
    }
    for name in ("last.pt", "best.pt"):
        torch.save(seed, stage_dir / name)
    done = {
        "preset": preset.name,
        "stage": stage.name,
        "step": stage.stop,
        "seeded_from": seeded,
        "last_sha256": lineage.file_sha256(stage_dir / "last.pt"),
        "best_sha256": lineage.file_sha256(stage_dir / "best.pt"),
        "train_config": seed["train_config"],
        "model_config": model,
    }
    (stage_dir / DONE).write_text(json.dumps(done, indent=1) + "\n")
    log.info("stage %s: seeded from %s (sha256 %s)", stage.name, artefact, seeded["sha256"])


def export_preset(preset: Preset, out_dir: Path, runtime: Runtime, command: str) -> Path:
    """OUT/<preset>.onnx: export_from's generator, the critic stage's last.pt as its critic, the
    preset's plausibility, model_id the preset's name; kept when it is there (written under another
    name first)."""
    output = out_dir / f"{preset.name}.onnx"
    if output.is_file():
        log.info("%s: exported, kept", output)
        return output
    partial = output.with_name(output.name + ".partial")
    export.export_model(
        checkpoint_path(out_dir, preset.export_from),
        partial,
        model_id=preset.name,
        critic_checkpoint=checkpoint_path(out_dir, StageRef(preset.critic.name, "last")),
        score=preset.plausibility,
        density=preset.density,
        mirror_average=preset.mirror_average,
        data_dir=runtime.data_dir or None,
        command=command,
        root=out_dir,
    )
    partial.replace(output)
    return output


def run_preset(
    train: TrainFunction,
    preset: Preset,
    out_dir: Path,
    runtime: Runtime,
    command: str,
    only: str | None = None,
    seeds: dict[str, Path] | None = None,
) -> Path | None:
    """Every stage of the preset in order, trained by `train`, then its export; returns the
    exported model. only -- that one stage (its parents must be done), no export; seeds -- stages
    taken as done from files (seed_stage), e.g. {"stretch5": the shipped v5 .onnx}."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, artefact in (seeds or {}).items():
        seed_stage(preset, preset.stage(name), out_dir, runtime, artefact)
    if only is not None:
        run_stage(train, preset, preset.stage(only), out_dir, runtime, command)
        return None
    needed = needed_stages(preset, out_dir, runtime)
    for stage in preset.all_stages:
        if stage.name in needed:
            run_stage(train, preset, stage, out_dir, runtime, command)
    return export_preset(preset, out_dir, runtime, command)


def needed_stages(preset: Preset, out_dir: Path, runtime: Runtime) -> set[str]:
    """The stages the export needs: its generator's and critic's stages and, back from them, the
    stages each starts from, stopping at stages already done (a seeded stage needs nothing before it)."""
    needed: set[str] = set()
    waiting = [preset.export_from.stage, preset.critic.name]
    while waiting:
        name = waiting.pop()
        if name in needed:
            continue
        needed.add(name)
        stage = preset.stage(name)
        if not is_done(out_dir, stage, runtime):
            waiting.extend(stage.parents())
    return needed
