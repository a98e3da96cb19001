"""Clips for the temporal model: the training subjects' 3D sequences through random cameras, with
real detector errors, lifted frame by frame by the single-frame model; and the held-out clips.

No image's 2D is paired with its own 3D. A synthetic clip is one training sequence (its first
1 - val_fraction, world coordinates) seen by a camera drawn here, at a frame rate drawn from
FPS_CHOICES, so the temporal model learns every rate the service resamples. Its 2D gets the errors
of a real detector: a stretch of the Stacked-Hourglass residuals (detection minus projected truth)
of another sequence and camera of the training split, in units of the pose's spread, so that the
errors keep their size relative to the person, their correlation over time (lag-1 autocorrelation
0.83 at 25 Hz) and their outliers. Validation clips are the held-out tails with their real
detections (ValidationClip).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from repnet.core import skeleton
from repnet.train import data, synthetic

SOURCE_HZ = 25.0  # the rate of the training copy's 3D poses and detections
FPS_CHOICES: tuple[float, ...] = (25.0, 30.0, 50.0, 60.0)

# (M, J, 2) px, (M, J) visibility -> (M, J, 3) single-frame pose_3d_camera, mm, root at the origin.
LiftFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]


def catmull_rom(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """x (n, ...) sampled at integer times -> (m, ...) at real times t (m,) by Catmull-Rom splines;
    times outside [0, n - 1] take the end values."""
    n = len(x)
    t = np.clip(t, 0.0, n - 1.0)
    i = np.minimum(np.floor(t).astype(np.int64), max(n - 2, 0))
    u = (t - i).reshape((-1,) + (1,) * (x.ndim - 1))
    p0, p1 = x[np.maximum(i - 1, 0)], x[i]
    p2, p3 = x[np.minimum(i + 1, n - 1)], x[np.minimum(i + 2, n - 1)]
    return 0.5 * (
        2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2 + (3 * p1 - p0 - 3 * p2 + p3) * u**3
    )


def resample(values: np.ndarray, visibility: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames (n, J, C) and their (n, J) visibility at real frame positions t (m,): linear between
    the two neighbouring frames, the end frame beyond the ends (what temporal.TemporalGraph does
    inside the exported model); a joint is visible where both neighbours see it. Hidden joints'
    values count as 0."""
    n = len(values)
    t = np.clip(t, 0.0, n - 1.0)
    lo = np.floor(t).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    u = (t - lo)[:, None, None]
    masked = values * visibility[..., None]
    out = masked[lo] * (1.0 - u) + masked[hi] * u
    seen = np.where(u[..., 0] > 0, np.minimum(visibility[lo], visibility[hi]), visibility[lo])
    return out.astype(np.float32), seen.astype(np.float32)


def pose_spread(points: np.ndarray, visibility: np.ndarray) -> np.ndarray:
    """(n,) the standard deviation of (n, J, 2) points over their visible joints (the size of a pose
    as the model's input normalisation takes it)."""
    w = visibility[..., None]
    count = np.maximum(visibility.sum(axis=1), 1.0)
    mean = (points * w).sum(axis=1) / count[:, None]
    return np.sqrt((((points - mean[:, None]) * w) ** 2).sum(axis=(1, 2)) / (2 * count))


