"""Pose metrics: MPJPE (Protocol I and II), PCK3D, AUC, symmetry error (the rotation in K, and the
turn along the ray, are repnet.core.geometry's, as the service computes them)."""

from __future__ import annotations

import numpy as np

from repnet.core import geometry, skeleton
from repnet.train.data import procrustes


def camera_frames(pose: np.ndarray, camera: np.ndarray, ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, J, 3) poses turned by K's rotation (Protocol I), and the same turned along the ray too:
    to_camera_frame without and with `ray`, with one polar decomposition of K."""
    rotation = geometry.rotation_of_camera(camera)
    return np.einsum("nrc,njc->njr", rotation, pose), np.einsum("nrc,njc->njr", ray @ rotation, pose)


def to_camera_frame(pose: np.ndarray, camera: np.ndarray, ray: np.ndarray | None = None) -> np.ndarray:
    """Rotate (N, J, 3) template-frame poses into the camera's orientation (Protocol I): by the
    rotation in K, then, given (N, 3, 3) ray rotations (geometry.ray_turn), by the turn of the ray."""
    rotation = geometry.rotation_of_camera(camera)
    if ray is not None:
        rotation = ray @ rotation
    return np.einsum("nrc,njc->njr", rotation, pose)


def off_axis_errors(gt: np.ndarray, ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Protocol I joint errors (N, J) of a perfect lifter that lacks the camera's intrinsics, and
    the (N,) angles in degrees between the optical axis and the ray to each person.

    Its pose and its view along the ray (ray_rotation, (N, 3, 3)) are both exact, so its answer
    in the camera frame is the (N, J, 3) camera-frame ground truth turned back by the ray: the
    floor of the plain P-I for any lifter of centred 2D inputs, which cannot see where in the
    image the person stands."""
    seen = np.einsum("ncr,njc->njr", ray, root_align(gt.astype(np.float64)))  # ray^T X
    cosine = (np.trace(ray, axis1=1, axis2=2) - 1.0) / 2.0
    return joint_errors(seen, gt), np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def root_align(pose: np.ndarray) -> np.ndarray:
    """(N, J, 3) -> the same with the root (pelvis) at the origin."""
    return pose - pose[:, skeleton.ROOT : skeleton.ROOT + 1]


def joint_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(N, J) Euclidean joint errors of root-aligned (N, J, 3) poses (Protocol I)."""
    return np.linalg.norm(root_align(pred) - root_align(gt), axis=-1)


def procrustes_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(N, J) joint errors after aligning each prediction to its ground truth by a similarity."""
    pred64, gt64 = pred.astype(np.float64), gt.astype(np.float64)
    scale, rot, trans = procrustes(pred64, gt64)
    aligned = scale[:, None, None] * pred64 @ rot.transpose(0, 2, 1) + trans[:, None]
    return np.linalg.norm(aligned - gt64, axis=-1)


