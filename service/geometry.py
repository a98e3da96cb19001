"""Camera geometry derived from the model's outputs: scale, rotation and pixel reprojection."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]


def camera_scale(camera: np.ndarray) -> FloatArray:
    """s = sqrt(trace(K K^T) / 2) for (N, 2, 3) weak-perspective K; returns (N,)."""
    k = camera.astype(np.float64)
    return np.asarray(np.sqrt((k**2).sum(axis=(1, 2)) / 2), dtype=np.float32)


def camera_rotation(camera: np.ndarray) -> FloatArray:
    """The rotation hidden in (N, 2, 3) K as (N, 3, 3) matrices with det 1.

    Rows 1 and 2 are the row-orthonormal 2x3 matrix nearest to K / s (polar decomposition,
    U V^T of K's SVD), which is K / s itself when K is a scaled row-orthonormal matrix as the
    RepNet camera loss asks (Wandt & Rosenhahn 2019, Eq. 5); row 3 is their cross product.
    Unlike Gram-Schmidt it favours neither row and stays orthonormal for any K.
    """
    u, _, vt = np.linalg.svd(camera.astype(np.float64), full_matrices=False)  # (N,2,2) (N,2) (N,2,3)
    rows = u @ vt  # (N, 2, 3)
    third = np.cross(rows[:, 0], rows[:, 1])  # (N, 3)
    return np.asarray(np.concatenate([rows, third[:, None]], axis=1), dtype=np.float32)


def rotate_to_camera(pose_3d: np.ndarray, rotation: np.ndarray) -> FloatArray:
    """pose_3d (N, J, 3) in the template frame -> (N, J, 3) in the camera's orientation (X R^T)."""
    return np.asarray(np.einsum("nkj,nij->nki", pose_3d.astype(np.float64), rotation), dtype=np.float32)


def _visible_stats(points: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (N, 2) and standard deviation (N,) of (N, J, 2) points over their visible joints.

    The deviation is taken over all coordinates of the visible joints together, as the
    model's input normalisation does.
    """
    w = visible[..., None].astype(np.float64)  # (N, J, 1)
    count = np.maximum(w.sum(axis=(1, 2)), 1.0)  # (N,)
    safe = np.where(w > 0, points.astype(np.float64), 0.0)  # missing joints may hold NaN
    mean = safe.sum(axis=1) / count[:, None]  # (N, 2)
    centred = (safe - mean[:, None]) * w
    std = np.sqrt((centred**2).sum(axis=(1, 2)) / (2 * count))  # (N,)
    return mean, std


def reproject(
    camera: np.ndarray, pose_3d: np.ndarray, keypoints_2d: np.ndarray, visible: np.ndarray
) -> FloatArray:
    """Project pose_3d (N, J, 3) with K (N, 2, 3) back into the input's pixels; returns (N, J, 2).

    K X matches the normalised input up to a translation, so it is centred on its visible joints,
    scaled by the input's standard deviation and moved to the input's visible mean.
    """
    projected = np.einsum("nij,nkj->nki", camera.astype(np.float64), pose_3d)  # (N, J, 2)
    proj_mean, _ = _visible_stats(projected, visible)
    in_mean, in_std = _visible_stats(keypoints_2d, visible)
    pixels = (projected - proj_mean[:, None]) * in_std[:, None, None] + in_mean[:, None]
    return np.asarray(pixels, dtype=np.float32)


def reprojection_error(reprojection: np.ndarray, keypoints_2d: np.ndarray, visible: np.ndarray) -> FloatArray:
    """Mean pixel distance (N,) between (N, J, 2) reprojection and input over the visible joints."""
    w = visible.astype(np.float64)  # (N, J)
    safe = np.where(w[..., None] > 0, keypoints_2d.astype(np.float64), 0.0)
    dist = np.linalg.norm(reprojection.astype(np.float64) - safe, axis=-1) * w  # (N, J)
    return np.asarray(dist.sum(axis=1) / np.maximum(w.sum(axis=1), 1.0), dtype=np.float32)
