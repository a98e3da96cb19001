"""The Human3.6M test frames (S9/S11) an evaluation scores: 2D inputs, camera-frame truth, labels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from repnet.train import data
from repnet.train.data import action_name

DATASET_LABEL = "S9/S11 without S9 Discussion 1"
# Detections may miss a few frames at a sequence's end; more means the wrong frame rate.
MAX_LENGTH_MISMATCH = 0.02


@dataclass(frozen=True)
class TestSet:
    """Test frames of all evaluated (subject, sequence, camera) triples, concatenated."""

    points: np.ndarray  # (M, 17, 2) float32 px
    visible: np.ndarray  # (M, 17) float32 in {0, 1}
    gt: np.ndarray  # (M, 17, 3) float32 camera-frame mm
    focal: np.ndarray  # (M, 2) the camera's focal lengths, px
    centre: np.ndarray  # (M, 2) the camera's principal point, px
    action: np.ndarray  # (M,) int index into actions
    subject: np.ndarray  # (M,) int index into subjects
    misaligned: np.ndarray  # (M,) bool: frame of a data.MISALIGNED sequence
    actions: tuple[str, ...]
    subjects: tuple[str, ...]
    sequences: int  # camera sequences evaluated
    skipped: tuple[str, ...]  # "<subject>/<sequence>/<camera>" without detections
    notes: tuple[str, ...]  # length mismatches that were trimmed


def _detections_2d(
    det: np.ndarray, world: np.ndarray, name: str, frame_step: int, notes: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, D, 2) MPII detections of a camera sequence, D = data.MPII_JOINTS -> (world, points,
    visible), stepped."""
    if len(det) != len(world):
        if abs(len(det) - len(world)) > MAX_LENGTH_MISMATCH * len(world):
            raise ValueError(
                f"detections {name}: expected {len(world)} frames (50 Hz, as poses_3d_test.npz), "
                f"got {len(det)}"
            )
        notes.append(f"{name}: {len(det)} detections for {len(world)} poses, trimmed")
        n = min(len(det), len(world))
        world, det = world[:n], det[:n]
    points, visible = data.mpii_to_h36m(det[::frame_step])
    finite = np.isfinite(points).all(axis=-1)  # a detector may leave NaN for a missed joint
    visible *= finite
    points[~finite] = 0.0
    return world[::frame_step], points, visible


def build_test_set(
    poses: dict[str, np.ndarray],
    cameras: dict[str, dict[str, data.Camera]],
    detections: dict[str, np.ndarray] | None,
    frame_step: int = 1,
    cameras_used: tuple[str, ...] = data.CAMERAS,
) -> TestSet:
    """Frames of `poses` ({"S9/Walking 1": (N, 17, 3) world mm}) seen by each camera.

    2D inputs are the distorted GT projections, or the MPII-16 `detections` mapped to the
    17 joints (spine masked); camera sequences without detections are skipped.
    """
    actions = tuple(sorted({action_name(key.split("/", 1)[1]) for key in poses}))
    subjects = tuple(sorted({key.split("/")[0] for key in poses}))
    keys = ("points", "visible", "gt", "focal", "centre", "action", "subject", "misaligned")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    skipped: list[str] = []
    notes: list[str] = []
    for key in sorted(poses):
        subject, sequence = key.split("/", 1)
        for cam_id in cameras_used:
            cam = cameras[subject][cam_id]
            if detections is None:
                world = poses[key][::frame_step]
                points = data.project_to_pixels(world, cam)
                visible = np.ones(points.shape[:2], dtype=np.float32)
            elif f"{key}/{cam_id}" in detections:
                det = detections[f"{key}/{cam_id}"]
                world, points, visible = _detections_2d(det, poses[key], f"{key}/{cam_id}", frame_step, notes)
            else:
                skipped.append(f"{key}/{cam_id}")
                continue
            parts["points"].append(points)
            parts["visible"].append(visible)
            parts["gt"].append(data.world_to_camera(world, cam))
            parts["focal"].append(np.repeat(cam.f[None].astype(np.float32), len(points), axis=0))
            parts["centre"].append(np.repeat(cam.c[None].astype(np.float32), len(points), axis=0))
            parts["action"].append(np.full(len(points), actions.index(action_name(sequence))))
            parts["subject"].append(np.full(len(points), subjects.index(subject)))
            parts["misaligned"].append(np.full(len(points), key in data.MISALIGNED))
    if not parts["points"]:
        raise ValueError(f"no test sequence to evaluate ({len(skipped)} camera sequences lack detections)")
    arrays = {k: np.concatenate(v) for k, v in parts.items()}
    return TestSet(
        **arrays,
        actions=actions,
        subjects=subjects,
        sequences=len(parts["points"]),
        skipped=tuple(skipped),
        notes=tuple(notes),
    )


def select_sequences(
    poses: dict[str, np.ndarray], subjects: list[str], actions: list[str]
) -> dict[str, np.ndarray]:
    """The sequences of `subjects` and, unless `actions` is empty, of those actions."""
    chosen = {
        key: world
        for key, world in poses.items()
        if key.split("/")[0] in subjects and (not actions or action_name(key.split("/", 1)[1]) in actions)
    }
    if not chosen:
        raise ValueError(f"no test sequence of subjects {subjects} and actions {actions}")
    return chosen
