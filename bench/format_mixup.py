"""How well the service's format mix-up warning works: Human3.6M S9/S11 poses under every 17-joint label.

    python -m bench.format_mixup [--frame-step 1] [--subjects S9,S11] [--out runs/bench/format_mixup.json]

The 17 ground-truth joints, projected through the Human3.6M cameras, are turned into each 17-joint
format (h36m17 as they are, coco17 with the service's own table: no eyes or ears, which Human3.6M
lacks), then sent through the service's input rules (keypoints.prepare_poses) and the model under
their own label and under every other 17-joint label. The reply's warnings (lookalike.format_warnings)
should fire on every wrongly labelled pose (target >= 99 %) and on almost no correctly labelled one
(target <= 0.5 %). The score's constants were chosen on the training subjects (`--subjects
S1,S5,S6,S7,S8`); S9/S11 are held out. Rows also give each part of the score alone.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/format_mixup.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.h36m_args import check_frame_step, h36m_parser
from bench.stats import report
from repnet.core.format_hints import lookalike_of
from repnet.core.formats import FORMATS, from_model_joints
from repnet.core.inputs import PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.core.lookalike import GEOMETRY_WEIGHT, THRESHOLD, relative_error
from repnet.runtime.lifter import Lifter
from repnet.runtime.replies import build_replies
from repnet.server.app import limits_of, load_lifter
from repnet.server.config import Settings
from repnet.train import data
from repnet.train.testset import DATASET_LABEL, build_test_set, select_sequences

log = logging.getLogger("bench.format_mixup")
BATCH = 4096
FORMATS_17 = [name for name, f in FORMATS.items() if len(f.joint_names) == 17 and lookalike_of(name)]


def detector_poses(name: str, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 17, 2) ground-truth px -> what a `name` detector gives: (M, 17, 2) points, (M, 17) present."""
    source, present = from_model_joints(FORMATS[name], points.astype(np.float32))
    return source.astype(np.float64), present


def send(lifter: Lifter, points: np.ndarray, present: np.ndarray, label: str) -> dict[str, np.ndarray]:
    """The poses through the service's input rules and the model under `label`: per pose whether a
    warning fired, its relative reprojection error and its nose height."""
    limits = limits_of(Settings())
    fired, relative, height = [], [], []
    for a in range(0, len(points), BATCH):
        chunk = zip(points[a : a + BATCH], present[a : a + BATCH], strict=True)
        poses = [PoseInput(p, v, None, label) for p, v in chunk]
        inputs = prepare_poses(poses, limits).check()
        replies = build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible))
        fired.append(np.array([bool(w) for w in replies.columns["warnings"]]))
        relative.append(relative_error(inputs, replies.columns["reprojection_error_px"]))
        height.append(inputs.nose_height)
    return {
        "fired": np.concatenate(fired),
        "relative": np.concatenate(relative),
        "height": np.concatenate(height),
    }


