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
  puts them, seen from the training cameras + N(0, 2 px) (SHIFTS, below). Scored on the tails
  changed the same way, and on GT 2D of the tails.
- no-sitting: GT 3D of the Sitting and SittingDown frames seen from the training cameras + N(0, 2 px),
  for a parent that never saw those actions (--parent, preset repnet-h36m-nositting). Scored on those
  actions' tails seen the same way, and on GT 2D of all the tails.

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

from repnet.cli.main import main as repnet
from repnet.core import skeleton
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.train import data, metrics, presets, sequences, synthetic
from repnet.train.config import TrainConfig
from repnet.train.export import load_generator
from repnet.train.validation import validate, validation_sets

SOURCE = ("S1", "S5", "S6", "S7")
HIGH_DEG = (45.0, 65.0)


def high_views(
    world: np.ndarray, seed: int, elevation: tuple[float, float] = HIGH_DEG
) -> tuple[np.ndarray, np.ndarray]:
    """(N, J, 3) world poses (mm, pelvis at the origin) seen from random cameras looking down by
    U(elevation) degrees (default: high ones): pixels (N, J, 2) and the poses in each camera's frame
    (mm, pelvis at the origin)."""
    rot, position = synthetic.random_views(len(world), torch.Generator().manual_seed(seed), elevation)
    w = torch.from_numpy(world).double()
    pixels = synthetic.project(w, rot, position).numpy()
    camera = synthetic.to_camera(w, rot, position).numpy() * 1000.0
    return pixels.astype(np.float32), (camera - camera[:, :1]).astype(np.float32)


def s8_sh(found: list[tuple[str, np.ndarray, data.Camera, np.ndarray]]) -> data.ValidationSet:
    """Every 10th frame of S8 with its SH detections, from sequences.detected_sequences' sequences."""
    s8: tuple[list[np.ndarray], ...] = ([], [], [])
    for name, seq, camera, detections in found:
        if name.startswith("S8/"):
            n = min(len(detections), len(seq))
            pts, vis = data.mpii_to_h36m(detections[:n])
            s8[0].append(data.world_to_camera(seq[:n:10], camera))
            s8[1].append(pts[::10])
            s8[2].append(vis[::10])
    return data.ValidationSet(*(np.concatenate(a).astype(np.float32) for a in s8))