@dataclass(frozen=True)
class Residuals:
    """Stacked-Hourglass errors per (sequence, camera): (m, J, 2) detection minus projected truth
    divided by the truth's spread, and the detector's (m, J) visibility (the spine it lacks: 0)."""

    streams: tuple[tuple[np.ndarray, np.ndarray], ...]

    def draw(self, frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """`frames` consecutive residuals from a random stream (streams joined when one is short)."""
        errors, seen = self.streams[rng.integers(len(self.streams))]
        while len(errors) < frames:
            more, more_seen = self.streams[rng.integers(len(self.streams))]
            errors, seen = np.concatenate([errors, more]), np.concatenate([seen, more_seen])
        start = int(rng.integers(0, len(errors) - frames + 1))
        return errors[start : start + frames], seen[start : start + frames]


def detected_sequences(
    data_dir: Path, exclude_actions: str = ""
) -> Iterator[tuple[str, np.ndarray, data.Camera, np.ndarray]]:
    """Each training-subject sequence seen by a camera with Stacked-Hourglass detections, in name
    order: ("S1/Walking/54138969", its 3D world poses, the camera, the (F, 16, 2) detections); none
    of exclude_actions (data.without_actions)."""
    cameras = data.load_cameras(data_dir)
    poses = data.without_actions(data.load_poses(data_dir, "train"), exclude_actions)
    detections = data.load_detections(data_dir / data.SH_TRAIN_FILE)
    for key, sequence in sorted(poses.items()):
        for cam_id, camera in cameras[key.split("/")[0]].items():
            found = detections.get(f"{key}/{cam_id}")
            if found is not None:
                yield f"{key}/{cam_id}", sequence, camera, found


def residuals(data_dir: Path, val_fraction: float = 0.1, exclude_actions: str = "") -> Residuals:
    """The detector errors of the training split (never of the held-out tails, nor of exclude_actions)."""
    streams = []
    for _, sequence, camera, found in detected_sequences(data_dir, exclude_actions):
        n = min(len(found), data.sequence_split(len(sequence), val_fraction))
        points, seen = data.mpii_to_h36m(found[:n])
        truth = data.project_to_pixels(sequence[:n], camera)
        errors = (points - truth) / np.maximum(pose_spread(truth, seen), 1e-6)[:, None, None]
        errors[seen < 0.5] = 0.0
        streams.append((errors.astype(np.float32), seen.astype(np.float32)))
    return Residuals(tuple(streams))


def with_residuals(
    pool: data.TrainingPool, data_dir: Path, val_fraction: float, exclude_actions: str = ""
) -> data.TrainingPool:
    """The pool with the detector errors of the training frames (every sequence and camera but those
    of exclude_actions), for TrainConfig.detector_error_prob."""
    streams = residuals(data_dir, val_fraction, exclude_actions).streams
    errors = np.concatenate([e for e, _ in streams]).astype(np.float32)
    seen = np.concatenate([v for _, v in streams]).astype(np.float32)
    return replace(pool, detector_errors=errors, detector_visible=seen)


@dataclass(frozen=True)
class ClipNoise:
    """How synthetic clips are spoiled: clean_prob of them get at most a few pixels of white noise
    and keep every joint; the others the real residuals scaled by U(amplitude), with the detector's
    own visibility in sh_visibility_prob of them; every clip gets occlusions_per_second stretches of
    3-40 frames where one joint is hidden."""

    clean_prob: float = 0.15
    clean_px: float = 3.0
    amplitude: tuple[float, float] = (0.6, 1.4)
    sh_visibility_prob: float = 0.6
    occlusions_per_second: float = 0.15


@dataclass(frozen=True)
class ClipConfig:
    """Which synthetic clips the temporal model learns from: `draws` passes over the training
    sequences, each with a new camera, frame rate and noise (synthesize)."""

    draws: int = 8
    seed: int = 0
    val_fraction: float = 0.1
    noise: ClipNoise = field(default_factory=ClipNoise)


@dataclass(frozen=True)
class Clip:
    """A clip at its own frame rate, lifted frame by frame, and its truth on the 50 Hz grid."""

    poses: np.ndarray  # (n, J, 3) single-frame pose_3d_camera, mm, root at the origin
    keypoints: np.ndarray  # (n, J, 2) px
    visibility: np.ndarray  # (n, J)
    fps: float
    truth: np.ndarray  # (g, J, 3) camera-frame mm, root at the origin, at t = k / grid_fps


def _camera_of(sequence_mm: np.ndarray, rng: np.random.Generator) -> Callable[[np.ndarray], np.ndarray]:
    """A camera that sees the sequence's mean pelvis as synthetic.random_views sees a pose: world mm
    -> camera-frame metres."""
    generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
    rotation, position = (a[0].numpy() for a in synthetic.random_views(1, generator))
    centre = sequence_mm[:, skeleton.ROOT].mean(axis=0)

    def to_camera(x: np.ndarray) -> np.ndarray:
        seen = (x - centre) / 1000.0 @ rotation.T + position
        seen[..., 2] = np.maximum(seen[..., 2], 1.0)  # a person walking up to the camera stays in front
        return seen

    return to_camera


def synthesize(
    sequence_mm: np.ndarray,
    bank: Residuals,
    lift: LiftFunction,
    rng: np.random.Generator,
    noise: ClipNoise,
    grid_fps: float,
    fps: float | None = None,
) -> Clip:
    """One synthetic clip of a (n, J, 3) world sequence at SOURCE_HZ (mirrored half the time)."""
    world = sequence_mm.astype(np.float64)
    if rng.random() < 0.5:
        world = world[:, list(skeleton.MIRROR)].copy()
        world[..., 0] = -world[..., 0]
    fps = float(rng.choice(FPS_CHOICES)) if fps is None else fps
    duration = (len(world) - 1) / SOURCE_HZ
    frames = math.floor(duration * fps + 1e-9) + 1
    grid = math.floor(duration * grid_fps + 1e-9) + 1
    to_camera = _camera_of(world, rng)
    seen = to_camera(catmull_rom(world, np.arange(frames) / fps * SOURCE_HZ))
    keypoints = synthetic.FOCAL_PX * seen[..., :2] / seen[..., 2:3] + synthetic.CENTRE_PX
    visibility = np.ones(keypoints.shape[:2], np.float32)
    if rng.random() < noise.clean_prob:
        keypoints = keypoints + rng.uniform(0.0, noise.clean_px) * rng.standard_normal(keypoints.shape)
    else:
        errors, detector_seen = bank.draw(frames, rng)
        size = pose_spread(keypoints, visibility)[:, None, None]
        keypoints = keypoints + rng.uniform(*noise.amplitude) * errors * size
        if rng.random() < noise.sh_visibility_prob:
            visibility = detector_seen.copy()
    for _ in range(rng.poisson(noise.occlusions_per_second * duration)):
        joint, start, length = rng.integers(1, skeleton.NUM_JOINTS), rng.integers(frames), rng.integers(3, 41)
        visibility[start : start + length, joint] = 0.0
    keypoints = keypoints.astype(np.float32)
    truth = to_camera(catmull_rom(world, np.arange(grid) / grid_fps * SOURCE_HZ)) * 1000.0
    truth -= truth[:, skeleton.ROOT : skeleton.ROOT + 1]
    return Clip(lift(keypoints, visibility), keypoints, visibility, fps, truth.astype(np.float32))


def training_sequences(data_dir: Path, val_fraction: float = 0.1) -> list[np.ndarray]:
    """The training split of every training sequence: (n, J, 3) world mm at SOURCE_HZ."""
    poses = data.load_poses(data_dir, "train")
    return [seq[: data.sequence_split(len(seq), val_fraction)] for _, seq in sorted(poses.items())]


@dataclass(frozen=True)
class ValidationClip:
    """A held-out tail seen by a real camera: its 2D (real detections or projected truth) at `fps`,
    and the truth at every answered frame (camera frame, mm, root at the origin)."""

    name: str  # "S1/Walking 1/54138969"
    keypoints: np.ndarray  # (n, J, 2) px
    visibility: np.ndarray  # (n, J)
    fps: float
    truth: np.ndarray  # (n, J, 3)
    # The 2D as the detector gave it: (n, D, 2) px in `source_format`'s joint order (MPII-16 for
    # Stacked Hourglass, h36m17 for projected truth): what a client sends the service.
    source: np.ndarray
    source_format: str


def validation_clips(
    data_dir: Path, kind: str, val_fraction: float = 0.1, min_frames: int = 10
) -> list[ValidationClip]:
    """The held-out tails of the training subjects with Stacked-Hourglass detections, one clip per
    sequence and camera. kind: "sh25" the detections at their 25 Hz; "sh50" the detections and the
    truth upsampled to 50 Hz (Catmull-Rom); "gt25" the projected truth at 25 Hz."""
    clips = []
    for name, sequence, camera, found in detected_sequences(data_dir):
        split, n = data.sequence_split(len(sequence), val_fraction), min(len(found), len(sequence))
        if n - split < min_frames:
            continue
        world = sequence[split:n].astype(np.float64)
        source, source_format = found[split:n].astype(np.float64), "mpii16"
        points, seen = data.mpii_to_h36m(found[split:n])
        fps = SOURCE_HZ
        if kind == "gt25":
            points, seen = data.project_to_pixels(world, camera), np.ones_like(seen)
            source, source_format = points.astype(np.float64), "h36m17"
        elif kind == "sh50":
            up = np.arange(2 * len(world) - 1) / 2.0
            world, points = catmull_rom(world, up), catmull_rom(points.astype(np.float64), up)
            source = catmull_rom(source, up)
            seen, fps = np.repeat(seen[:1], len(up), axis=0), 2 * SOURCE_HZ
        elif kind != "sh25":
            raise ValueError(f"validation clips are sh25, sh50 or gt25, got {kind!r}")
        truth = data.world_to_camera(world, camera)
        truth = truth - truth[:, skeleton.ROOT : skeleton.ROOT + 1]
        clips.append(
            ValidationClip(
                name,
                points.astype(np.float32),
                seen,
                fps,
                truth.astype(np.float32),
                source.astype(np.float32),
                source_format,
            )
        )
    return clips
