"""Train RepNet on Human3.6M: the training loop, its checkpoints and resume, and the command line.

A shipped model's whole chain, its presets, or one run from flags (as in TrainConfig):
python -m repnet.train.train --preset repnet-h36m-v6 --threads 2
python -m repnet.train.train --list-presets
python -m repnet.train.train --out-dir runs/x --warm-start-steps 20000 ...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, TextIO

import torch
from tqdm import tqdm

from repnet.train import chain, checkpoint, data, lineage, presets, sequences
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.trainer import Terms, Trainer, adversarial_weight, learning_rate, pick_device
from repnet.train.validation import validate, validation_sets

log = logging.getLogger(__name__)


class _Run:
    """The bookkeeping of one train() call: step count, wall time, best score, history, checkpoints."""

    def __init__(
        self,
        config: TrainConfig,
        model_config: RepNetConfig,
        trainer: Trainer,
        val_sets: dict[str, data.ValidationSet],
        command: str,
        stages: list[lineage.Record],
    ) -> None:
        self.config, self.model_config, self.trainer = config, model_config, trainer
        self.val_sets, self.command, self.stages = val_sets, command, stages
        self.out = Path(config.out_dir)
        self.step, self.elapsed, self.best = 0, 0.0, math.inf
        self._wall = (float(stages[-1].get("wall_time_s", 0.0)), 0.0)  # the stage's and the run's, at start

    def begin(self, step: int, elapsed: float, best: float) -> None:
        """Start at this step, wall time and best score (a fresh run: 0, 0, inf)."""
        self.step, self.elapsed, self.best = step, elapsed, best
        self._wall = (self._wall[0], elapsed)

    def out_of_time(self) -> bool:
        """max_minutes of training done (0: no limit)."""
        return bool(self.config.max_minutes) and self.elapsed >= 60 * self.config.max_minutes

    def save(self, path: Path) -> None:
        """Write the run's whole state to `path` atomically: never a half-written checkpoint."""
        tmp = path.with_suffix(".tmp")
        stage_wall, run_wall = self._wall
        self.stages[-1]["steps"] = self.step
        self.stages[-1]["wall_time_s"] = round(stage_wall + self.elapsed - run_wall, 1)
        state = {
            **self.trainer.state_dict(),
            "step": self.step,
            "elapsed_s": self.elapsed,
            "best": self.best,
            "command": self.command,
            "model_config": asdict(self.model_config),
            "train_config": asdict(self.config),
            "lineage": self.stages,
        }
        torch.save(state, tmp)
        tmp.replace(path)

    def record(self, terms: Terms) -> dict[str, Any]:
        """The history record of the step just done; every val_every steps with the validation
        figures, and best.pt saved when the first set's P-II improved."""
        config, step = self.config, self.step
        record: dict[str, Any] = {
            "step": step,
            "minutes": round(self.elapsed / 60, 2),
            "lr": learning_rate(config, step - 1),
            "adv_weight": adversarial_weight(config, step - 1),
            **{name: value.item() for name, value in terms.items()},
        }
        if step % config.val_every == 0:
            for kind, val in self.val_sets.items():
                for name, value in validate(self.trainer.generator, val, self.trainer.device).items():
                    record[f"val_{kind}_{name}"] = round(value, 2)
            score = record[f"val_{next(iter(self.val_sets))}_pa_mpjpe"]
            if score < self.best:
                self.best = score
                self.save(self.out / "best.pt")
            log.info(json.dumps(record))
        return record

    def loop(self, history: TextIO, bar: Any) -> None:
        """Train up to stop_step (or iterations) or max_minutes, phase by phase."""
        config = self.config
        start = time.monotonic() - self.elapsed
        last_save = time.monotonic()
        stop = min(config.iterations, config.stop_step or config.iterations)
        for phase in self.trainer.phases:
            while self.step < min(phase.end, stop) and not self.out_of_time():
                terms = self.trainer.run(phase, self.step)
                self.step += 1
                self.elapsed = time.monotonic() - start
                bar.update(1)
                if self.step % config.log_every == 0:
                    record = self.record(terms)
                    bar.set_postfix(
                        {k: f"{record[k]:.3f}" for k in ("rep", "cam", "w_dist", "synthetic_pose")}
                    )
                    history.write(json.dumps(record) + "\n")
                    history.flush()
                due = time.monotonic() - last_save >= 60 * config.checkpoint_minutes
                if self.step % config.checkpoint_every == 0 or due:
                    self.save(self.out / "last.pt")
                    last_save = time.monotonic()


