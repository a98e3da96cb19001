"""Train and export the temporal model (repnet.train.temporal): python -m repnet.train.temporal_train.

python -m repnet.train.temporal_train --preset repnet-h36m-temporal-v1 --threads 1
trains the preset's causal and offline models on synthetic clips (repnet.train.temporal_data) from the
base single-frame model, resumable (run it again after an interruption), validates on the held-out
tails with real detections, and exports both ONNX files. Steps, not wall time, end each model.
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
from typing import Any

import numpy as np
import torch

from repnet.core import skeleton
from repnet.train import checkpoint, lineage, presets
from repnet.train.export import write_onnx
from repnet.train.metadata import LICENCE
from repnet.train.temporal import (
    GRID_FPS,
    TemporalConfig,
    TemporalGraph,
    TemporalNet,
    TemporalTrainConfig,
    slots_needed,
)
from repnet.train.temporal_data import (
    ClipSet,
    answer_clips,
    chunk,
    figures,
    held_out_clips,
    synthetic_clips,
    synthetic_source,
)

log = logging.getLogger(__name__)

VALIDATION_KINDS = ("sh25", "sh50", "gt25")
MAX_FPS = 60.0  # the highest frame rate a window is built at; the service thins faster streams


def learning_rate(config: TemporalTrainConfig, step: int) -> float:
    """Cosine from lr to lr * final_lr over the steps."""
    cosine = 0.5 * (1 + math.cos(math.pi * min(step / max(config.steps, 1), 1.0)))
    return config.lr * (config.final_lr + (1 - config.final_lr) * cosine)


def loss_terms(answers: torch.Tensor, truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """Position, velocity and acceleration errors (mean per-joint norms, metres) of (N, L, J, 3)."""
    velocity = (answers.diff(dim=1) - truth.diff(dim=1)).norm(dim=-1).mean()
    accel = (answers.diff(n=2, dim=1) - truth.diff(n=2, dim=1)).norm(dim=-1).mean()
    return {"position": (answers - truth).norm(dim=-1).mean(), "velocity": velocity, "acceleration": accel}


def validate(net: TemporalNet, sets: dict[str, ClipSet]) -> dict[str, float]:
    """Figures of every held-out set, "<set>_<figure>"."""
    out = {
        f"{kind}_{name}": round(value, 2)
        for kind, found in sets.items()
        for name, value in figures(answer_clips(net, found)).items()
    }
    net.train()
    return out


def train_model(
    name: str,
    model: TemporalConfig,
    config: TemporalTrainConfig,
    clips: ClipSet,
    sets: dict[str, ClipSet],
    out_dir: Path,
    command: str,
) -> TemporalNet:
    """Train (or resume from out_dir/last.pt) one temporal model to config.steps."""
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    net = TemporalNet(model)
    optimiser = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    rng = np.random.default_rng(config.seed)
    step, elapsed = 0, 0.0
    last = out_dir / "last.pt"
    if last.is_file():
        state = checkpoint.read_state(last)
        stored = (state["model_config"], state["train_config"])
        if stored != (asdict(model), asdict(config)):
            raise ValueError(f"{last} was trained with another configuration: {stored}; use a new --out-dir")
        net.load_state_dict(state["net"])
        optimiser.load_state_dict(state["optimiser"])
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        step, elapsed = state["step"], state["elapsed_s"]
        log.info("%s: resumed at step %d", name, step)

    def save() -> None:
        state = {
            "net": net.state_dict(),
            "optimiser": optimiser.state_dict(),
            "rng": rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "step": step,
            "elapsed_s": elapsed,
            "model_config": asdict(model),
            "train_config": asdict(config),
            "command": command,
        }
        partial = last.with_suffix(".tmp")
        torch.save(state, partial)
        partial.replace(last)

    net.train()
    started = time.monotonic() - elapsed
    with (out_dir / "history.jsonl").open("a") as history:
        while step < config.steps:
            for group in optimiser.param_groups:
                group["lr"] = learning_rate(config, step)
            features, truth = chunk(clips, model.window, config.batch, config.outputs, rng)
            terms = loss_terms(net(features), truth)
            loss = terms["position"] + config.velocity_weight * terms["velocity"]
            loss = loss + config.acceleration_weight * terms["acceleration"]
            optimiser.zero_grad(set_to_none=True)
            loss.backward()  # type: ignore[no-untyped-call]
            optimiser.step()
            step += 1
            elapsed = time.monotonic() - started
            if step % config.val_every == 0 or step == config.steps:
                record: dict[str, Any] = {"step": step, "minutes": round(elapsed / 60, 2)}
                record |= {k: round(v.item() * 1000, 2) for k, v in terms.items()}
                record |= validate(net, sets)
                history.write(json.dumps(record) + "\n")
                history.flush()
                log.info("%s %s", name, json.dumps(record))
            if step % config.checkpoint_every == 0 or step == config.steps:
                save()
    return net.eval()


def export_temporal(
    net: TemporalNet, path: Path, model_id: str, base_model: Path, extra: dict[str, str]
) -> float:
    """Write the TemporalGraph to `path` (inputs poses, keypoints_2d, visibility, fps; output
    pose_3d_camera; N and K dynamic) with its contract in the metadata; returns the largest
    torch-onnxruntime difference (mm) over windows at 25, 30, 50 and 60 fps."""
    import onnxruntime as ort

    graph = TemporalGraph(net.eval()).eval()
    config = net.config
    example = _example(3, slots_needed(config, MAX_FPS), 30.0)
    inputs = ["poses", "keypoints_2d", "visibility", "fps"]
    windows = {0: "N", 1: "K"}
    axes = {
        "poses": windows,
        "keypoints_2d": windows,
        "visibility": windows,
        "fps": {0: "N"},
        "pose_3d_camera": {0: "N"},
    }
    contract = {
        "mode": config.mode,
        "grid_fps": GRID_FPS,
        "window": config.window,
        "target": config.target,
        "max_fps": MAX_FPS,
        "window_seconds": (config.window - 1) / GRID_FPS,
        "slots": "causal: the answered frame is the last of K slots; offline: the middle of K (odd)",
    }
    metadata = {
        "model_id": model_id,
        "kind": "temporal",
        "temporal": json.dumps(contract),
        "joint_names": json.dumps(list(skeleton.JOINT_NAMES)),
        "parents": json.dumps(list(skeleton.PARENTS)),
        "skeleton": "h36m17",
        "base_model_sha256": lineage.file_sha256(base_model),
        "model_config": json.dumps(asdict(config)),
        "licence": LICENCE,
        **extra,
    }
    doc = "RepNet temporal model: a window of one person's frames -> the pose of one frame"
    write_onnx(graph, example, path, (inputs, ["pose_3d_camera"], axes), doc, metadata)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for fps in (25.0, 30.0, 50.0, 60.0):
        feed = _example(4, slots_needed(config, fps), fps)
        got = session.run(None, dict(zip(inputs, (t.numpy() for t in feed), strict=True)))[0]
        with torch.no_grad():
            want = graph(*feed).numpy()
        worst = max(worst, float(np.abs(got - want).max()))
    return worst


def _example(n: int, k: int, fps: float) -> tuple[torch.Tensor, ...]:
    """A plausible window: a standing pose (mm) drifting, 2D in px, every joint visible."""
    generator = torch.Generator().manual_seed(k)
    poses = torch.randn(n, 1, skeleton.NUM_JOINTS, 3, generator=generator) * 200
    poses = poses + torch.randn(n, k, skeleton.NUM_JOINTS, 3, generator=generator) * 5
    points = poses[..., :2] + 500
    return poses, points, torch.ones(n, k, skeleton.NUM_JOINTS), torch.full((n,), fps)


def run_preset(
    name: str,
    out_dir: Path | None,
    threads: int,
    data_dir: str,
    argv: list[str],
    only: str | None = None,
    base_model: Path | None = None,
) -> list[Path]:
    """Every model of a temporal preset (or `only` that one): clips, training, export to
    OUT/<model_id>.onnx (kept when there). base_model: refit over another single-frame model than
    the preset's (an adapted one: `repnet adapt`'s output), its model id from its metadata."""
    preset = presets.temporal(name)
    if base_model is not None:
        base_id = checkpoint.read_metadata(base_model).get("model_id", base_model.stem)
        preset = dataclasses.replace(preset, base_model=str(base_model), base_model_id=base_id)
    out = out_dir or lineage.cache_dir() / "runs" / preset.name
    out.mkdir(parents=True, exist_ok=True)
    command = lineage.command_line(argv, out, "repnet.train.temporal_train")
    base = Path(preset.base_model)
    if not base.is_file():
        raise FileNotFoundError(f"base model {base} not found (run from the repository root)")
    root = sequences_data_dir(data_dir)
    written = []
    source = synthetic_source(preset.clips, base, root, threads)
    for model_id, model in preset.models:
        if only is not None and model_id != only:
            continue
        path = out / f"{model_id}.onnx"
        if path.is_file():
            log.info("%s: exported, kept", path)
            written.append(path)
            continue
        clips = synthetic_clips(source, model)
        sets = {kind: held_out_clips(kind, model, base, root, threads) for kind in VALIDATION_KINDS}
        net = train_model(model_id, model, preset.train, clips, sets, out / model_id, command)
        figures_now = validate(net, sets)
        lineage_record = {
            "preset": preset.name,
            "command": command,
            **lineage.environment(),
            "base_model": {"path": base.name, "sha256": lineage.file_sha256(base)},
            "clips": dataclasses.asdict(preset.clips),
            "train": dataclasses.asdict(preset.train),
        }
        extra = {
            "validation": json.dumps(figures_now),
            "lineage": json.dumps(lineage_record),
            "base_model_id": preset.base_model_id,
        }
        worst = export_temporal(net, path, model_id, base, extra)
        log.info(
            "%s: exported %s (torch vs onnxruntime within %.2g mm); validation %s",
            model_id,
            path,
            worst,
            figures_now,
        )
        written.append(path)
    return written


def sequences_data_dir(path: str) -> Path:
    """The Human3.6M folder (repnet.train.data.resolve_data_dir)."""
    from repnet.train import data

    return data.resolve_data_dir(path or None)


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.temporal_train --preset NAME [--out-dir DIR] [--threads N] [--data-dir DIR]."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", required=True, help=f"one of {', '.join(presets.TEMPORAL_PRESETS)}")
    parser.add_argument("--out-dir", type=Path, help="default ~/.cache/repnet/runs/<preset>")
    parser.add_argument("--threads", type=int, default=1, help="torch and onnxruntime threads (default 1)")
    parser.add_argument("--model", help="only this model of the preset (to train its models side by side)")
    parser.add_argument(
        "--data-dir", default="", help="Human3.6M folder (default $REPNET_H36M_DIR, ../shared/data/h36m)"
    )
    parser.add_argument(
        "--base-model",
        type=Path,
        help="refit over this single-frame model (e.g. an adapted one) instead of the preset's",
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    chosen = (args.out_dir, args.threads, args.data_dir, argv, args.model, args.base_model)
    for path in run_preset(args.preset, *chosen):
        print(path)


if __name__ == "__main__":
    main()
