"""Validation during training: the held-out sets a run scores itself on, and the figures it logs.

The sets are the tails of the training subjects' sequences (data.build_training_sets), never
S9/S11: val_size poses of each 2D input kind, and of GT 2D also with pixel noise and mirrored.
repnet.train.validate re-scores a checkpoint on the same sets from the command line.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from repnet.core import geometry, skeleton
from repnet.train import data, metrics
from repnet.train.config import TrainConfig
from repnet.train.losses import bone_lengths
from repnet.train.model import LiftingGraph, RepNet

# A bone over this many times its true mean length makes an answer "wild" (validation's wild_pct).
WILD_RATIO = 3.0


def validate(
    generator: RepNet, val: data.ValidationSet, device: torch.device, mirror_average: bool = False
) -> dict[str, float]:
    """Protocol I and II MPJPE, symmetry error and limb bone length std (mm) on a validation set;
    mirror_average: of the graph that averages each answer with the mirrored one (LiftingGraph)."""
    generator.eval()
    graph = LiftingGraph(generator, mirror_average=mirror_average)
    poses, cameras = [], []
    with torch.no_grad():
        for start in range(0, len(val.points_2d), 4096):
            rows = slice(start, start + 4096)
            pose, cam = graph(
                torch.from_numpy(val.points_2d[rows]).to(device),
                torch.from_numpy(val.visible[rows]).to(device),
            )[:2]
            poses.append(pose.cpu().numpy())
            cameras.append(cam.cpu().numpy())
    generator.train()
    pose, camera = np.concatenate(poses), np.concatenate(cameras)
    ray: dict[str, float] = {}
    if val.focal is not None and val.centre is not None:
        rotation = geometry.ray_turn(val.points_2d, val.visible, val.focal, val.centre)
        pose_cam, pose_ray = metrics.camera_frames(pose, camera, rotation)
        ray["mpjpe_ray"] = metrics.mpjpe(pose_ray, val.poses_camera)
    else:
        pose_cam = metrics.to_camera_frame(pose, camera)
    lengths = bone_lengths(torch.from_numpy(pose)).numpy()  # (N, B) mm
    truth = bone_lengths(torch.from_numpy(val.poses_camera)).numpy().mean(axis=0)  # (B,)
    return {
        "mpjpe": metrics.mpjpe(pose_cam, val.poses_camera),
        **ray,
        "pa_mpjpe": metrics.pa_mpjpe(pose, val.poses_camera),
        "symmetry": float(metrics.symmetry_error(pose).mean()),
        "bone_std": float(metrics.limb_length_std(pose).mean()),
        "wild_pct": 100.0 * float(((lengths / truth).max(axis=1) > WILD_RATIO).mean()),
    }


def validation_sets(
    config: TrainConfig, held_out: dict[str, data.ValidationSet]
) -> dict[str, data.ValidationSet]:
    """The sets a run validates on, from build_training_sets' held-out tails: val_size poses of each
    input kind, and of GT 2D also with noise (gt_noise) and mirrored (gt_mirror). The same draw
    for the same seed, so runs and repnet.train.validate score the same poses."""
    rng = np.random.default_rng(config.seed)
    sets = {kind: _subsample(val, config.val_size, rng) for kind, val in held_out.items()}
    if config.val_noise_px > 0 and "gt" in sets:
        sets["gt_noise"] = with_noise(sets["gt"], config.val_noise_px, rng)
    if config.val_mirror and "gt" in sets:
        sets["gt_mirror"] = mirrored(sets["gt"])
    return sets


def _subsample(val: data.ValidationSet, size: int, rng: np.random.Generator) -> data.ValidationSet:
    idx = np.sort(rng.choice(len(val.points_2d), size=min(size, len(val.points_2d)), replace=False))
    return data.ValidationSet(
        poses_camera=val.poses_camera[idx],
        points_2d=val.points_2d[idx],
        visible=val.visible[idx],
        focal=None if val.focal is None else val.focal[idx],
        centre=None if val.centre is None else val.centre[idx],
    )


def with_noise(val: data.ValidationSet, sigma_px: float, rng: np.random.Generator) -> data.ValidationSet:
    """The same validation poses with N(0, sigma_px) px added to their 2D points."""
    noise = rng.normal(0.0, sigma_px, val.points_2d.shape).astype(val.points_2d.dtype)
    return dataclasses.replace(val, points_2d=val.points_2d + noise)


def with_hidden_joints(val: data.ValidationSet, count: int, rng: np.random.Generator) -> data.ValidationSet:
    """The same validation poses with `count` random non-root joints of each hidden."""
    points, visible = data.hide_random_joints(val.points_2d, val.visible, count, rng)
    return dataclasses.replace(val, points_2d=points, visible=visible)


def mirrored(val: data.ValidationSet) -> data.ValidationSet:
    """The validation poses mirrored: 2D flipped about each camera's principal point, 3D (camera
    frame) flipped in x, left and right joints swapped in both."""
    if val.centre is None:
        raise ValueError("mirroring a validation set needs its principal points")
    swap = list(skeleton.MIRROR)
    points = val.points_2d[:, swap].copy()
    points[..., 0] = 2 * val.centre[:, None, 0] - points[..., 0]
    poses = val.poses_camera[:, swap].copy()
    poses[..., 0] = -poses[..., 0]
    return dataclasses.replace(val, poses_camera=poses, points_2d=points, visible=val.visible[:, swap].copy())
