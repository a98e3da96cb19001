"""The temporal model's data: synthetic clips lifted by the single-frame model and turned into grid
features (cached on disk), held-out clips, chunks for a step, and the figures of a clip set."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from repnet.train import data, lineage, metrics, sequences
from repnet.train.sequences import ClipConfig
from repnet.train.temporal import GRID_FPS, TemporalConfig, TemporalNet, grid_features

log = logging.getLogger(__name__)


def onnx_lift(model: Path, threads: int) -> sequences.LiftFunction:
    """The single-frame model as a LiftFunction: its pose_3d turned by K's rotation (the service's
    pose_3d_camera without intrinsics), root at the origin."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    session = ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])

    def lift(keypoints: np.ndarray, visibility: np.ndarray) -> np.ndarray:
        out = []
        for start in range(0, len(keypoints), 4096):
            feed = {
                "keypoints_2d": keypoints[start : start + 4096].astype(np.float32),
                "visibility": visibility[start : start + 4096].astype(np.float32),
            }
            pose, camera = session.run(["pose_3d", "camera"], feed)
            out.append(metrics.to_camera_frame(pose, camera))
        return metrics.root_align(np.concatenate(out)).astype(np.float32)

    return lift


def clip_features(
    poses: np.ndarray, keypoints: np.ndarray, visibility: np.ndarray, fps: float, grid: np.ndarray
) -> np.ndarray:
    """(G, FEATURES) network input at grid times `grid` (seconds) from a clip's frames at `fps`:
    what the exported graph computes for a window, for a whole clip at once."""
    positions = grid * fps
    grid_poses, _ = sequences.resample(poses, np.ones(visibility.shape, np.float32), positions)
    grid_points, grid_seen = sequences.resample(keypoints, visibility, positions)
    with torch.no_grad():
        features = grid_features(
            torch.from_numpy(grid_poses)[None],
            torch.from_numpy(grid_points)[None],
            torch.from_numpy(grid_seen)[None],
        )
    return features[0].T.numpy()


def padded_grid(frames: int, config: TemporalConfig) -> np.ndarray:
    """Grid times of `frames` answers and the window around each: from -target to the end plus the
    window's rest (times beyond the clip take its end frames)."""
    return np.arange(-config.target, frames + config.window - 1 - config.target) / GRID_FPS


@dataclass(frozen=True)
class ClipSet:
    """Clips as one array each: features on the padded grid and truth on the answer grid."""

    features: np.ndarray  # (sum of G_i + T - 1, FEATURES) float32
    truth: np.ndarray  # (sum of G_i, J, 3) float32 mm
    frames: np.ndarray  # (clips,) G_i answers per clip
    step: np.ndarray  # (clips,) answers kept for the figures: every step-th grid frame (frame times)

    def clip(self, index: int, window: int) -> tuple[np.ndarray, np.ndarray]:
        """Clip `index`'s padded features and truth."""
        first = int(self.frames[:index].sum())
        start = first + index * (window - 1)
        return self.features[start : start + int(self.frames[index]) + window - 1], self.truth[
            first : first + int(self.frames[index])
        ]


def _stack(parts: list[tuple[np.ndarray, np.ndarray, int]]) -> ClipSet:
    if not parts:
        raise ValueError("no clips: the held-out tails are too short, or no sequence has detections")
    return ClipSet(
        np.concatenate([f for f, _, _ in parts]).astype(np.float32),
        np.concatenate([t for _, t, _ in parts]).astype(np.float32),
        np.array([len(t) for _, t, _ in parts]),
        np.array([s for _, _, s in parts]),
    )


def synthetic_source(
    clips: ClipConfig, base_model: Path, data_dir: Path, threads: int
) -> list[sequences.Clip]:
    """The training clips lifted by the base model, built once and cached by what they depend on
    (the base model's and the data's sha256, the clip settings)."""
    names = (data.CAMERAS_FILE, data.poses_file("train"), data.SH_TRAIN_FILE)
    key = json.dumps(
        {
            "base": lineage.file_sha256(base_model),
            "data": lineage.data_hashes(data_dir, names),
            "clips": asdict(clips),
        },
        sort_keys=True,
    )
    cache = lineage.cache_dir() / "temporal" / f"clips-{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if cache.is_file():
        with np.load(cache) as found:
            frames, grid = np.cumsum(found["frames"])[:-1], np.cumsum(found["grid"])[:-1]
            parts = zip(
                *(np.split(found[name], frames) for name in ("poses", "keypoints", "visibility")),
                found["fps"],
                np.split(found["truth"], grid),
                strict=True,
            )
            return [sequences.Clip(p, k, v, float(f), t) for p, k, v, f, t in parts]
    lift = onnx_lift(base_model, threads)
    bank = sequences.residuals(data_dir, clips.val_fraction)
    training = sequences.training_sequences(data_dir, clips.val_fraction)
    rng = np.random.default_rng(clips.seed)
    found_clips: list[sequences.Clip] = []
    started = time.monotonic()
    for draw in range(clips.draws):
        found_clips += [sequences.synthesize(s, bank, lift, rng, clips.noise, GRID_FPS) for s in training]
        log.info("synthetic clips: draw %d of %d (%.0f s)", draw + 1, clips.draws, time.monotonic() - started)
    cache.parent.mkdir(parents=True, exist_ok=True)
    # Each process writes its own partial file: two runs side by side (temporal_train --model) make
    # the same clips, and the second to finish replaces the first's file with equal bytes.
    partial = cache.with_suffix(f".partial-{os.getpid()}.npz")
    np.savez(
        partial,
        poses=np.concatenate([c.poses for c in found_clips]),
        keypoints=np.concatenate([c.keypoints for c in found_clips]),
        visibility=np.concatenate([c.visibility for c in found_clips]),
        fps=np.array([c.fps for c in found_clips]),
        truth=np.concatenate([c.truth for c in found_clips]),
        frames=np.array([len(c.poses) for c in found_clips]),
        grid=np.array([len(c.truth) for c in found_clips]),
    )
    partial.replace(cache)
    return found_clips


