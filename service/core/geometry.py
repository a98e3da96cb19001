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
    """The rotation hidden in (N, 2, 3) K as (N, 3, 3) float32 matrices with det 1 (rotation_of_camera)."""
    return np.asarray(rotation_of_camera(camera), dtype=np.float32)


def rotation_of_camera(camera: np.ndarray) -> npt.NDArray[np.float64]:
    """The rotation hidden in (N, 2, 3) K as (N, 3, 3) float64 matrices with det 1: the service's
    replies (camera_rotation) and training's Protocol I (repnet.train.metrics) use this one.

    Rows 1 and 2 are the row-orthonormal 2x3 matrix nearest to K / s: the orthogonal factor Q of
    K's polar decomposition K = P Q, P = (K K^T)^(1/2), which equals U V^T of K's SVD and is
    K / s itself when K is a scaled row-orthonormal matrix as the RepNet camera loss asks (Wandt &
    Rosenhahn 2019, Eq. 8); row 3 is their cross product. Unlike Gram-Schmidt it favours neither
    row and stays orthonormal for any K. Q = P^-1 K uses the closed form of a 2x2 matrix square
    root, (M + sqrt(det M) I) / sqrt(tr M + 2 sqrt(det M)); cameras of rank < 2 go through the SVD.
    """
    k = camera.astype(np.float64)
    m = k @ k.transpose(0, 2, 1)  # (N, 2, 2) K K^T
    det = np.maximum(m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0], 0.0)
    trace = m[:, 0, 0] + m[:, 1, 1]
    root_det = np.sqrt(det)
    full_rank = det > 1e-12 * np.maximum(trace, 1e-300) ** 2
    # P^-1 = t (M + r I)^-1 with r = sqrt(det M), t = sqrt(tr M + 2 r); (M + r I)^-1 by its adjugate.
    r = np.where(full_rank, root_det, 1.0)
    t = np.sqrt(trace + 2 * r)
    a, b, c, d = m[:, 0, 0] + r, m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] + r
    scale = t / np.where(full_rank, a * d - b * c, 1.0)
    adjugate = np.empty((len(k), 2, 2))  # filled in place: np.stack cost more than the arithmetic
    adjugate[:, 0, 0], adjugate[:, 0, 1], adjugate[:, 1, 0], adjugate[:, 1, 1] = d, -b, -c, a
    rows = (adjugate * scale[:, None, None]) @ k  # (N, 2, 3)
    if not full_rank.all():
        u, _, vt = np.linalg.svd(k[~full_rank], full_matrices=False)
        rows[~full_rank] = u @ vt
    r0, r1 = rows[:, 0], rows[:, 1]
    rotation = np.empty((len(k), 3, 3))
    rotation[:, :2] = rows
    rotation[:, 2, 0] = r0[:, 1] * r1[:, 2] - r0[:, 2] * r1[:, 1]
    rotation[:, 2, 1] = r0[:, 2] * r1[:, 0] - r0[:, 0] * r1[:, 2]
    rotation[:, 2, 2] = r0[:, 0] * r1[:, 1] - r0[:, 1] * r1[:, 0]
    return rotation


def rotation_to_ray(direction: np.ndarray) -> npt.NDArray[np.float64]:
    """(N, 3) directions in front of a camera (z > 0) -> (N, 3, 3) float64, the smallest rotations
    that take the optical axis (0, 0, 1) onto each of them (Rodrigues' formula for the turn from
    (0, 0, 1) to the unit direction z: I + [v]x + [v]x^2 / (1 + z3) with v = (0, 0, 1) x z)."""
    z = direction.astype(np.float64) / np.linalg.norm(direction, axis=1, keepdims=True)
    vx = np.zeros((len(z), 3, 3))
    vx[:, 0, 2], vx[:, 1, 2], vx[:, 2, 0], vx[:, 2, 1] = z[:, 0], z[:, 1], -z[:, 0], -z[:, 1]
    turn: npt.NDArray[np.float64] = np.eye(3)[None] + vx + vx @ vx / (1.0 + z[:, 2])[:, None, None]
    return turn


def ray_turn(
    points: np.ndarray, visible: np.ndarray, focal: np.ndarray, centre: np.ndarray
) -> npt.NDArray[np.float64]:
    """ray_rotation in float64 (training's Protocol I with intrinsics)."""
    w = visible.astype(np.float64)[..., None]
    centroid = (points.astype(np.float64) * w).sum(axis=1) / np.maximum(w.sum(axis=1), 1.0)  # (N, 2)
    ray = np.concatenate([(centroid - centre) / focal, np.ones((len(points), 1))], axis=1)
    return rotation_to_ray(ray)


