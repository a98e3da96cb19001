"""How the pose density behind the plausibility output was chosen: its variants side by side on the
validation shifts. Validation tails only, never S9/S11.

    python -m bench.plausibility_density --threads 1

The bundled generator lifts the shifts of bench.plausibility_rank once (GT 2D clean, + 20 px,
+ 40 px, SH detections of the held-out tails, the tails from high cameras, all of S8 with SH
detections). Each variant is fitted to the training poses (every 5th frame, the tails left out),
calibrated as export calibrates it (percentile among the real validation poses, 0 outside the bone
range) and scored per shift: Spearman rank correlation of plausibility with per-pose P-II, the
lowest decile's P-II over the highest's, the mean plausibility and the share at 0. Also the
critic's calibrated score (v6's plausibility), and how many of the 29 broken poses of
tests/training/test_shipped_critic.py each scores below the real one. It measures and prints.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

if __package__ in (None, ""):  # `python bench/plausibility_density.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.plausibility_rank import lift_shift, rank_figures, shifts
from bench.stats import write_json
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.train import checkpoint, data, density
from repnet.train import plausibility as plausibility_of
from repnet.train.evaluate import open_model
from repnet.train.export import load_critic
from repnet.train.model import MM_PER_UNIT

# name -> PoseDensity.fit settings; None: the critic
VARIANTS: dict[str, dict[str, float] | None] = {
    "critic (v6)": None,
    "directions only": {"length_widen": 1e6},
    "floor 0.1 %, widened 2x": {"length_floor": 0.001, "length_widen": 2.0},
    "floor 0.1 %, widened 4x (v7)": {"length_floor": 0.001, "length_widen": 4.0},
    "floor 0.1 %, widened 6x": {"length_floor": 0.001, "length_widen": 6.0},
    "floor 1 %, widened 4x": {"length_floor": 0.01, "length_widen": 4.0},
}


def broken_pairs() -> tuple[np.ndarray, np.ndarray]:
    """The real and broken poses of the shipped-critic test, template-aligned (mm)."""
    from tests.training.test_shipped_critic import _pairs

    cases = _pairs()
    return tuple(data.align_to_template(np.stack([c[i] for c in cases])) for i in (1, 2))  # type: ignore[return-value]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Fit, calibrate and rank every variant; print the table (and --out JSON)."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", type=Path, default=BUNDLED_MODEL, help="whose generator and critic")
    parser.add_argument("--data-dir", default=None, help=f"Human3.6M folder (default: ${data.DATA_ENV})")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    data_dir = data.resolve_data_dir(args.data_dir)
    # One read of the data: the pool (every 5th frame; its poses are the same whatever the 2D
    # inputs) and the held-out sets (the same whatever the frame step).
    pool, held_out = data.build_training_sets(data_dir, "gt+sh", frame_step=5)
    sets = shifts(data_dir, 4000, 0, held_out)
    lift, _ = open_model(args.model, args.threads)
    answers = {}
    for name, val in sets.items():
        pose, _, errors = lift_shift(lift, val)
        answers[name] = (pose, errors)
    real = data.align_to_template(held_out["gt"].poses_camera)
    real_cases, broken_cases = broken_pairs()
    results: dict[str, Any] = {}
    print("| variant | " + " | ".join(sets) + " | broken poses below the real one |")
    print("|---|" + "---:|" * (len(sets) + 1))
    for variant, settings in VARIANTS.items():
        score: torch.nn.Module
        if settings is None:
            score = load_critic(checkpoint.load(args.model))
        else:
            score = density.PoseDensity.fit(pool.poses_aligned, **settings)  # type: ignore[arg-type]
        plausibility, _, _ = plausibility_of.build(score, real)
        row: dict[str, Any] = {}
        with torch.no_grad():
            for name, (pose, errors) in answers.items():
                p = plausibility(torch.from_numpy(pose / MM_PER_UNIT)).numpy()
                ranked = rank_figures(p, errors)
                row[name] = {
                    "spearman": ranked["spearman"],
                    "ratio": ranked["ratio"],
                    "mean": float(p.mean()),
                    "zero_share": ranked["zero_share"],
                }
            below = score(torch.from_numpy(broken_cases / MM_PER_UNIT)) < score(
                torch.from_numpy(real_cases / MM_PER_UNIT)
            )
        row["broken_below_real"] = int(below.sum())
        results[variant] = row
        cells = [
            f"{r['spearman']:+.3f} / {r['ratio']:.2f} / {r['mean']:.2f} / {100 * r['zero_share']:.0f} %"
            for k, r in row.items()
            if k != "broken_below_real"
        ]
        print(
            f"| {variant} | " + " | ".join(cells) + f" | {row['broken_below_real']} of {len(real_cases)} |",
            flush=True,
        )
    print("cells: Spearman / lowest decile's P-II over the highest's / mean plausibility / share at 0")
    if args.out:
        write_json(args.out, results)
    return results


if __name__ == "__main__":
    main()