def synthetic_clips(source: list[sequences.Clip], config: TemporalConfig) -> ClipSet:
    """The lifted training clips as features on the grid padded for `config`'s window."""
    return _stack(
        [
            (
                clip_features(c.poses, c.keypoints, c.visibility, c.fps, padded_grid(len(c.truth), config)),
                c.truth,
                1,
            )
            for c in source
        ]
    )


def held_out_clips(
    kind: str, config: TemporalConfig, base_model: Path, data_dir: Path, threads: int
) -> ClipSet:
    """The held-out tails (sequences.validation_clips) lifted by the base model; answers at the
    clip's own frames (every 2nd grid frame of a 25 Hz clip)."""
    lift = onnx_lift(base_model, threads)
    parts = []
    for clip in sequences.validation_clips(data_dir, kind):
        step = round(GRID_FPS / clip.fps)
        frames = (len(clip.keypoints) - 1) * step + 1
        grid = padded_grid(frames, config)
        poses = lift(clip.keypoints, clip.visibility)
        truth = np.repeat(clip.truth, step, axis=0)[:frames]  # the truth at frame times (every step-th)
        parts.append((clip_features(poses, clip.keypoints, clip.visibility, clip.fps, grid), truth, step))
    return _stack(parts)


def chunk(
    found: ClipSet, window: int, count: int, outputs: int, rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """`count` runs of `outputs` consecutive answers from random clips: features (count, FEATURES,
    outputs + window - 1) and truth (count, outputs, J, 3) metres."""
    starts = np.concatenate([[0], np.cumsum(found.frames)[:-1]])
    clips = rng.integers(0, len(found.frames), count)
    features = np.empty((count, outputs + window - 1, found.features.shape[1]), np.float32)
    truth = np.empty((count, outputs) + found.truth.shape[1:], np.float32)
    for row, index in enumerate(clips):
        frames = int(found.frames[index])
        first = int(rng.integers(0, max(frames - outputs, 0) + 1))
        answers = np.clip(np.arange(first, first + outputs), 0, frames - 1)
        padded = starts[index] + index * (window - 1)
        features[row] = found.features[
            padded + np.clip(np.arange(first, first + outputs + window - 1), 0, frames + window - 2)
        ]
        truth[row] = found.truth[starts[index] + answers]
    return torch.from_numpy(features).transpose(1, 2), torch.from_numpy(truth) / 1000.0


def answer_clips(net: TemporalNet, found: ClipSet) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each clip's answers and truth at its frame times (mm), the net in eval mode."""
    window = net.config.window
    out = []
    net.eval()
    with torch.no_grad():
        for index in range(len(found.frames)):
            features, truth = found.clip(index, window)
            answers = net(torch.from_numpy(features).T[None])[0].numpy() * 1000.0
            step = int(found.step[index])
            out.append((answers[::step].astype(np.float64), truth[::step].astype(np.float64)))
    return out


def figures(answers: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Acceleration and velocity error (per frame of the clip's own rate), P-II, P-I and the mean
    std of a clip's limb bone lengths, all in mm, over every frame of every clip."""
    accel = np.concatenate([metrics.acceleration_error(a, t) for a, t in answers])
    velocity = np.concatenate([metrics.velocity_error(a, t) for a, t in answers])
    poses, truth = np.concatenate([a for a, _ in answers]), np.concatenate([t for _, t in answers])
    return {
        "accel": float(accel.mean()),
        "mpjve": float(velocity.mean()),
        "pa_mpjpe": metrics.pa_mpjpe(poses, truth),
        "mpjpe": metrics.mpjpe(poses, truth),
        "bone_std": float(np.mean([metrics.limb_length_std(a).mean() for a, _ in answers])),
    }
