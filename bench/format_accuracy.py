"""What each keypoint format costs in accuracy: Human3.6M S9/S11 ground truth through every format table.

    python -m bench.format_accuracy [--model PATH] [--frame-step 10] [--out runs/bench/format_accuracy.json]

For each format the 17 ground-truth joints, projected through the Human3.6M cameras, are turned
into that detector's keypoints (joints it lacks are dropped; pelvis or thorax become midpoints
where the detector has hips or shoulders), converted back with the service's own table, and lifted
by the model. The numbers are Protocol II (PA-MPJPE) and Protocol I (MPJPE in the camera's
orientation, repnet.train.metrics.to_camera_frame) as in repnet.train.evaluate.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/format_accuracy.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.h36m_args import check_frame_step, h36m_parser
from bench.stats import report
from repnet.core.formats import FORMATS, KeypointFormat, from_model_joints, to_model_joints
from repnet.runtime.lifter import Lifter
from repnet.server.app import load_lifter
from repnet.server.config import Settings
from repnet.train import data, metrics
from repnet.train.testset import DATASET_LABEL, build_test_set, select_sequences

log = logging.getLogger("bench.format_accuracy")
BATCH = 4096


def format_inputs(fmt: KeypointFormat, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, 17, 2) ground-truth px -> what a `fmt` detector gives the model: points, visible, imputed."""
    source, source_visible = from_model_joints(fmt, points)  # (M, K, 2), (M, K)
    model_points, visible, _derived, imputed = to_model_joints(fmt, source, source_visible)
    return model_points, visible, imputed


def lift_all(lifter: Lifter, points: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """pose_3d (M, 17, 3) and camera (M, 2, 3) in batches of BATCH."""
    poses, cameras = [], []
    for start in range(0, len(points), BATCH):
        prediction = lifter.lift(points[start : start + BATCH], visible[start : start + BATCH])
        poses.append(prediction.pose_3d)
        cameras.append(prediction.camera)
    return np.concatenate(poses), np.concatenate(cameras)


def score_format(fmt: KeypointFormat, lifter: Lifter, points: np.ndarray, gt: np.ndarray) -> dict[str, Any]:
    """MPJPE and P-MPJPE of the test poses sent in `fmt` (through its mapping) against the ground truth."""
    model_points, visible, imputed = format_inputs(fmt, points)
    pose, camera = lift_all(lifter, model_points, visible)
    p1 = metrics.joint_errors(metrics.to_camera_frame(pose, camera), gt)  # (M, 17)
    p2 = metrics.procrustes_errors(pose, gt)  # (M, 17)
    imputed_joints = [name for name, flag in zip(lifter.info.joint_names, imputed[0], strict=True) if flag]
    derived = [lifter.info.joint_names[j] for j, src in enumerate(fmt.sources) if len(src) == 2]
    return {
        "format": fmt.name,
        "input_joints": len(fmt.joint_names),
        "imputed": imputed_joints,
        "derived": derived,
        "mpjpe": float(p1.mean()),
        "pa_mpjpe": float(p2.mean()),
        "pa_mpjpe_imputed_joints": float(p2[imputed].mean()) if imputed.any() else None,
        "pa_mpjpe_other_joints": float(p2[~imputed].mean()),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Score every format on the Human3.6M test subjects."""
    started = time.perf_counter()
    data_dir = data.resolve_data_dir(args.data_dir)
    poses = select_sequences(data.load_poses(data_dir, "test"), list(data.TEST_SUBJECTS), [])
    test = build_test_set(poses, data.load_cameras(data_dir), None, args.frame_step)
    lifter = load_lifter(Settings(model_path=args.model, intra_op_threads=args.threads))
    log.info(
        "%d poses from %d camera sequences, model %s", len(test.gt), test.sequences, lifter.info.model_id
    )
    rows = []
    for fmt in FORMATS.values():
        log.info("format %s", fmt.name)
        rows.append(score_format(fmt, lifter, test.points, test.gt))
    base = next(r for r in rows if r["format"] == "h36m17")
    for row in rows:
        row["pa_mpjpe_cost"] = row["pa_mpjpe"] - base["pa_mpjpe"]
        row["mpjpe_cost"] = row["mpjpe"] - base["mpjpe"]
    return {
        "command": " ".join(["python -m bench.format_accuracy", *sys.argv[1:]]),
        "dataset": f"Human3.6M {DATASET_LABEL}, ground-truth 2D (distorted projections), all 4 cameras",
        "model": str(args.model),
        "model_id": lifter.info.model_id,
        "frame_step": args.frame_step,
        "poses": len(test.gt),
        "formats": rows,
        "wall_time_s": round(time.perf_counter() - started, 1),
    }


def markdown(result: dict[str, Any]) -> str:
    """The result as the markdown table of docs/BENCHMARKS.md."""
    lines = [
        f"`{result['command']}`: {result['dataset']}, every {result['frame_step']}th frame "
        f"({result['poses']:,} poses), model `{result['model_id']}`.",
        "",
        "| format | input joints | derived (midpoints) | imputed by the model | PA-MPJPE mm | cost "
        "| MPJPE mm | cost | PA-MPJPE of imputed joints |",
        "|---|---:|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in result["formats"]:
        imputed, derived = ", ".join(r["imputed"]) or "—", ", ".join(r["derived"]) or "—"
        on_imputed = "—" if r["pa_mpjpe_imputed_joints"] is None else f"{r['pa_mpjpe_imputed_joints']:.1f}"
        lines.append(
            f"| {r['format']} | {r['input_joints']} | {derived} | {imputed} | {r['pa_mpjpe']:.1f} | "
            f"{r['pa_mpjpe_cost']:+.1f} | {r['mpjpe']:.1f} | {r['mpjpe_cost']:+.1f} | {on_imputed} |"
        )
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.format_accuracy`."""
    parser = h36m_parser("format_accuracy", __doc__)
    parser.add_argument("--frame-step", type=int, default=10, help="use every n-th test frame")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/format_accuracy.json"))
    args = parser.parse_args(argv)
    check_frame_step(parser, args)
    return args


def main(argv: list[str] | None = None) -> int:
    """Run, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    result = run(args)
    return report(result, args.out, markdown)


if __name__ == "__main__":
    sys.exit(main())
