"""How far root_camera_m is from the true pelvis: Human3.6M ground-truth 2D with the true intrinsics.

    python -m bench.root_trajectory [--split test|validation] [--frame-step 10] [--out PATH.json]

The 17 ground-truth joints are projected through the true (distorted) cameras and sent with each
camera's focal lengths and principal point, once without a height (root_height_source "template")
and once with the subject's true skeleton height (geometry.skeleton_height of the subject's ground
truth, the median over its frames: one height per person, the same definition the answers are
measured with). The reply path is the service's (input rules, model, repnet.runtime.replies). The error is
the Euclidean distance in mm between root_camera_m and the ground-truth pelvis in camera coordinates.

`--split validation` uses the held-out tail of the training subjects' sequences (the last 10 %,
repnet.train.data.build_training_sets) and also scores the depth from the weak-perspective scale alone
(depth = f x size / (s x spread), the root back-projected at it): the comparison the service's
choice of geometry.root_translation rests on. Report S9/S11 (`--split test`) as the final figure.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # `python bench/root_trajectory.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.h36m_args import h36m_parser
from repnet.core import geometry
from repnet.core.formats import MODEL_PARENTS
from repnet.core.inputs import PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.lifter import Lifter
from repnet.runtime.replies import build_replies
from repnet.server.app import limits_of, load_lifter
from repnet.server.config import Settings
from repnet.train import data
from repnet.train.testset import DATASET_LABEL, build_test_set, select_sequences

log = logging.getLogger("bench.root_trajectory")
BATCH = 4096


def frames_of(args: argparse.Namespace) -> dict[str, np.ndarray]:
    """points (M, 17, 2) px, gt (M, 17, 3) camera mm, camera (M, 4) fx fy cx cy, subject (M,) of a split."""
    data_dir = data.resolve_data_dir(args.data_dir)
    if args.split == "test":
        poses = select_sequences(data.load_poses(data_dir, "test"), list(data.TEST_SUBJECTS), [])
        test = build_test_set(poses, data.load_cameras(data_dir), None, args.frame_step)
        subject = np.array(test.subjects)[test.subject]
        return {
            "points": test.points,
            "gt": test.gt,
            "camera": np.concatenate([test.focal, test.centre], 1),
            "subject": subject,
        }
    _, sets = data.build_training_sets(data_dir, "gt")
    val = sets["gt"]
    assert val.focal is not None and val.centre is not None
    subjects = validation_subjects(data_dir)  # the validation set does not name its poses' subjects
    if len(subjects) != len(val.points_2d):
        raise RuntimeError(f"expected {len(val.points_2d)} validation poses, counted {len(subjects)}")
    step = slice(None, None, args.frame_step)
    camera = np.concatenate([val.focal, val.centre], 1)
    return {
        "points": val.points_2d[step],
        "gt": val.poses_camera[step],
        "camera": camera[step],
        "subject": subjects[step],
    }


def validation_subjects(data_dir: Path) -> np.ndarray:
    """(N,) the subject of each validation pose, in build_training_sets' order (sequences sorted,
    then each subject's cameras, the tail of every sequence)."""
    cameras = data.load_cameras(data_dir)
    names: list[str] = []
    for key, seq in sorted(data.load_poses(data_dir, "train").items()):
        subject = key.split("/")[0]
        tail = len(seq) - int(round(len(seq) * 0.9))
        names += [subject] * (tail * len(cameras[subject]))
    return np.array(names)


def true_heights(
    gt: np.ndarray,
    subject: np.ndarray,
    measure: Callable[[np.ndarray], np.ndarray] = geometry.skeleton_height,
) -> np.ndarray:
    """(M,) each pose's subject's skeleton height in m (or another `measure`): the median over that
    subject's poses."""
    heights = measure(gt.astype(np.float64)) / 1000.0
    out = np.empty(len(gt))
    for name in np.unique(subject):
        out[subject == name] = np.median(heights[subject == name])
    return out


def lift(lifter: Lifter, frames: dict[str, np.ndarray], heights: np.ndarray | None) -> dict[str, np.ndarray]:
    """root_camera_m (M, 3) mm through the service's reply path, and what the weak-perspective
    alternative needs: pose_3d_camera, scale, the visible spread."""
    limits = replace(limits_of(Settings()), max_request_poses=BATCH)
    parts: dict[str, list[np.ndarray]] = {"root": [], "weak": [], "answer_height": [], "answer_bones": []}
    points, camera = frames["points"], frames["camera"]
    for start in range(0, len(points), BATCH):
        rows = range(start, min(start + BATCH, len(points)))
        given = [None] * len(rows) if heights is None else heights[rows].tolist()
        whole = np.ones(17, bool)
        poses = [
            PoseInput(points[i], whole, intrinsics=intrinsics_of(camera[i]), person_height_m=h)
            for i, h in zip(rows, given, strict=True)
        ]
        inputs = prepare_poses(poses, limits).check()
        replies = build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible)).check()
        parts["root"].append(1000.0 * np.array(replies.columns["root_camera_m"], np.float64))
        pose = replies.columns["pose_3d_camera"].astype(np.float64)
        parts["answer_height"].append(geometry.skeleton_height(pose))
        parts["answer_bones"].append(bone_sum(pose))
        size = np.ones(len(pose)) if heights is None else 1000.0 * heights[rows] / parts["answer_height"][-1]
        parts["weak"].append(
            weak_perspective_root(inputs.keypoints_2d, pose, replies.columns["scale"], camera[rows], size)
        )
    return {k: np.concatenate(v) for k, v in parts.items()}


