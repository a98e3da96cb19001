"""RepNet losses: reprojection, camera, Wasserstein critic and gradient penalty."""

from __future__ import annotations

from collections.abc import Callable

import torch

from repnet.core import skeleton
from repnet.train.camera import masked_centre, project_weak_perspective
from repnet.train.shapes import check_shape


def reprojection_loss(
    points_2d: torch.Tensor,
    visible: torch.Tensor,
    pose: torch.Tensor,
    camera: torch.Tensor,
    norm: str = "fro",
) -> torch.Tensor:
    """Reprojection loss L_rep: mean over the batch of ||W - K X||_F, the columns of hidden joints
    zeroed (Wandt & Rosenhahn 2019, Eq. 2).

    points_2d -- (N, J, 2) normalised input W (centred on its visible joints);
    visible -- (N, J); pose -- (N, J, 3); camera -- (N, 2, 3).
    Weak perspective leaves the translation free, so K X is centred on the same visible
    joints as W before the difference. norm "l1" is the authors' code instead: the sum of
    |W - K X| over the coordinates, weighted per joint (skeleton.REPROJECTION_WEIGHTS),
    divided by 2J.
    """
    n, j = points_2d.shape[:2]
    check_shape(points_2d, (n, j, 2), "W (N, J, 2)")
    check_shape(visible, (n, j), "visibility (N, J)")
    check_shape(pose, (n, j, 3), "pose X (N, J, 3)")
    check_shape(camera, (n, 2, 3), "camera K (N, 2, 3)")
    reprojected = masked_centre(project_weak_perspective(camera, pose), visible)  # (N, J, 2)
    diff = (points_2d - reprojected) * visible.unsqueeze(-1)
    if norm == "l1":
        weights = torch.as_tensor(skeleton.REPROJECTION_WEIGHTS, dtype=diff.dtype, device=diff.device)
        return (diff.abs() * weights[:, None]).sum(dim=(1, 2)).mean() / (2 * diff.shape[1])
    if norm != "fro":
        raise ValueError(f"reprojection norm must be fro or l1, got {norm!r}")
    return diff.pow(2).sum(dim=(1, 2)).add(1e-12).sqrt().mean()


def camera_loss(camera: torch.Tensor, norm: str = "fro") -> torch.Tensor:
    """Camera loss L_cam: mean of ||(2 / trace(K K^T)) K K^T - I_2||_F over (N, 2, 3) K (Wandt &
    Rosenhahn 2019, Eq. 10); norm "l1" sums the absolute entries instead (the authors' code).

    Zero exactly when K K^T = s^2 I (Eq. 8): K is a scaled orthographic projection (rows
    orthogonal, equal norm).
    """
    check_shape(camera, (None, 2, 3), "camera K (N, 2, 3)")
    kkt = camera @ camera.transpose(1, 2)  # (N, 2, 2)
    trace = kkt.diagonal(dim1=1, dim2=2).sum(dim=1).clamp_min(1e-12)  # (N,)
    eye = torch.eye(2, dtype=camera.dtype, device=camera.device)
    residual = (2.0 / trace)[:, None, None] * kkt - eye
    if norm == "l1":
        return residual.abs().sum(dim=(1, 2)).mean()
    if norm != "fro":
        raise ValueError(f"camera norm must be fro or l1, got {norm!r}")
    return residual.pow(2).sum(dim=(1, 2)).add(1e-12).sqrt().mean()


def bone_lengths(pose: torch.Tensor) -> torch.Tensor:
    """(N, J, 3) poses -> (N, B) lengths of the skeleton's bone vectors b = child - parent
    (Wandt & Rosenhahn 2019, Eq. 3), differentiable."""
    check_shape(pose, (None, None, 3), "poses (N, J, 3)")
    parents, children = zip(*skeleton.BONES, strict=True)
    return (pose[:, list(children)] - pose[:, list(parents)]).pow(2).sum(dim=-1).add(1e-12).sqrt()


def bone_loss(pose: torch.Tensor, mean_lengths: torch.Tensor) -> torch.Tensor:
    """Mean |bone length - its mean over real poses| of (N, J, 3) poses; mean_lengths (B,)."""
    check_shape(mean_lengths, (len(skeleton.BONES),), "mean lengths (B,)")
    return (bone_lengths(pose) - mean_lengths).abs().mean()


def pose_loss(pose: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean per-joint Euclidean distance of (N, J, 3) poses (the synthetic warm start)."""
    check_shape(pose, (None, None, 3), "poses (N, J, 3)")
    check_shape(target, tuple(pose.shape), "targets (N, J, 3)")
    return (pose - target).pow(2).sum(dim=-1).add(1e-12).sqrt().mean()


def gradient_penalty(
    critic: Callable[[torch.Tensor], torch.Tensor], real: torch.Tensor, fake: torch.Tensor
) -> torch.Tensor:
    """WGAN-GP term E[(||grad D(x_hat)||_2 - 1)^2] on random interpolates (Gulrajani et al. 2017).

    real, fake -- (N, J, 3) poses.
    """
    check_shape(real, (None, None, 3), "real poses (N, J, 3)")
    check_shape(fake, tuple(real.shape), "fake poses (N, J, 3)")
    alpha = torch.rand(real.shape[0], 1, 1, dtype=real.dtype, device=real.device)
    mixed = (alpha * real + (1 - alpha) * fake).requires_grad_(True)
    (grad,) = torch.autograd.grad(critic(mixed).sum(), mixed, create_graph=True)
    return (grad.flatten(1).norm(dim=1) - 1).pow(2).mean()


def critic_loss(
    critic: Callable[[torch.Tensor], torch.Tensor],
    real: torch.Tensor,
    fake: torch.Tensor,
    gp_weight: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """WGAN-GP critic loss D(fake) - D(real) + lambda * GP; also returns the Wasserstein estimate."""
    wasserstein = critic(real).mean() - critic(fake).mean()
    return -wasserstein + gp_weight * gradient_penalty(critic, real, fake), wasserstein.detach()
