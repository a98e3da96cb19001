"""Weak-perspective camera: reprojection layer and the rotation and scale hidden in K."""

from __future__ import annotations

import torch

from repnet.train.shapes import check_shape


def masked_centre(points: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """Subtract from (N, J, D) points the mean of their visible joints; zero the others.

    visible -- (N, J) visibility: 1 for a visible joint, 0 for a hidden one.
    """
    check_shape(points, (None, None, None), "points (N, J, D)")
    check_shape(visible, tuple(points.shape[:2]), "visibility (N, J)")
    w = visible.unsqueeze(-1)  # (N, J, 1)
    count = w.sum(dim=1, keepdim=True).clamp_min(1.0)  # (N, 1, 1)
    mean = (points * w).sum(dim=1, keepdim=True) / count  # (N, 1, D)
    return (points - mean) * w


def project_weak_perspective(camera: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Reprojection layer W' = K X (Wandt & Rosenhahn 2019, Eq. 1).

    camera -- (N, 2, 3) weak-perspective K; pose -- (N, J, 3) X; returns (N, J, 2) W'.
    """
    check_shape(camera, (None, 2, 3), "camera K (N, 2, 3)")
    check_shape(pose, (camera.shape[0], None, 3), "pose X (N, J, 3)")
    return torch.einsum("nrc,njc->njr", camera, pose)


def camera_scale(camera: torch.Tensor) -> torch.Tensor:
    """The scale s = sqrt(trace(K K^T) / 2) of (N, 2, 3) K (Wandt & Rosenhahn 2019, Eq. 9);
    returns (N,). For K = s R, R two orthonormal rows, it is that s."""
    check_shape(camera, (None, 2, 3), "camera K (N, 2, 3)")
    return torch.sqrt((camera**2).sum(dim=(1, 2)) / 2)


def camera_frame(pose: torch.Tensor, camera: torch.Tensor) -> torch.Tensor:
    """(N, J, 3) poses X turned by the rotation in their (N, 2, 3) K: rows K / s, and their cross
    product (differentiable; for K = s R with R's rows orthonormal, R X)."""
    check_shape(camera, (None, 2, 3), "camera K (N, 2, 3)")
    rows = camera / camera_scale(camera).clamp_min(1e-6)[:, None, None]
    third = torch.linalg.cross(rows[:, 0], rows[:, 1], dim=-1)
    rotation = torch.cat([rows, third[:, None]], dim=1)  # (N, 3, 3)
    return torch.einsum("nrc,njc->njr", rotation, pose)