def ray_rotation(
    points: np.ndarray, visible: np.ndarray, focal: np.ndarray, centre: np.ndarray
) -> FloatArray:
    """(N, 3, 3) smallest rotations taking the optical axis onto the ray through the centroid of
    each pose's visible (N, J, 2) pixel points, for pinhole focal lengths and principal points
    (N, 2) px.

    K sees the person along that ray (the normalised input has lost where in the image they
    stood), so ray_rotation @ camera_rotation(K) is the pose's orientation in the camera frame
    (Rodrigues' formula for the turn from (0, 0, 1) to the unit ray z: I + [v]x + [v]x^2 / (1 + z3)
    with v = (0, 0, 1) x z).
    """
    return np.asarray(ray_turn(points, visible, focal, centre), dtype=np.float32)


def rotate_to_camera(pose_3d: np.ndarray, rotation: np.ndarray) -> FloatArray:
    """pose_3d (N, J, 3) in the template frame -> (N, J, 3) in the camera's orientation (X R^T)."""
    return np.asarray(pose_3d.astype(np.float64) @ rotation.transpose(0, 2, 1), dtype=np.float32)


def visible_stats(points: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (N, 2) and standard deviation (N,) of (N, J, 2) points over their visible joints.

    The deviation is taken over all coordinates of the visible joints together, as the model's
    input normalisation does: the one spread formula of the service (input rules, the start-up
    check, the reprojection and the format mix-up score all use it).
    """
    w = visible[..., None].astype(np.float64)  # (N, J, 1)
    count = np.maximum(w.sum(axis=(1, 2)), 1.0)  # (N,)
    safe = np.where(w > 0, points.astype(np.float64), 0.0)  # missing joints may hold NaN
    mean = safe.sum(axis=1) / count[:, None]  # (N, 2)
    centred = (safe - mean[:, None]) * w
    std = np.sqrt((centred**2).sum(axis=(1, 2)) / (2 * count))  # (N,)
    return mean, std


def visible_spread(points: np.ndarray, visible: np.ndarray) -> npt.NDArray[np.float64]:
    """(N,) the standard deviation of (N, J, 2) points over their visible joints, as the model's
    input normalisation takes it: the size of a pose in pixels."""
    return visible_stats(points, visible)[1]


def reproject(
    camera: np.ndarray,
    pose_3d: np.ndarray,
    keypoints_2d: np.ndarray,
    visible: np.ndarray,
    input_stats: tuple[np.ndarray, np.ndarray] | None = None,
) -> FloatArray:
    """Project pose_3d (N, J, 3) with K (N, 2, 3) back into the input's pixels; returns (N, J, 2).

    K X matches the normalised input up to a translation, so it is centred on its visible joints,
    scaled by the input's standard deviation and moved to the input's visible mean (`input_stats`:
    visible_stats of the input, when the caller has them).
    """
    projected = pose_3d.astype(np.float64) @ camera.astype(np.float64).transpose(0, 2, 1)  # (N, J, 2)
    proj_mean, _ = visible_stats(projected, visible)
    in_mean, in_std = visible_stats(keypoints_2d, visible) if input_stats is None else input_stats
    pixels = (projected - proj_mean[:, None]) * in_std[:, None, None] + in_mean[:, None]
    return np.asarray(pixels, dtype=np.float32)


def reprojection_error(reprojection: np.ndarray, keypoints_2d: np.ndarray, visible: np.ndarray) -> FloatArray:
    """Mean pixel distance (N,) between (N, J, 2) reprojection and input over the visible joints."""
    w = visible.astype(np.float64)  # (N, J)
    safe = np.where(w[..., None] > 0, keypoints_2d.astype(np.float64), 0.0)
    dist = np.linalg.norm(reprojection.astype(np.float64) - safe, axis=-1) * w  # (N, J)
    return np.asarray(dist.sum(axis=1) / np.maximum(w.sum(axis=1), 1.0), dtype=np.float32)


# The skeleton height of an h36m17 pose (the model's joints): the bone chain head - neck - thorax -
# spine - pelvis plus the mean of the two legs' thigh + shin. It does not change with the pose, so it
# is one definition for a person's given height, the model's answers and Human3.6M's ground truth
# (about stature minus the height of the ankle above the ground).
HEIGHT_CHAIN: tuple[tuple[int, int], ...] = ((10, 9), (9, 8), (8, 7), (7, 0))
HEIGHT_LEGS: tuple[tuple[int, int], ...] = ((1, 2), (2, 3), (4, 5), (5, 6))


# The skeleton heights a person_height_m may give (skeleton_height: a child to a giant).
MIN_HEIGHT_M, MAX_HEIGHT_M = 0.5, 2.5


def height_problem(height: float) -> str | None:
    """Why a person_height_m (metres) cannot be used, or None when it can."""
    if MIN_HEIGHT_M <= height <= MAX_HEIGHT_M:  # NaN fails too
        return None
    hint = " (millimetres? divide by 1000)" if height > 100 * MIN_HEIGHT_M else ""
    return f"expected metres in [{MIN_HEIGHT_M}, {MAX_HEIGHT_M}], got {height:g}{hint}"


def skeleton_height(pose_3d: np.ndarray) -> npt.NDArray[np.float64]:
    """(N,) the skeleton height (HEIGHT_CHAIN, HEIGHT_LEGS) of (N, 17, 3) h36m17 poses, in their unit."""
    p = pose_3d.astype(np.float64)

    def length(bones: tuple[tuple[int, int], ...]) -> npt.NDArray[np.float64]:
        return sum((np.linalg.norm(p[:, a] - p[:, b], axis=-1) for a, b in bones), np.zeros(len(p)))

    return length(HEIGHT_CHAIN) + 0.5 * length(HEIGHT_LEGS)


def root_translation(
    points: np.ndarray, visible: np.ndarray, pose_camera: np.ndarray, intrinsics: np.ndarray, rounds: int = 3
) -> npt.NDArray[np.float64]:
    """(N, 3) camera-frame position of the root (the pose's origin) that best reprojects a
    root-relative (N, J, 3) pose in the camera's orientation, of the person's true size, through
    pinhole cameras (N, 4) fx, fy, cx, cy onto its visible (N, J, 2) pixel points.

    Each visible joint j gives two equations linear in the root T (the pinhole model with the
    denominators cleared): fx (Tx + Xj) = (uj - cx)(Tz + Zj) and fy (Ty + Yj) = (vj - cy)(Tz + Zj),
    solved by least squares, then `rounds` times again with each joint weighted by 1 / max(its
    reprojection error, ROBUST_FLOOR_PX) (iteratively reweighted least squares: a joint the answer
    got wrong pulls less). The pose's size sets the depth, as the weak-perspective scale does, but
    the full perspective also places the root itself: on Human3.6M's validation poses with the true
    height 144 mm of error, 151 mm without the reweighting, 218 mm for depth = f size / (scale x
    spread) (bench.root_trajectory --split validation). NaN rows where fewer than two joints are
    visible or the system is singular.
    """
    k = intrinsics.astype(np.float64)
    pose = pose_camera.astype(np.float64)
    visible_w = visible.astype(np.float64)  # (N, J)
    root = _weighted_root(points, visible_w, pose, k)
    for _ in range(rounds):
        with np.errstate(divide="ignore", invalid="ignore"):
            placed = pose + root[:, None]  # (N, J, 3)
            pixels = placed[..., :2] / placed[..., 2:] * k[:, None, :2] + k[:, None, 2:]
            error = np.linalg.norm(pixels - np.where(visible_w[..., None] > 0, points, 0.0), axis=-1)
        weights = visible_w * ROBUST_FLOOR_PX / np.maximum(np.nan_to_num(error, nan=np.inf), ROBUST_FLOOR_PX)
        again = _weighted_root(points, weights, pose, k)
        root = np.where(np.isfinite(again), again, root)
    root[visible_w.sum(axis=1) < 2] = np.nan
    return root


ROBUST_FLOOR_PX = 10.0  # joints reprojected within this many pixels weigh fully


def _weighted_root(
    points: np.ndarray,
    weights: npt.NDArray[np.float64],
    pose: npt.NDArray[np.float64],
    k: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """(N, 3) the weighted least-squares root of root_translation's equations; NaN where singular."""
    fx, fy, cx, cy = (k[:, i : i + 1] for i in range(4))  # (N, 1)
    w = weights
    u = np.where(w > 0, points[..., 0].astype(np.float64), 0.0) - cx  # (N, J)
    v = np.where(w > 0, points[..., 1].astype(np.float64), 0.0) - cy
    x, y, z = pose[..., 0], pose[..., 1], pose[..., 2]
    n, j = w.shape
    a = np.zeros((n, 2 * j, 3))
    a[:, :j, 0], a[:, :j, 2] = fx * w, -u * w
    a[:, j:, 1], a[:, j:, 2] = fy * w, -v * w
    b = np.concatenate([(u * z - fx * x) * w, (v * z - fy * y) * w], axis=1)  # (N, 2J)
    normal = a.transpose(0, 2, 1) @ a  # (N, 3, 3)
    rhs = a.transpose(0, 2, 1) @ b[..., None]  # (N, 3, 1)
    scale = np.maximum(np.abs(normal).max(axis=(1, 2)), 1e-300)
    solvable = np.abs(np.linalg.det(normal / scale[:, None, None])) > 1e-12
    root = np.full((n, 3), np.nan)
    if solvable.any():
        root[solvable] = np.linalg.solve(normal[solvable], rhs[solvable])[..., 0]
    return root