def source_frames(poses: dict[str, np.ndarray], count: int) -> np.ndarray:
    """About `count` of the source subjects' training frames (data.load_poses' "train" poses, the
    validation tails left out), pelvis at the origin."""
    heads = [
        seq[: data.sequence_split(len(seq), 0.1)]
        for key, seq in sorted(poses.items())
        if key.split("/")[0] in SOURCE
    ]
    world = np.concatenate(heads)
    world = world[:: max(1, len(world) // count)]
    return world - world[:, :1]


def tail_frames(poses: dict[str, np.ndarray]) -> np.ndarray:
    """Every 10th frame of the validation tails of all training subjects, pelvis at the origin."""
    tail = np.concatenate([seq[data.sequence_split(len(seq), 0.1) :: 10] for _, seq in sorted(poses.items())])
    return tail - tail[:, :1]


def high_tails(poses: dict[str, np.ndarray]) -> data.ValidationSet:
    """Every 10th frame of the validation tails of all training subjects (data.load_poses' "train"
    poses), seen from high cameras (seed 2)."""
    pixels, camera = high_views(tail_frames(poses), seed=2)
    return data.ValidationSet(camera, pixels, np.ones(pixels.shape[:2], np.float32))


def sh_shift(
    data_dir: Path, poses: int, run_length: int = 1
) -> tuple[np.ndarray, np.ndarray, dict[str, data.ValidationSet], np.ndarray | None]:
    """The SH detections of the source subjects' training frames (about `poses` of them), and S8's.
    run_length > 1: runs of that many consecutive frames (25 Hz) spread over each sequence instead
    of every k-th frame, with their frame numbers (a gap between runs and between sequences), so
    that the input is read as clips (--smoothness-weight); 1: every k-th frame, no frame numbers."""
    points: list[np.ndarray] = []
    visible: list[np.ndarray] = []
    frames: list[np.ndarray] = []
    found = list(sequences.detected_sequences(data_dir))
    total = sum(
        data.sequence_split(len(seq), 0.1) for name, seq, _, _ in found if name.split("/")[0] in SOURCE
    )
    step = max(1, total // poses)
    offset = 0
    for name, seq, _, detections in found:
        if name.split("/")[0] in SOURCE:
            n = min(len(detections), len(seq))
            pts, vis = data.mpii_to_h36m(detections[:n])
            split = min(data.sequence_split(len(seq), 0.1), n)
            if run_length > 1:
                starts = np.arange(0, max(split - run_length + 1, 0), step * run_length)
                take = (starts[:, None] + np.arange(run_length)).reshape(-1)
            else:
                take = np.arange(0, split, step)
            points.append(pts[take])
            visible.append(vis[take])
            frames.append(offset + take)
            offset += n + 2
    numbers = np.concatenate(frames) if run_length > 1 else None
    return np.concatenate(points), np.concatenate(visible), {"s8_sh": s8_sh(found)}, numbers


def high_shift(
    data_dir: Path, poses: int, run_length: int = 1
) -> tuple[np.ndarray, np.ndarray, dict[str, data.ValidationSet], None]:
    """The source subjects' training frames from high cameras, and the tails from other high ones."""
    train = data.load_poses(data_dir, "train")
    pixels, _ = high_views(source_frames(train, poses), seed=1)
    pixels += np.random.default_rng(0).normal(0.0, 2.0, pixels.shape).astype(np.float32)
    return pixels, np.ones(pixels.shape[:2], np.float32), {"high": high_tails(train)}, None


# Shifts built from Human3.6M's 3D, stand-ins for a new dataset's people and a detector's joint
# definitions (issue 32), chosen before their results. proportions: a build the bundled model never
# saw, its limbs 15 % shorter and its spine and thorax 10 % longer (every bone scaled from the
# pelvis out). coco-hips: the hips where COCO annotators put them, on the outside of the pelvis (25 %
# wider) and higher (8 % of the pelvis-thorax length), the pelvis their midpoint; the people are
# unchanged, so the answers are scored against the true joints.
BONE_SCALE = {"right_knee": 0.85, "right_ankle": 0.85, "left_knee": 0.85, "left_ankle": 0.85,
              "left_elbow": 0.85, "left_wrist": 0.85, "right_elbow": 0.85, "right_wrist": 0.85,
              "spine": 1.1, "thorax": 1.1}  # fmt: skip


def rescaled(world: np.ndarray) -> np.ndarray:
    """(N, J, 3) poses with each joint's bone to its parent scaled by BONE_SCALE (parents first)."""
    out = world.copy()
    for j, parent in enumerate(skeleton.PARENTS):
        if parent >= 0:
            scale = BONE_SCALE.get(skeleton.JOINT_NAMES[j], 1.0)
            out[:, j] = out[:, parent] + scale * (world[:, j] - world[:, parent])
    return out


def coco_hips(world: np.ndarray) -> np.ndarray:
    """(N, J, 3) world poses (Z up) whose hips are where COCO puts them and pelvis their midpoint."""
    out = world.copy()
    pelvis, thorax = world[:, 0], world[:, skeleton.JOINT_NAMES.index("thorax")]
    up = np.linalg.norm(thorax - pelvis, axis=-1, keepdims=True) * 0.08
    hips = [skeleton.RIGHT_HIP, skeleton.LEFT_HIP]
    for j in hips:
        out[:, j] = world[:, j] + 0.25 * (world[:, j] - pelvis)
        out[:, j, 2] += up[:, 0]
    out[:, 0] = out[:, hips].mean(1)
    return out


def of_actions(poses: dict[str, np.ndarray], actions: str) -> dict[str, np.ndarray]:
    """The sequences of the comma-separated `actions` only ("": every one)."""
    others = data.without_actions(poses, actions)
    return {key: seq for key, seq in poses.items() if key not in others} if actions else poses


def built_shift(name: str, change: Any, truth_changes: bool, actions: str = "") -> Any:
    """A shift of the source subjects' training frames (of `actions` only, comma-separated, when
    given) changed by `change` (seen by the training cameras, + N(0, 2 px)), scored on the tails
    (of those actions) changed the same way, against the changed 3D when `truth_changes` (other
    people) else the true 3D (another detector)."""

    def shift(
        data_dir: Path, poses: int, run_length: int = 1
    ) -> tuple[np.ndarray, np.ndarray, dict[str, data.ValidationSet], None]:
        train = of_actions(data.load_poses(data_dir, "train"), actions)
        pixels, _ = high_views(change(source_frames(train, poses)), seed=1, elevation=synthetic.ELEVATION_DEG)
        pixels += np.random.default_rng(0).normal(0.0, 2.0, pixels.shape).astype(np.float32)
        tail = tail_frames(train)
        seen, truth = high_views(change(tail), seed=2, elevation=synthetic.ELEVATION_DEG)
        if not truth_changes:
            _, truth = high_views(tail, seed=2, elevation=synthetic.ELEVATION_DEG)
        tails = data.ValidationSet(truth, seen, np.ones(seen.shape[:2], np.float32))
        return pixels, np.ones(pixels.shape[:2], np.float32), {name: tails}, None

    return shift


SHIFTS = {
    "proportions": built_shift("proportions", rescaled, truth_changes=True),
    "coco-hips": built_shift("coco_hips", coco_hips, truth_changes=False),
    # no-sitting: the people and joints unchanged, only actions the parent never saw (issue 32).
    "no-sitting": built_shift("sitting", np.asarray, truth_changes=True, actions=presets.NO_SITTING),
}


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
        help="sh: runs of this many consecutive frames, numbered (default 1: every k-th frame)",
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