def bone_sum(pose: np.ndarray) -> np.ndarray:
    """(M,) the summed length of the 16 bones of (M, 17, 3) h36m17 poses."""
    bones = [(p, j) for j, p in enumerate(MODEL_PARENTS) if p >= 0]
    return sum((np.linalg.norm(pose[:, j] - pose[:, p], axis=-1) for p, j in bones), np.zeros(len(pose)))


def weak_perspective_root(
    points: np.ndarray, pose: np.ndarray, scale: np.ndarray, camera: np.ndarray, size: np.ndarray
) -> np.ndarray:
    """(M, 3) mm: the depth of the visible centroid from K's scale, Z = f size / (s spread) (the
    input is normalised by its spread, and K X matches it at the answer's size), moved to the root by
    the answer's mean depth, the root's pixel back-projected at that depth."""
    focal = camera[:, :2].mean(axis=1)
    spread = geometry.visible_spread(points, np.ones(points.shape[:2], bool))
    depth = focal * size / (scale.astype(np.float64) * spread) - size * pose[:, :, 2].mean(axis=1)
    x = (points[:, 0, 0] - camera[:, 2]) / camera[:, 0] * depth
    y = (points[:, 0, 1] - camera[:, 3]) / camera[:, 1] * depth
    return np.stack([x, y, depth], axis=1)


def errors(root: np.ndarray, gt_root: np.ndarray) -> dict[str, float]:
    """Mean and median Euclidean error, mean depth and lateral errors, mm."""
    diff = root - gt_root
    euclid = np.linalg.norm(diff, axis=1)
    return {
        "mean_mm": float(euclid.mean()),
        "median_mm": float(np.median(euclid)),
        "depth_mean_abs_mm": float(np.abs(diff[:, 2]).mean()),
        "depth_bias_mm": float(diff[:, 2].mean()),
        "xy_mean_mm": float(np.linalg.norm(diff[:, :2], axis=1).mean()),
        "relative_to_distance": float((euclid / np.linalg.norm(gt_root, axis=1)).mean()),
    }


def intrinsics_of(row: np.ndarray) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of one camera row."""
    fx, fy, cx, cy = (float(v) for v in row)
    return (fx, fy, cx, cy)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Score root_camera_m on the split, without and with the true heights."""
    started = time.perf_counter()
    frames = frames_of(args)
    lifter = load_lifter(Settings(model_path=args.model, intra_op_threads=args.threads))
    gt_root = frames["gt"][:, 0].astype(np.float64)
    heights = true_heights(frames["gt"], frames["subject"])
    log.info("%d poses, model %s", len(gt_root), lifter.info.model_id)
    template, given = lift(lifter, frames, None), lift(lifter, frames, heights)
    label = (
        f"Human3.6M {DATASET_LABEL}"
        if args.split == "test"
        else "Human3.6M training subjects' held-out tails"
    )
    subjects = np.unique(frames["subject"])
    result: dict[str, Any] = {
        "command": " ".join(["python -m bench.root_trajectory", *sys.argv[1:]]),
        "dataset": f"{label}, ground-truth 2D (distorted projections), true intrinsics",
        "model_id": lifter.info.model_id,
        "frame_step": args.frame_step,
        "poses": len(gt_root),
        "height_definition": "geometry.skeleton_height: head-neck-thorax-spine-pelvis + mean thigh+shin",
        "true_heights_m": {str(s): float(heights[frames["subject"] == s][0]) for s in subjects},
        "template_height_m": float(np.median(template["answer_height"]) / 1000.0),
        "mean_distance_m": float(np.linalg.norm(gt_root, axis=1).mean() / 1000.0),
        "root_template_height": errors(template["root"], gt_root),
        "root_true_height": errors(given["root"], gt_root),
    }
    if args.split == "validation":
        # the person's size from all 16 true bone lengths instead of the height: passed to the
        # service as the height that scales the answer by the same factor
        true_bones = true_heights(frames["gt"], frames["subject"], bone_sum)
        equivalent = template["answer_height"] * true_bones / template["answer_bones"]  # m
        result["root_true_bone_lengths"] = errors(lift(lifter, frames, equivalent)["root"], gt_root)
        result["weak_perspective_template_height"] = errors(template["weak"], gt_root)
        result["weak_perspective_true_height"] = errors(given["weak"], gt_root)
    result["wall_time_s"] = round(time.perf_counter() - started, 1)
    return result


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.root_trajectory`."""
    parser = h36m_parser("root_trajectory", __doc__)
    parser.add_argument("--split", choices=["test", "validation"], default="test")
    parser.add_argument("--frame-step", type=int, default=10, help="use every n-th frame")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="JSON result (default: runs/bench/root_trajectory[_validation].json)",
    )
    args = parser.parse_args(argv)
    if args.frame_step < 1:
        parser.error("--frame-step must be at least 1")
    if args.out is None:
        suffix = "" if args.split == "test" else "_validation"
        args.out = Path(f"runs/bench/root_trajectory{suffix}.json")
    return args


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run, write the JSON and print it."""
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    args = parse_args(argv)
    result = run(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