def mpjpe(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean per-joint position error after root alignment, in the poses' unit."""
    return float(joint_errors(pred, gt).mean())


def pa_mpjpe(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean per-joint position error after Procrustes alignment (Protocol II)."""
    return float(procrustes_errors(pred, gt).mean())


def pck(errors: np.ndarray, threshold: float = 150.0) -> float:
    """Percentage of joint errors within threshold (PCK3D, in %)."""
    return float((errors <= threshold).mean() * 100.0)


def auc(errors: np.ndarray, max_threshold: float = 150.0, steps: int = 31) -> float:
    """Area under the PCK curve for thresholds 0..max_threshold, normalised to [0, 100]."""
    thresholds = np.linspace(0.0, max_threshold, steps)
    return float(np.mean([pck(errors, t) for t in thresholds]))


def segment_lengths(pose: np.ndarray, segments: tuple[tuple[int, int], ...]) -> np.ndarray:
    """(N, J, 3) poses -> (N, len(segments)) lengths of the given (parent, child) joint pairs (numpy;
    losses.bone_lengths is the differentiable torch one of all skeleton.BONES)."""
    parents, children = np.asarray(segments).T
    return np.linalg.norm(pose[:, children] - pose[:, parents], axis=-1)


def symmetry_error(pose: np.ndarray) -> np.ndarray:
    """(N,) symmetry error of (N, J, 3) poses: the sum over the arm and leg bones of |left - right|
    length (Wandt & Rosenhahn 2019, Sec. 4.3)."""
    left = segment_lengths(pose, tuple(pair[0] for pair in skeleton.SYMMETRIC_BONES))
    right = segment_lengths(pose, tuple(pair[1] for pair in skeleton.SYMMETRIC_BONES))
    return np.abs(left - right).sum(axis=1)


def summarize(
    errors_p1: np.ndarray,
    errors_p2: np.ndarray,
    symmetry: np.ndarray,
    gt_symmetry: np.ndarray,
    errors_p1_ray: np.ndarray | None = None,
) -> dict[str, float]:
    """Figures of one group of poses, in mm and %.

    errors_p1, errors_p2 -- (N, J) joint errors under Protocol I and II; symmetry,
    gt_symmetry -- (N,) symmetry errors of the predictions and of the ground truth;
    errors_p1_ray -- Protocol I with the ray to the person (known intrinsics), if measured.
    Medians are over the per-pose mean errors; PCK3D (150 mm) and AUC (0-150 mm) over all joints.
    """
    pose_p1, pose_p2 = errors_p1.mean(axis=1), errors_p2.mean(axis=1)
    ray: dict[str, float] = {}
    if errors_p1_ray is not None:
        pose_ray = errors_p1_ray.mean(axis=1)
        ray = {"mpjpe_ray": float(pose_ray.mean()), "mpjpe_ray_median": float(np.median(pose_ray))}
    return {
        **ray,
        "poses": int(len(errors_p1)),
        "mpjpe": float(pose_p1.mean()),
        "mpjpe_median": float(np.median(pose_p1)),
        "pa_mpjpe": float(pose_p2.mean()),
        "pa_mpjpe_median": float(np.median(pose_p2)),
        "pck3d_150": pck(errors_p1),
        "auc": auc(errors_p1),
        "pa_pck3d_150": pck(errors_p2),
        "pa_auc": auc(errors_p2),
        "symmetry_mean": float(symmetry.mean()),
        "symmetry_std": float(symmetry.std()),
        "symmetry_max": float(symmetry.max()),
        "gt_symmetry_mean": float(gt_symmetry.mean()),
        "gt_symmetry_std": float(gt_symmetry.std()),
        "gt_symmetry_max": float(gt_symmetry.max()),
    }


LIMB_BONES: tuple[tuple[int, int], ...] = tuple(bone for pair in skeleton.SYMMETRIC_BONES for bone in pair)


def limb_length_std(pose: np.ndarray) -> np.ndarray:
    """(8,) standard deviation over (N, J, 3) poses of each arm and leg bone's length.

    One subject's bones keep their length; a lifter whose limbs stretch and shrink from
    pose to pose shows it here (the ground truth of one subject: a few mm).
    """
    return segment_lengths(pose, LIMB_BONES).std(axis=0)


def acceleration(pose: np.ndarray) -> np.ndarray:
    """(n - 2, ...) the second time differences of a clip's (n, ...) poses (per frame^2)."""
    return pose[2:] - 2 * pose[1:-1] + pose[:-2]


def acceleration_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n - 2,) mean per-joint norm of the difference of second time differences of a clip's
    (n, J, 3) answers and truth (mm / frame^2), as VideoPose3D and SmoothNet define it (root-relative
    poses in the camera's orientation)."""
    return np.linalg.norm(acceleration(pred) - acceleration(gt), axis=-1).mean(axis=-1)


def velocity_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(n - 1,) MPJVE of a clip: mean per-joint norm of the difference of first time differences
    (mm / frame)."""
    return np.linalg.norm(np.diff(pred, axis=0) - np.diff(gt, axis=0), axis=-1).mean(axis=-1)


def average_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n of a vector, ties given the mean of the ranks they span (as Spearman's needs)."""
    order = np.argsort(values, kind="stable")
    sorted_values = values[order]
    starts = np.flatnonzero(np.r_[True, sorted_values[1:] != sorted_values[:-1]])
    ends = np.r_[starts[1:], len(values)]  # one past each run of equal values
    ranks = np.empty(len(values))
    ranks[order] = np.repeat((starts + ends + 1) / 2.0, ends - starts)  # mean of ranks starts+1..ends
    return ranks


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of two equal-length vectors: Pearson's of their average ranks
    (0 when either is constant)."""
    ra = average_ranks(np.asarray(a, np.float64))
    rb = average_ranks(np.asarray(b, np.float64))
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denominator = np.sqrt((ra**2).sum() * (rb**2).sum())
    return float((ra * rb).sum() / denominator) if denominator > 0 else 0.0
