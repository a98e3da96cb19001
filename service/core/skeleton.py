"""Human3.6M 17-joint skeleton: joint names, parents, bones and the KCS bone matrix."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "right_hip",
    "right_knee",
    "right_ankle",
    "left_hip",
    "left_knee",
    "left_ankle",
    "spine",
    "thorax",
    "neck",
    "head",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
)
NUM_JOINTS = len(JOINT_NAMES)
PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)
ROOT = 0
SPINE = 7

# Joints that fix the body frame: the Procrustes fit onto the template uses them.
RIGHT_HIP, LEFT_HIP, LEFT_SHOULDER, RIGHT_SHOULDER = 1, 4, 11, 14
TORSO_JOINTS: tuple[int, ...] = (RIGHT_HIP, LEFT_HIP, LEFT_SHOULDER, RIGHT_SHOULDER)

# Per-joint weights of the L1 reprojection (the authors' code): the pelvis 0, the neck and head
# 0.1 (detectors place them least consistently), every other joint 1.
REPROJECTION_WEIGHTS: tuple[float, ...] = tuple(
    0.0 if j == ROOT else 0.1 if name in ("neck", "head") else 1.0 for j, name in enumerate(JOINT_NAMES)
)


def _mirror_name(name: str) -> str:
    side, _, part = name.partition("_")
    other = {"left": "right", "right": "left"}.get(side)
    return f"{other}_{part}" if other else name


# The joint in each slot of a mirrored pose: left and right swapped, the midline kept.
MIRROR: tuple[int, ...] = tuple(JOINT_NAMES.index(_mirror_name(name)) for name in JOINT_NAMES)

# One bone per non-root joint, from its parent to itself.
BONES: tuple[tuple[int, int], ...] = tuple((p, j) for j, p in enumerate(PARENTS) if p >= 0)
NUM_BONES = len(BONES)

# Left/right bone pairs of the symmetry error (Wandt & Rosenhahn 2019, Sec. 4.3): upper/lower arm and leg.
SYMMETRIC_BONES: tuple[tuple[tuple[int, int], tuple[int, int]], ...] = (
    ((4, 5), (1, 2)),  # thigh
    ((5, 6), (2, 3)),  # shin
    ((11, 12), (14, 15)),  # upper arm
    ((12, 13), (15, 16)),  # forearm
)

# Template torso in the template frame (mm). The frame is that of a camera looking at the
# subject from the front: x to the image's right, y down, z away from the camera; the
# subject faces the camera, so its right side lies at negative x. The sizes are the
# averages over the Human3.6M training subjects; pelvis at the origin.
TEMPLATE_TORSO = np.array(
    [
        [-134.5, 0.0, 0.0],  # right hip
        [134.5, 0.0, 0.0],  # left hip
        [137.0, -431.0, 0.0],  # left shoulder
        [-137.0, -431.0, 0.0],  # right shoulder
    ],
    dtype=np.float64,
)


def bone_matrix() -> np.ndarray:
    """The KCS bone matrix C (J, B): B = X C gives the bone vectors of a pose X (3, J)
    (Wandt & Rosenhahn 2019, Eq. 5-6).

    Column c of a bone has +1 at its child joint and -1 at its parent (Eq. 4), so that X c is the
    bone vector b = child - parent (Eq. 3).
    """
    c = np.zeros((NUM_JOINTS, NUM_BONES), dtype=np.float32)
    for b, (parent, child) in enumerate(BONES):
        c[child, b] = 1.0
        c[parent, b] = -1.0
    return c


_PARENTS, _CHILDREN = (np.array(ends) for ends in zip(*BONES, strict=True))


def _bone_paths() -> npt.NDArray[np.float64]:
    """(J, B): 1 where bone b lies on the path from the root to joint j."""
    paths = np.zeros((NUM_JOINTS, NUM_BONES))
    for b, (parent, child) in enumerate(BONES):  # parents come before children
        paths[child] = paths[parent]
        paths[child, b] = 1.0
    return paths


BONE_PATHS = _bone_paths()


def bone_lengths(poses: np.ndarray) -> np.ndarray:
    """(N, B) length of each bone (parent to joint) of (N, J, 3) poses."""
    return np.asarray(np.linalg.norm(poses[:, _CHILDREN] - poses[:, _PARENTS], axis=-1))


def fix_bone_lengths(poses: np.ndarray, lengths: np.ndarray) -> npt.NDArray[np.float32]:
    """(N, J, 3) poses with each bone scaled to (N, B) `lengths` along its own direction, from the
    root outwards (a joint moves with its parent): one person's bones keep one length per track.
    Each joint is the root plus the scaled bones on its path (BONE_PATHS), for all poses at once."""
    poses = np.asarray(poses, np.float64)
    bones = poses[:, _CHILDREN] - poses[:, _PARENTS]  # (N, B, 3)
    norm = np.linalg.norm(bones, axis=-1, keepdims=True)
    scaled = bones / np.maximum(norm, 1e-6) * np.asarray(lengths, np.float64)[..., None]
    fixed: npt.NDArray[np.float32] = (poses[:, :1] + np.einsum("jb,nbd->njd", BONE_PATHS, scaled)).astype(
        np.float32
    )
    return fixed