def train(
    config: TrainConfig,
    model_config: RepNetConfig,
    resume: str | Path | None = None,
    command: str = "",
    extend: bool = False,
    preset: str | None = None,
    stage: str | None = None,
) -> Path:
    """Run training; returns the path of the best checkpoint (by validation PA-MPJPE).

    resume -- a checkpoint, or "auto" for out_dir/last.pt if there is one. A resumed run
    continues bit for bit: weights, optimiser moments, every random generator, the step
    count (which alone drives the schedules) and the poses the next critic step judges. Its
    configuration must be the checkpoint's but for checkpoint.RESUME_MAY_CHANGE (ConfigChanged);
    extend -- also let iterations and warm_start_steps grow: the run goes on along a longer schedule.

    Every checkpoint records its lineage (repnet.train.lineage): the stages it comes from and its own,
    named by preset and stage when a preset runs it; command is recorded free of absolute paths.
    """
    torch.manual_seed(config.seed)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = pick_device(config.device)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    command = lineage.path_free(command, out.resolve().parent)
    resume_path = checkpoint.resolve_resume(resume, out)
    state = None
    if resume_path is not None:
        state = checkpoint.read_state(resume_path, device)
        checkpoint.check_resume(resume_path, state, config, model_config, extend)
    data_dir = data.resolve_data_dir(config.data_dir or None)
    pool, held_out = data.build_training_sets(
        data_dir, config.inputs, config.frame_step, config.val_fraction, config.exclude_actions
    )
    val_sets = validation_sets(config, held_out)
    if config.detector_error_prob > 0:
        pool = sequences.with_residuals(pool, data_dir, config.val_fraction, config.exclude_actions)
    hashes = lineage.data_hashes(data_dir, data.training_files(config.inputs))
    sizes = f"{len(pool.poses_aligned)} 3D poses, {len(pool.points_2d)} 2D poses"
    log.info("training on %s: %s, device %s", config.inputs, sizes, device)
    trainer = Trainer(config, model_config, pool, device, torch.Generator().manual_seed(config.seed))
    init = None
    if config.init_from and state is None:
        init = (Path(config.init_from), checkpoint.load(config.init_from))
        _initialise(trainer, init[1], config.init_from)
    stages = lineage.run_stages(out, command, hashes, (preset, stage), (resume_path, state, extend), init)
    run = _Run(config, model_config, trainer, val_sets, command, stages)
    if state is not None:
        trainer.load_state_dict(state)
        run.begin(state["step"], state["elapsed_s"], state["best"])
        _truncate_history(out / "history.jsonl", run.step)
        log.info("resumed from %s at step %d (%.1f min)", resume_path, run.step, run.elapsed / 60)
    with (out / "history.jsonl").open("a") as history:
        bar = tqdm(total=config.iterations, initial=run.step, desc="train", mininterval=10, file=sys.stderr)
        run.loop(history, bar)
        bar.close()
    run.save(out / "last.pt")
    if untrained := config.critic_only and not config.init_from:  # its generator stayed as made
        log.info("critic only, from scratch: the generator was never trained, so it is not validated")
    for kind, val in ({} if untrained else val_sets).items():
        log.info("final validation on %s: %s", kind, validate(trainer.generator, val, device))
    if not (out / "best.pt").exists():
        run.save(out / "best.pt")
    return out / "best.pt"


def _initialise(trainer: Trainer, state: dict[str, Any], init_from: str) -> None:
    """Take the generator (and the critic, when it has the same shape) of a checkpoint or an
    exported model's state; the run still starts at step 0 with fresh optimisers."""
    trainer.generator.load_state_dict(state["generator"])
    own = trainer.critic.state_dict()
    same_critic = state["critic"].keys() == own.keys() and all(
        v.shape == own[k].shape for k, v in state["critic"].items()
    )
    if same_critic:
        trainer.critic.load_state_dict(state["critic"])
    log.info(
        "initialised the generator%s from %s (its step %d); starting at step 0",
        " and the critic" if same_critic else " (the critic's shape differs: a fresh critic)",
        init_from,
        state["step"],
    )


def _truncate_history(path: Path, step: int) -> None:
    """Drop the records an interrupted run wrote after the checkpoint it resumes from."""
    if not path.is_file():
        return
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    kept = [line for line in lines if json.loads(line)["step"] <= step]
    path.write_text("".join(line + "\n" for line in kept))


# What may go with --preset: how the stages run, never what they compute.
PRESET_FLAGS = ("out_dir", "threads", "device", "data_dir")


def _add_flags(parser: argparse.ArgumentParser, cls: type) -> None:
    """One flag per field of a config dataclass; a flag not given is not in the parsed values."""
    group = parser.add_argument_group(f"{cls.__name__} (one run)")
    for field in dataclasses.fields(cls):
        flag = "--" + field.name.replace("_", "-")
        kind = type(field.default)
        parse = (lambda s: s.lower() in ("1", "true", "yes")) if kind is bool else kind
        group.add_argument(flag, type=parse, default=argparse.SUPPRESS, help=f"default {field.default!r}")