def rates(runs: list[dict[str, Any]], key: str) -> float:
    """The fraction of poses over `runs` for which `key` fires."""
    return float(np.concatenate([r[key] for r in runs]).mean())


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Send every 17-joint format's poses under every 17-joint label and count the warnings."""
    started = time.perf_counter()
    data_dir = data.resolve_data_dir(args.data_dir)
    split = "test" if set(args.subjects) <= set(data.TEST_SUBJECTS) else "train"
    poses = select_sequences(data.load_poses(data_dir, split), args.subjects, [])
    test = build_test_set(poses, data.load_cameras(data_dir), None, args.frame_step)
    points_2d = test.points.astype(np.float64)  # (M, 17, 2) px
    if args.noise > 0:  # detector-like jitter: a fraction of each pose's spread, per coordinate
        spread = points_2d.reshape(len(points_2d), -1).std(axis=1)  # (M,)
        jitter = np.random.default_rng(0).normal(size=points_2d.shape)
        points_2d = points_2d + jitter * (args.noise * spread)[:, None, None]
    lifter = load_lifter(Settings(model_path=args.model, intra_op_threads=args.threads))
    log.info(
        "%d poses from %d camera sequences, model %s", len(test.gt), test.sequences, lifter.info.model_id
    )
    rows = []
    for truth in FORMATS_17:
        points, present = detector_poses(truth, points_2d)
        for label in FORMATS_17:
            log.info("%s poses sent as %s", truth, label)
            out = send(lifter, points, present, label)
            toward_other = out["height"] if label == "h36m17" else -out["height"]
            rows.append(
                {
                    "truth": truth,
                    "label": label,
                    "poses": len(points),
                    "wrong": truth != label,
                    "fired": out["fired"],
                    "fired_count": int(out["fired"].sum()),
                    # Each part of the score alone, at the same threshold.
                    "reprojection_only": out["relative"] > THRESHOLD,
                    "geometry_only": np.nan_to_num(toward_other, nan=-1.0) > 0,
                    "relative_p": np.percentile(out["relative"], [0.1, 0.5, 50, 99.5, 99.9])
                    .round(3)
                    .tolist(),
                }
            )
    wrong, right = [r for r in rows if r["wrong"]], [r for r in rows if not r["wrong"]]
    summary = {
        key: {"fires_when_wrong": rates(wrong, key), "fires_when_right": rates(right, key)}
        for key in ("fired", "reprojection_only", "geometry_only")
    }
    for row in rows:
        for key in ("fired", "reprojection_only", "geometry_only"):
            row[key] = float(row[key].mean())
    return {
        "command": " ".join(["python -m bench.format_mixup", *sys.argv[1:]]),
        "dataset": f"Human3.6M {DATASET_LABEL if split == 'test' else ','.join(args.subjects)}, "
        f"ground-truth 2D{f' + {args.noise:.0%} noise' if args.noise else ''}, all 4 cameras",
        "noise": args.noise,
        "model": str(args.model),
        "model_id": lifter.info.model_id,
        "plausibility": lifter.has_plausibility,
        "frame_step": args.frame_step,
        "poses_per_format": len(test.gt),
        "threshold": THRESHOLD,
        "geometry_weight": GEOMETRY_WEIGHT,
        "rows": rows,
        "summary": summary,
        "wall_time_s": round(time.perf_counter() - started, 1),
    }


def frames(step: int) -> str:
    """'every frame', 'every 2nd frame', 'every 10th frame'."""
    if step == 1:
        return "every frame"
    suffix = "th" if 10 <= step % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(step % 10, "th")
    return f"every {step}{suffix} frame"


def markdown(result: dict[str, Any]) -> str:
    """The result as the markdown tables of docs/BENCHMARKS.md."""
    s = result["summary"]
    lines = [
        f"`{result['command']}`: {result['dataset']}, {frames(result['frame_step'])} "
        f"({result['poses_per_format']:,} poses per format and label), model `{result['model_id']}`"
        f"{' with' if result['plausibility'] else ', no'} plausibility output.",
        "",
        "| poses in | sent as | poses | warning fires (poses) | reprojection alone | geometry alone "
        "| relative reprojection error p0.5 / p50 / p99.5 |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for r in result["rows"]:
        p = r["relative_p"]
        lines.append(
            f"| {r['truth']} | {r['label']} | {r['poses']:,} | {r['fired']:.3%} ({r['fired_count']:,}) "
            f"| {r['reprojection_only']:.2%} | {r['geometry_only']:.2%} "
            f"| {p[1]:.3f} / {p[2]:.3f} / {p[3]:.3f} |"
        )
    lines += [
        "",
        f"Warning (score > {result['threshold']}): fires on {s['fired']['fires_when_wrong']:.3%} of wrongly "
        f"labelled poses (target >= 99 %) and {s['fired']['fires_when_right']:.3%} of correctly labelled "
        "ones (target <= 0.5 %).",
    ]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.format_mixup`."""
    parser = h36m_parser("format_mixup", __doc__)
    parser.add_argument("--subjects", default=",".join(data.TEST_SUBJECTS), help="comma-separated subjects")
    parser.add_argument("--frame-step", type=int, default=1, help="use every n-th frame (default: all)")
    parser.add_argument(
        "--noise", type=float, default=0.0, help="Gaussian 2D noise, a fraction of each pose's spread (0.05)"
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/format_mixup.json"))
    args = parser.parse_args(argv)
    check_frame_step(parser, args)
    args.subjects = args.subjects.split(",")
    known = set(data.TRAIN_SUBJECTS) | set(data.TEST_SUBJECTS)
    if not set(args.subjects) <= known or not (
        set(args.subjects) <= set(data.TEST_SUBJECTS) or set(args.subjects) <= set(data.TRAIN_SUBJECTS)
    ):
        parser.error(f"--subjects must be training subjects or test subjects of {sorted(known)}")
    return args


def main(argv: list[str] | None = None) -> int:
    """Run, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    result = run(args)
    return report(result, args.out, markdown)


if __name__ == "__main__":
    sys.exit(main())
