"""Weak-perspective camera: reprojection layer and the rotation and scale hidden in K."""

from __future__ import annotations

import torch


def masked_centre(points: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """Subtract from (N, J, D) points the mean of their visible joints; zero the others.

    visible -- (N, J) with 1 for a visible joint and 0 for a missing one.
    """
    w = visible.unsqueeze(-1)  # (N, J, 1)
    count = w.sum(dim=1, keepdim=True).clamp_min(1.0)  # (N, 1, 1)
    mean = (points * w).sum(dim=1, keepdim=True) / count  # (N, 1, D)
    return (points - mean) * w


def project_weak_perspective(camera: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Reprojection layer W' = K X (Wandt & Rosenhahn 2019, Eq. 2).

    camera -- (N, 2, 3) weak-perspective K; pose -- (N, J, 3); returns (N, J, 2).
    """
    return torch.einsum("nij,nkj->nki", camera, pose)


def camera_scale(camera: torch.Tensor) -> torch.Tensor:
    """s = sqrt(trace(K K^T) / 2) for (N, 2, 3) K; returns (N,)."""
    return torch.sqrt((camera**2).sum(dim=(1, 2)) / 2)
