"""Training-time augmentation: hidden joints, real 2D batches, and corrupted poses for the critic."""

from __future__ import annotations

import torch

from repnet.core import skeleton
from repnet.train import data, metrics
from repnet.train.config import TrainConfig
from repnet.train.model import normalize_keypoints
from repnet.train.shapes import check_shape


def augment_visibility(visible: torch.Tensor, config: TrainConfig, gen: torch.Generator) -> torch.Tensor:
    """Hide 1..mask_max random non-root joints in a mask_prob share of the (N, J) masks, and the
    spine in another spine_mask_prob share, so that the network learns to lift occluded poses."""
    n, j = visible.shape
    dev = visible.device
    scores = torch.rand(n, j, generator=gen, device=dev)
    scores[:, skeleton.ROOT] = 2.0  # never picked
    count = torch.randint(1, config.mask_max + 1, (n, 1), generator=gen, device=dev)
    count = count * (torch.rand(n, 1, generator=gen, device=dev) < config.mask_prob)
    rank = scores.argsort(dim=1).argsort(dim=1)  # (N, J) rank of each joint's score
    hide = rank < count
    hide[:, skeleton.SPINE] |= torch.rand(n, generator=gen, device=dev) < config.spine_mask_prob
    return visible * (~hide).to(visible.dtype)


def sample_2d(
    pool: data.TrainingPool, config: TrainConfig, device: torch.device, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """A random normalised 2D batch of the pool's real inputs: (N, J, 2) points and (N, J)
    visibility, N = batch_size, with augment_visibility's hidden joints and noise_px pixel noise."""
    idx = torch.randint(0, pool.points_2d.shape[0], (config.batch_size,), generator=gen)
    points = torch.from_numpy(pool.points_2d[idx.numpy()]).to(device)
    visible = augment_visibility(torch.from_numpy(pool.visible[idx.numpy()]).to(device), config, gen)
    if config.noise_px > 0:
        points = points + config.noise_px * torch.randn(points.shape, generator=gen, device=device)
    return normalize_keypoints(points, visible), visible


def _subtrees() -> torch.Tensor:
    """(J, J) mask: row c marks joint c and every joint below it in the kinematic tree."""
    mask = torch.eye(skeleton.NUM_JOINTS, dtype=torch.bool)
    for joint in range(skeleton.NUM_JOINTS):  # parents come before their children
        parent = skeleton.PARENTS[joint]
        while parent >= 0:
            mask[parent, joint] = True
            parent = skeleton.PARENTS[parent]
    return mask


SUBTREES = _subtrees()
LIMB_CHILDREN = torch.tensor([child for _, child in metrics.LIMB_BONES])


def corrupt_poses(poses: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Implausible versions of (N, J, 3) real poses (metres), a third each way: one arm or leg
    bone 25-50 % longer or 20-40 % shorter (the joints below it moved along); two non-root
    joints swapped; every joint jittered by N(0, 3-8 cm)."""
    check_shape(poses, (None, skeleton.NUM_JOINTS, 3), "real poses (N, J, 3)")
    n = poses.shape[0]
    out = poses.clone()
    kind = torch.randint(0, 3, (n,), generator=gen)
    # 0: a limb bone stretched or shrunk
    child = LIMB_CHILDREN[torch.randint(0, len(LIMB_CHILDREN), (n,), generator=gen)]
    parent = torch.tensor(skeleton.PARENTS)[child]
    longer = torch.rand(n, generator=gen) < 0.5
    factor = torch.where(
        longer, 1.25 + 0.25 * torch.rand(n, generator=gen), 0.6 + 0.2 * torch.rand(n, generator=gen)
    )
    rows = torch.arange(n)
    bone = poses[rows, child] - poses[rows, parent]  # (N, 3)
    moved = SUBTREES[child].to(poses.dtype)  # (N, J)
    stretched = poses + (factor - 1)[:, None, None] * moved[:, :, None] * bone[:, None, :]
    # 1: two joints swapped
    a = torch.randint(1, skeleton.NUM_JOINTS, (n,), generator=gen)
    b = 1 + (a - 1 + torch.randint(1, skeleton.NUM_JOINTS - 1, (n,), generator=gen)) % (
        skeleton.NUM_JOINTS - 1
    )
    swapped = poses.clone()
    swapped[rows, a], swapped[rows, b] = poses[rows, b], poses[rows, a]
    # 2: jitter
    sigma = 0.03 + 0.05 * torch.rand(n, 1, 1, generator=gen)
    jittered = poses + sigma * torch.randn(poses.shape, generator=gen)
    out = torch.where((kind == 0)[:, None, None], stretched, out)
    out = torch.where((kind == 1)[:, None, None], swapped, out)
    out = torch.where((kind == 2)[:, None, None], jittered, out)
    return out - out[:, skeleton.ROOT : skeleton.ROOT + 1]


def with_detector_errors(
    pixels: torch.Tensor,
    visible: torch.Tensor,
    pool: data.TrainingPool,
    config: TrainConfig,
    gen: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, J, 2) synthetic pixels and (N, J) visibility with a real detector's error in a
    detector_error_prob share of them (TrainConfig); draws nothing when that share is 0."""
    if config.detector_error_prob <= 0:
        return pixels, visible
    if pool.detector_errors is None or pool.detector_visible is None:
        raise ValueError(
            "detector_error_prob > 0 needs the pool's detector errors (repnet.train.sequences.residuals)"
        )
    n = pixels.shape[0]
    check_shape(pixels, (n, skeleton.NUM_JOINTS, 2), "pixels")
    chosen = torch.rand(n, generator=gen) < config.detector_error_prob  # (N,)
    idx = torch.randint(0, len(pool.detector_errors), (n,), generator=gen).numpy()
    errors = torch.from_numpy(pool.detector_errors[idx])  # (N, J, 2) in units of the pose's spread
    seen = torch.from_numpy(pool.detector_visible[idx])  # (N, J)
    scale = config.detector_error_min + (config.detector_error_max - config.detector_error_min) * torch.rand(
        n, generator=gen
    )
    centred = pixels - pixels.mean(dim=1, keepdim=True)
    spread = centred.pow(2).mean(dim=(1, 2)).sqrt()  # (N,) px: all joints are visible here
    moved = pixels + (scale * spread)[:, None, None] * errors
    pixels = torch.where(chosen[:, None, None], moved.to(pixels.dtype), pixels)
    visible = torch.where(chosen[:, None], visible * seen.to(visible.dtype), visible)
    return pixels, visible
