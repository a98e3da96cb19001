"""Score a checkpoint on the validation sets its run used, as exported and mirror-averaged.

The sets are rebuilt from the checkpoint's own training configuration (seed, held-out fraction,
size, noise), so the figures are those of the run's history.jsonl; `--mirror-average` adds the
graph that averages every answer with the mirrored answer to the mirrored input (the choice
`repnet.train.export --mirror-average` makes). Validation only: never S9/S11.

    python -m repnet.train.validate --checkpoint ~/.cache/repnet/runs/NAME/best.pt --mirror-average
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from repnet.train import data, validation
from repnet.train.config import TrainConfig
from repnet.train.export import load_generator


def run_config(state: dict[str, Any]) -> TrainConfig:
    """The TrainConfig saved in a checkpoint; fields added since it was written take their defaults."""
    saved = state.get("train_config") or {}
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    return TrainConfig(**{key: value for key, value in saved.items() if key in known})


def score(
    checkpoint: Path,
    mirror_average: tuple[bool, ...] = (False,),
    data_dir: str | None = None,
    noise_px: tuple[float, ...] = (),
    val_size: int = 0,
    hidden_joints: tuple[int, ...] = (),
) -> dict[str, dict[str, dict[str, float]]]:
    """{"plain" | "mirror_average": {set name: {figure: mm}}} for the checkpoint's generator;
    noise_px adds GT 2D + N(0, sigma) sets ("gt_noise40"), one fixed draw each; hidden_joints adds
    GT 2D sets with that many random non-root joints of every pose hidden ("gt_hidden2"), one
    fixed draw each; val_size other than 0 scores that many poses per set instead of the run's
    (more than there are: all)."""
    generator, state = load_generator(checkpoint)
    config = run_config(state)
    if val_size:
        config = dataclasses.replace(config, val_size=val_size)
    _, held_out = data.build_training_sets(
        data.resolve_data_dir(data_dir or config.data_dir or None),
        config.inputs,
        config.frame_step,
        config.val_fraction,
        config.exclude_actions,
    )
    sets = validation.validation_sets(config, held_out)
    for sigma in noise_px:
        rng = np.random.default_rng(config.seed + 1)
        sets[f"gt_noise{sigma:g}"] = validation.with_noise(sets["gt"], sigma, rng)
    for count in hidden_joints:
        rng = np.random.default_rng([config.seed, 2, count])
        sets[f"gt_hidden{count}"] = validation.with_hidden_joints(sets["gt"], count, rng)
    device = torch.device("cpu")
    return {
        "mirror_average" if mirrored else "plain": {
            kind: {
                name: round(value, 2)
                for name, value in validation.validate(generator, val, device, mirrored).items()
            }
            for kind, val in sets.items()
        }
        for mirrored in mirror_average
    }


def main(argv: list[str] | None = None) -> None:
    """python -m repnet.train.validate: print (and write) a checkpoint's validation figures."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument(
        "--mirror-average",
        action="store_true",
        help="also score the mirror-averaged graph, beside the plain one",
    )
    parser.add_argument(
        "--noise-px",
        type=float,
        nargs="*",
        default=[],
        help="also score GT 2D + N(0, sigma) for these sigmas (px)",
    )
    parser.add_argument(
        "--hidden-joints",
        type=int,
        nargs="*",
        default=[],
        help="also score GT 2D with this many random non-root joints hidden (one set per count)",
    )
    parser.add_argument(
        "--val-size",
        type=int,
        default=0,
        help="poses per set (default: the run's; a large number: all of them)",
    )
    parser.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    parser.add_argument(
        "--data-dir", default=None, help="Human3.6M folder (default: the run's, else as train)"
    )
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    graphs = (False, True) if args.mirror_average else (False,)
    figures = score(
        args.checkpoint, graphs, args.data_dir, tuple(args.noise_px), args.val_size, tuple(args.hidden_joints)
    )
    names = sorted({name for by_set in figures.values() for row in by_set.values() for name in row})
    print("| graph | set | " + " | ".join(names) + " |")
    print("|---|---|" + "---:|" * len(names))
    for graph, by_set in figures.items():
        for kind, row in by_set.items():
            print(
                f"| {graph} | {kind} | "
                + " | ".join(f"{row[n]:.2f}" if n in row else "–" for n in names)
                + " |"
            )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"checkpoint": str(args.checkpoint), **figures}, indent=2) + "\n")


if __name__ == "__main__":
    main()
