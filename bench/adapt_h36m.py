"""`repnet adapt` on Human3.6M domain shifts, scored against the 3D truth it never sees.

    python -m bench.adapt_h36m --shift sh [--poses 50000] [--threads 2] [-- ADAPT FLAGS...]
    python -m bench.adapt_h36m --shift high ...   (or proportions, coco-hips)
    python -m bench.adapt_h36m --shift no-sitting --parent runs/nositting/repnet-h36m-nositting.onnx ...

Shifts (the adapted-on 2D is always of S1 S5 S6 S7's training frames, never their 3D; the
validation tails, repnet.train.data.build_training_sets, are never adapted on):
- sh: the Stacked-Hourglass detections. Scored on the SH detections of the validation tails and
  of all of S8 (a subject the adaptation never saw), and on GT 2D of the tails (the source).
- high: GT 3D of those frames seen from high cameras (45-65 degrees down instead of -10..30, a
  view the bundled model was not trained on, + N(0, 2 px)). Scored on the tails seen the same way
  (other draws), and on GT 2D of the tails (the source).
- proportions, coco-hips: GT 3D of those frames with other proportions, or with the hips where COCO
  puts them, seen from the training cameras + N(0, 2 px) (bench.adapt_shifts.SHIFTS). Scored on the tails
  changed the same way, and on GT 2D of the tails.
- no-sitting: GT 3D of the Sitting and SittingDown frames seen from the training cameras + N(0, 2 px),
  for a parent that never saw those actions (--parent, preset repnet-h36m-nositting). Scored on those
  actions' tails seen the same way, and on GT 2D of all the tails.

--run-length N gives any shift's 2D as clips: runs of N consecutive frames (25 Hz) spread over each
sequence, numbered in the NPZ's `frame` array, each run seen by one camera (built shifts), as a video
gives them; the default, 1, is every k-th frame, no numbers.

It writes the 2D to an NPZ the command reads as a user's file, runs `repnet adapt` on it (the
command and its report are printed), then scores the parent (--parent, default the bundled model)
and the adapted model: P-II, P-I along the ray (where intrinsics exist), symmetry (mm). Choose on
these validation figures, never S9/S11.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

if __package__ in (None, ""):  # `python bench/adapt_h36m.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.adapt_shifts import SHIFTS, high_shift, sh_shift
from repnet.cli.main import main as repnet
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.train import data, metrics
from repnet.train.config import TrainConfig
from repnet.train.export import load_generator
from repnet.train.validation import validate, validation_sets


def score(model: Path, sets: dict[str, data.ValidationSet]) -> dict[str, dict[str, float]]:
    """A model's validation figures (repnet.train.validation.validate on its generator, mirror-averaged
    as the bundled model, a preset's and an adapted one are exported)."""
    generator, _ = load_generator(model)
    return {
        kind: validate(generator, val, torch.device("cpu"), mirror_average=True) for kind, val in sets.items()
    }


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation of two (N,) arrays (ties broken by order)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def ranking(model: Path, sets: dict[str, data.ValidationSet]) -> dict[str, dict[str, float]]:
    """How the model's plausibility ranks its own errors on each set (onnxruntime, as served):
    rank correlation with per-pose P-II, and the lowest plausibility decile's P-II over the
    highest's."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    out = {}
    for kind, val in sets.items():
        pose, plausible = session.run(
            ["pose_3d", "plausibility"], {"keypoints_2d": val.points_2d, "visibility": val.visible}
        )
        errors = metrics.procrustes_errors(pose, val.poses_camera).mean(axis=1)
        deciles = np.array_split(np.argsort(plausible, kind="stable"), 10)
        out[kind] = {
            "spearman": spearman(plausible, errors),
            "decile_ratio": float(errors[deciles[0]].mean() / errors[deciles[-1]].mean()),
        }
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Write the shift's 2D, run `repnet adapt` on the parent with it, score both models; prints and
    returns the table."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--shift", choices=["sh", "high", *SHIFTS], default="sh")
    parser.add_argument("--poses", type=int, default=50_000, help="2D poses to adapt on (default 50000)")
    parser.add_argument(
        "--data-dir", help="Human3.6M folder (default: $REPNET_H36M_DIR or ../shared/data/h36m)"
    )
    parser.add_argument(
        "--work-dir", type=Path, default=Path("runs/bench/adapt"), help="input, model, report"
    )
    parser.add_argument(
        "--parent",
        type=Path,
        default=BUNDLED_MODEL,
        help="the model adapted, and scored as before (default: the bundled one)",
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--run-length",
        type=int,
        default=1,
        help="runs of this many consecutive frames (25 Hz), numbered, as a video's clips; built shifts: "
        "one camera per run (default 1: every k-th frame)",
    )
    parser.add_argument("adapt_flags", nargs="*", help="more `repnet adapt` flags (after --)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    data_dir = data.resolve_data_dir(args.data_dir)
    build = {"sh": sh_shift, "high": high_shift, **SHIFTS}[args.shift]
    points, visible, extra, frames = build(data_dir, args.poses, args.run_length)
    work = args.work_dir / args.shift
    work.mkdir(parents=True, exist_ok=True)
    keypoints = np.where(visible[..., None] > 0.5, points, np.nan)
    numbered = {} if frames is None else {"frame": frames}
    np.savez(work / "input.npz", keypoints=keypoints, format="h36m17", **numbered)
    out = work / "adapted.onnx"
    command = [
        "adapt",
        str(work / "input.npz"),
        "-o",
        str(out),
        "--threads",
        str(args.threads),
        "--run-dir",
        str(work / "run"),
        "--model",
        str(args.parent),
        *args.adapt_flags,
    ]
    print("repnet " + " ".join(command), flush=True)
    start = time.monotonic()
    status = repnet(command)
    took = time.monotonic() - start
    _, held = data.build_training_sets(data_dir, "gt+sh")
    sets = {**validation_sets(TrainConfig(val_size=4000, val_mirror=False, val_noise_px=0.0), held), **extra}
    result: dict[str, Any] = {
        "shift": args.shift,
        "parent_model": args.parent.name,
        "poses": len(points),
        "run_length": args.run_length,
        "flags": args.adapt_flags,
        "status": status,
        "wall_s": round(took, 1),
    }
    result["parent"] = score(args.parent, sets)
    result["parent_plausibility"] = ranking(args.parent, sets)
    if out.exists() and status == 0:
        result["adapted"] = score(out, sets)
        result["adapted_plausibility"] = ranking(out, sets)
    for kind in sets:
        before = result["parent"][kind]
        after = result.get("adapted", {}).get(kind, {})
        line = f"{kind:8} P-II {before['pa_mpjpe']:6.2f}"
        if after:
            line += f" -> {after['pa_mpjpe']:6.2f} ({after['pa_mpjpe'] - before['pa_mpjpe']:+.2f})"
            line += f"  symmetry {before['symmetry']:.1f} -> {after['symmetry']:.1f}"
            rank = result["adapted_plausibility"][kind]
            line += (
                f"  plausibility-error rank corr {rank['spearman']:+.2f}, deciles {rank['decile_ratio']:.2f}x"
            )
        print(line)
    print(f"adapt on {len(points)} poses: {took / 60:.1f} min wall (exit {status})")
    (work / "result.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