def _list_presets() -> str:
    return "\n\n".join(
        "\n".join([f"{preset.name}: {preset.description}"] + [f"  {s.summary()}" for s in preset.all_stages])
        + f"\n  export: {preset.export_from} with {preset.critic.name}/last.pt's critic"
        f"{', mirror-averaged' if preset.mirror_average else ''} -> <out-dir>/{preset.name}.onnx"
        for preset in presets.PRESETS.values()
    )


def _run_preset(parser: argparse.ArgumentParser, args: argparse.Namespace, argv: list[str]) -> None:
    """--preset NAME [--stage NAME]: the preset's chain (repnet.train.chain) into --out-dir."""
    values = vars(args)
    fields = {f.name for cls in (TrainConfig, RepNetConfig) for f in dataclasses.fields(cls)}
    extra = sorted((fields & set(values)) - set(PRESET_FLAGS))
    given = [f"--{name.replace('_', '-')}" for name in extra] + ["--resume"] * bool(args.resume)
    if given or args.extend:
        allowed = ", ".join("--" + name.replace("_", "-") for name in PRESET_FLAGS)
        parser.error(f"--preset sets every training flag; only {allowed} go with it, got {' '.join(given)}")
    try:
        preset = presets.get(args.preset)
        if args.stage:
            preset.stage(args.stage)
    except KeyError as err:
        parser.error(str(err.args[0]))
    out_dir = Path(values.get("out_dir") or chain.default_out_dir(preset))
    out_dir.mkdir(parents=True, exist_ok=True)
    _log_to(out_dir / "train.log")
    runtime = chain.Runtime(
        values.get("threads", 0), values.get("device", "auto"), values.get("data_dir", "")
    )
    seeds: dict[str, Path] = {}
    for item in args.seed_stages:
        name, _, path = item.partition("=")
        if not path or not Path(path).is_file():
            parser.error(f"--seed-stage expects STAGE=FILE with an existing file, got {item!r}")
        try:
            preset.stage(name)
        except KeyError as err:
            parser.error(str(err.args[0]))
        seeds[name] = Path(path)
    exported = chain.run_preset(
        train, preset, out_dir, runtime, lineage.command_line(argv, out_dir), args.stage or None, seeds
    )
    log.info("%s", f"exported {exported}" if exported else f"stage {args.stage} done")


def _log_to(path: Path) -> None:
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(message)s",
        handlers=[logging.StreamHandler(), logging.FileHandler(path)],
    )


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.train: a preset's whole chain (--preset), or one run from flags."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", help="run this preset's stages and export (--list-presets)")
    parser.add_argument("--stage", help="with --preset: only this stage (the stages it starts from done)")
    parser.add_argument("--list-presets", action="store_true", help="list the presets and their stages")
    parser.add_argument(
        "--seed-stage",
        dest="seed_stages",
        action="append",
        default=[],
        metavar="STAGE=FILE",
        help="with --preset: take STAGE as done with the weights of FILE (a checkpoint or an exported "
        ".onnx, e.g. a shipped model from git history) and go on from there; repeatable",
    )
    parser.add_argument(
        "--resume",
        default="",
        help="checkpoint to continue from (e.g. runs/x/last.pt), or 'auto': out-dir/last.pt when it exists; "
        "the flags must be the checkpoint's but for " + ", ".join(sorted(checkpoint.RESUME_MAY_CHANGE)),
    )
    parser.add_argument(
        "--extend",
        action="store_true",
        help="with --resume: also let --iterations and --warm-start-steps grow (the run goes on along a "
        "longer schedule, e.g. a finished 60,000-step run to 120,000)",
    )
    _add_flags(parser, TrainConfig)
    _add_flags(parser, RepNetConfig)
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if args.list_presets:
        print(_list_presets())
        return
    if args.preset:
        _run_preset(parser, args, argv)
        return
    if args.stage:
        parser.error("--stage goes with --preset")
    values = vars(args)
    config = TrainConfig(
        **{f.name: values[f.name] for f in dataclasses.fields(TrainConfig) if f.name in values}
    )
    model_config = RepNetConfig(
        **{f.name: values[f.name] for f in dataclasses.fields(RepNetConfig) if f.name in values}
    )
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _log_to(out / "train.log")
    command = lineage.command_line(argv, out.resolve().parent)
    best = train(config, model_config, resume=args.resume, command=command, extend=args.extend)
    log.info("best checkpoint: %s", best)


if __name__ == "__main__":
    main()
