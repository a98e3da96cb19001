"""The Human3.6M domain shifts that bench.adapt_h36m adapts on: each a builder of the 2D a user would
give `repnet adapt` (of S1 S5 S6 S7's training frames, never their 3D) and the validation sets it is
scored on (the validation tails, never adapted on; never S9/S11). bench.adapt_h36m's docstring says
what each shift is."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from repnet.core import skeleton
from repnet.train import data, presets, sequences, synthetic

SOURCE = ("S1", "S5", "S6", "S7")
HIGH_DEG = (45.0, 65.0)


def high_views(
    world: np.ndarray, seed: int, elevation: tuple[float, float] = HIGH_DEG, runs: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, J, 3) world poses (mm, pelvis at the origin) seen from random cameras looking down by
    U(elevation) degrees (default: high ones): pixels (N, J, 2) and the poses in each camera's frame
    (mm, pelvis at the origin). `runs` (N,): each pose's run, one camera per run (None: per pose)."""
    gen = torch.Generator().manual_seed(seed)
    if runs is None:
        rot, position = synthetic.random_views(len(world), gen, elevation)
    else:
        index = torch.from_numpy(np.unique(runs, return_inverse=True)[1].reshape(-1))
        rot, position = synthetic.random_views(int(index.max()) + 1, gen, elevation)
        rot, position = rot[index], position[index]
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


def run_frames(frames: int, run_length: int, step: int) -> np.ndarray:
    """The frames of a sequence of `frames` taken as runs of `run_length` consecutive ones, a run
    starting every `step * run_length` frames (about one frame in `step` in all)."""
    starts = np.arange(0, max(frames - run_length + 1, 0), step * run_length)
    return (starts[:, None] + np.arange(run_length)).reshape(-1)


def source_runs(poses: dict[str, np.ndarray], count: int, run_length: int) -> tuple[np.ndarray, np.ndarray]:
    """About `count` of the source subjects' training frames (data.load_poses' "train" poses, the
    validation tails left out), pelvis at the origin, and their numbers: every k-th frame of them all
    in a row (run_length 1: numbered by their place in that row), or runs of `run_length` consecutive
    frames (25 Hz) spread over each sequence (run_frames), numbered with a gap between runs and
    between sequences."""
    heads = [
        seq[: data.sequence_split(len(seq), 0.1)]
        for key, seq in sorted(poses.items())
        if key.split("/")[0] in SOURCE
    ]
    step = max(1, sum(len(h) for h in heads) // count)
    if run_length <= 1:  # every k-th frame of all of them in a row
        every = np.concatenate(heads)[::step]
        return every - every[:, :1], np.arange(len(every)) * step
    world, frames, offset = [], [], 0
    for head in heads:
        take = run_frames(len(head), run_length, step)
        world.append(head[take])
        frames.append(offset + take)
        offset += len(head) + 2
    out = np.concatenate(world)
    return out - out[:, :1], np.concatenate(frames)


def clip_views(
    world: np.ndarray, frames: np.ndarray, run_length: int, seed: int, elevation: tuple[float, float]
) -> np.ndarray:
    """Pixels of `world` at `frames` (source_runs), one camera per run of consecutive frame numbers
    (every pose its own with run_length 1), + N(0, 2 px)."""
    runs = np.concatenate([[0], np.cumsum(np.diff(frames) != 1)]) if run_length > 1 else None
    pixels, _ = high_views(world, seed=seed, elevation=elevation, runs=runs)
    return pixels + np.random.default_rng(0).normal(0.0, 2.0, pixels.shape).astype(np.float32)


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
            take = run_frames(split, run_length, step) if run_length > 1 else np.arange(0, split, step)
            points.append(pts[take])
            visible.append(vis[take])
            frames.append(offset + take)
            offset += n + 2
    numbers = np.concatenate(frames) if run_length > 1 else None
    return np.concatenate(points), np.concatenate(visible), {"s8_sh": s8_sh(found)}, numbers


def high_shift(
    data_dir: Path, poses: int, run_length: int = 1
) -> tuple[np.ndarray, np.ndarray, dict[str, data.ValidationSet], np.ndarray | None]:
    """The source subjects' training frames from high cameras, and the tails from other high ones."""
    train = data.load_poses(data_dir, "train")
    world, frames = source_runs(train, poses, run_length)
    pixels = clip_views(world, frames, run_length, seed=1, elevation=HIGH_DEG)
    numbers = frames if run_length > 1 else None
    return pixels, np.ones(pixels.shape[:2], np.float32), {"high": high_tails(train)}, numbers


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
    ) -> tuple[np.ndarray, np.ndarray, dict[str, data.ValidationSet], np.ndarray | None]:
        train = of_actions(data.load_poses(data_dir, "train"), actions)
        world, frames = source_runs(train, poses, run_length)
        pixels = clip_views(change(world), frames, run_length, seed=1, elevation=synthetic.ELEVATION_DEG)
        tail = tail_frames(train)
        seen, truth = high_views(change(tail), seed=2, elevation=synthetic.ELEVATION_DEG)
        if not truth_changes:
            _, truth = high_views(tail, seed=2, elevation=synthetic.ELEVATION_DEG)
        tails = data.ValidationSet(truth, seen, np.ones(seen.shape[:2], np.float32))
        numbers = frames if run_length > 1 else None
        return pixels, np.ones(pixels.shape[:2], np.float32), {name: tails}, numbers

    return shift


SHIFTS = {
    "proportions": built_shift("proportions", rescaled, truth_changes=True),
    "coco-hips": built_shift("coco_hips", coco_hips, truth_changes=False),
    # no-sitting: the people and joints unchanged, only actions the parent never saw (issue 32).
    "no-sitting": built_shift("sitting", np.asarray, truth_changes=True, actions=presets.NO_SITTING),
}
