"""Does a model's plausibility output rank its own errors? Validation tails only, never S9/S11.

    python -m bench.plausibility_rank --models service/models/repnet-h36m.onnx --threads 1

For each model (an .onnx with a plausibility output) it lifts the held-out tails of the training
subjects' sequences (repnet.train.validation.validation_sets: the same draw a training run validates
on) through onnxruntime, one shift at a time: GT 2D clean, GT 2D + N(0, 20 px), GT 2D + N(0, 40 px)
and Stacked-Hourglass detections; and the two shifts of the adaptation benchmark (bench.adapt_h36m):
the tails seen from high cameras (45-65 degrees down) and all of S8 with its SH detections (every
10th frame). Per shift it prints the P-II (mm) of each plausibility decile, the lowest decile's
P-II over the highest's, the Spearman rank correlation between plausibility and per-pose P-II
(negative: a lower score goes with a larger error), and the answers' 1st and 5th percentile of
plausibility (the GT shift's 1st sets the service's implausible-pose warning) and the share of
answers that warning is given (below IMPLAUSIBLE_BELOW). It measures and prints; it asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/plausibility_rank.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.adapt_shifts import high_tails, s8_sh
from bench.stats import write_json
from repnet.runtime.replies import IMPLAUSIBLE_BELOW
from repnet.train import data, metrics, sequences
from repnet.train.config import TrainConfig
from repnet.train.evaluate import open_model
from repnet.train.validation import validation_sets, with_noise

# The fourth shift's noise (px); the second is validation's own 20 px draw (gt_noise).
EXTRA_NOISE_PX = 40.0


def decile_errors(plausibility: np.ndarray, errors: np.ndarray) -> list[float]:
    """Mean per-pose error of each tenth of the poses, from least to most plausible; ties keep the
    poses' order (evaluate.plausibility_deciles' rule)."""
    order = np.argsort(plausibility, kind="stable")
    return [float(errors[idx].mean()) for idx in np.array_split(order, 10)]


def lift_shift(lift: Any, val: data.ValidationSet, batch: int = 4096) -> tuple[np.ndarray, ...]:
    """Lift one validation set: the (N, J, 3) poses, the (N,) plausibility and the (N,) per-pose P-II;
    ValueError when the model has no plausibility output."""
    poses, plausibility, errors = [], [], []
    for start in range(0, len(val.points_2d), batch):
        rows = slice(start, start + batch)
        pose, _, score = lift(val.points_2d[rows], val.visible[rows].astype(np.float32))
        if score is None:
            raise ValueError("the model has no plausibility output")
        poses.append(pose)
        plausibility.append(score)
        errors.append(metrics.procrustes_errors(pose, val.poses_camera[rows]).mean(axis=1))
    return np.concatenate(poses), np.concatenate(plausibility), np.concatenate(errors)


def rank_shift(lift: Any, val: data.ValidationSet, batch: int = 4096) -> dict[str, Any]:
    """Lift one validation set; its decile P-II, lowest/highest ratio, Spearman and share of 0s."""
    _, p, e = lift_shift(lift, val, batch)
    return rank_figures(p, e)


def rank_figures(p: np.ndarray, e: np.ndarray) -> dict[str, Any]:
    """How plausibility p (N,) ranks per-pose P-II e (N,): decile P-II, lowest/highest ratio,
    Spearman and share of 0s."""
    deciles = decile_errors(p, e)
    return {
        "poses": len(p),
        "pa_mpjpe": float(e.mean()),
        "deciles_pa_mpjpe": deciles,
        "ratio": deciles[0] / deciles[-1],
        "spearman": metrics.spearman(p, e),
        "zero_share": float((p == 0).mean()),
        # the low tail the service's warning is set against, and the share it warns
        "percentile_1": float(np.percentile(p, 1)),
        "percentile_5": float(np.percentile(p, 5)),
        "warned_share": float((p < IMPLAUSIBLE_BELOW).mean()),
    }


def shifts(
    data_dir: Path, val_size: int, seed: int, held_out: dict[str, data.ValidationSet] | None = None
) -> dict[str, data.ValidationSet]:
    """The validation shifts: GT clean, GT + 20 px (validation's draw), GT + 40 px, SH detections,
    and bench.adapt_h36m's: the tails from high cameras, S8's SH detections. held_out: the held-out
    sets of data.build_training_sets(data_dir, "gt+sh") when the caller has them."""
    config = TrainConfig(inputs="gt+sh", val_size=val_size, seed=seed, val_noise_px=20.0, val_mirror=False)
    if held_out is None:
        _, held_out = data.build_training_sets(data_dir, "gt+sh", val_fraction=config.val_fraction)
    sets = validation_sets(config, held_out)
    rng = np.random.default_rng([seed, 40])
    extra = with_noise(sets["gt"], EXTRA_NOISE_PX, rng)
    return {
        "gt": sets["gt"],
        "gt_noise20": sets["gt_noise"],
        "gt_noise40": extra,
        "sh": sets["sh"],
        "high": high_tails(data.load_poses(data_dir, "train")),
        "s8_sh": s8_sh(list(sequences.detected_sequences(data_dir))),
    }


def table(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    """Markdown: one row per model and shift."""
    lines = [
        "| model | shift | P-II | decile 1 | decile 10 | ratio | Spearman | share at 0 | 1st pct | 5th pct "
        f"| warned (< {IMPLAUSIBLE_BELOW:g}) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for model, by_shift in results.items():
        for shift, r in by_shift.items():
            d = r["deciles_pa_mpjpe"]
            lines.append(
                f"| {model} | {shift} | {r['pa_mpjpe']:.1f} | {d[0]:.1f} | {d[-1]:.1f} | "
                f"{r['ratio']:.2f} | {r['spearman']:+.3f} | {100 * r['zero_share']:.1f} % | "
                f"{r['percentile_1']:.3f} | {r['percentile_5']:.3f} | {100 * r['warned_share']:.1f} % |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, dict[str, dict[str, Any]]]:
    """Rank every model's plausibility on the validation shifts; print the table (and --out JSON)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--models", type=Path, nargs="+", required=True)
    parser.add_argument("--data-dir", default=None, help=f"Human3.6M folder (default: ${data.DATA_ENV})")
    parser.add_argument("--val-size", type=int, default=4000, help="poses per shift (training's default)")
    parser.add_argument("--seed", type=int, default=0, help="the validation draw (training's seed)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime threads")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    sets = shifts(data.resolve_data_dir(args.data_dir), args.val_size, args.seed)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for path in args.models:
        lift, meta = open_model(path, args.threads)
        name = f"{meta.get('model_id', '') or path.stem} ({path})"
        results[name] = {shift: rank_shift(lift, val) for shift, val in sets.items()}
    print(table(results))
    if args.out:
        write_json(args.out, results)
    return results


if __name__ == "__main__":
    main()
