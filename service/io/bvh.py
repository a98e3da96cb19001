"""BVH motion of one person's lifted poses: a fixed skeleton, joint rotations solved from the 3D
positions, the root trajectory; and the parser and forward kinematics that read it back."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from repnet.core.formats import MODEL_JOINTS, MODEL_PARENTS

F64 = npt.NDArray[np.float64]
# Camera frame (x right, y down, z forward) -> BVH's Y-up frame (x right, y up, z towards the viewer):
# a rotation by 180 degrees about x, so handedness is kept.
CAMERA_TO_BVH = np.diag([1.0, -1.0, -1.0])
ROTATION_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")  # local rotation Rz @ Rx @ Ry
END_SITE_SHARE = 0.2  # an End Site continues its joint's bone by this share of the bone's length


@dataclass(frozen=True)
class Motion:
    """A BVH skeleton and its frames: what write_bvh writes and parse_bvh reads."""

    names: tuple[str, ...]  # J joints, parents before children
    parents: tuple[int, ...]  # (J,) index of each joint's parent, -1 for the root
    offsets: F64  # (J, 3) each joint's offset from its parent at rest, metres (BVH axes)
    root_position: F64  # (T, 3) the root's position per frame, metres (BVH axes)
    rotations: F64  # (T, J, 3) each joint's local rotation: Z, X, Y angles in degrees
    frame_time: float  # seconds


def _children(parents: tuple[int, ...]) -> list[list[int]]:
    kids: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[p].append(j)
    return kids


def _turn(a: F64, b: F64) -> F64:
    """(3, 3) the smallest rotation taking direction a onto direction b (Rodrigues)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, cos = np.cross(a, b), float(np.dot(a, b))
    if cos < -1 + 1e-12:  # opposite: half a turn about any axis normal to a
        normal = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        normal /= np.linalg.norm(normal)
        return np.asarray(2 * np.outer(normal, normal) - np.eye(3))
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.asarray(np.eye(3) + skew + skew @ skew / (1 + cos))


def _fit(rest: F64, target: F64) -> F64:
    """(3, 3) the rotation taking the (k, 3) rest directions closest onto the target directions (Kabsch)."""
    u, _, vt = np.linalg.svd(target.T @ rest)
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return np.asarray(u @ fix @ vt)


def to_euler(r: F64) -> F64:
    """(3,) Z, X, Y degrees of a rotation r = Rz @ Rx @ Ry."""
    x = np.arcsin(np.clip(r[2, 1], -1.0, 1.0))
    return np.degrees([np.arctan2(-r[0, 1], r[1, 1]), x, np.arctan2(-r[2, 0], r[2, 2])])


def from_euler(zxy: F64) -> F64:
    """(..., 3, 3) Rz @ Rx @ Ry of (..., 3) Z, X, Y degrees."""
    z, x, y = np.moveaxis(np.radians(zxy), -1, 0)
    one, zero = np.ones_like(z), np.zeros_like(z)
    rz = np.stack([np.cos(z), -np.sin(z), zero, np.sin(z), np.cos(z), zero, zero, zero, one], -1)
    rx = np.stack([one, zero, zero, zero, np.cos(x), -np.sin(x), zero, np.sin(x), np.cos(x)], -1)
    ry = np.stack([np.cos(y), zero, np.sin(y), zero, one, zero, -np.sin(y), zero, np.cos(y)], -1)
    shape = (*z.shape, 3, 3)
    return np.asarray(rz.reshape(shape) @ rx.reshape(shape) @ ry.reshape(shape))


def solve_motion(positions: F64, frame_time: float) -> Motion:
    """The motion of (T, 17, 3) h36m17 joint positions in metres, BVH axes.

    Each bone gets the median of its lengths over the frames; the rest pose is the first frame with
    those lengths. Per frame, a joint's rotation takes its children's rest offsets onto their
    directions in the frame (the best rotation where it has several, exact for a rigid body), and
    a joint with one child turns by the smallest rotation from where its parent's rotation points it.
    """
    parents, kids = MODEL_PARENTS, _children(MODEL_PARENTS)
    lengths = np.zeros(len(parents))
    offsets = np.zeros((len(parents), 3))
    for j, p in enumerate(parents):
        if p >= 0:
            lengths[j] = np.median(np.linalg.norm(positions[:, j] - positions[:, p], axis=-1))
            bone = positions[0, j] - positions[0, p]
            offsets[j] = lengths[j] * bone / max(float(np.linalg.norm(bone)), 1e-12)
    rotations = np.zeros((len(positions), len(parents), 3))
    for t, frame in enumerate(positions):
        world = np.tile(np.eye(3), (len(parents), 1, 1))  # each joint's rotation in the world
        for j, p in enumerate(parents):
            base = world[p] if p >= 0 else np.eye(3)
            below = kids[j]
            if len(below) > 1:
                world[j] = _fit(offsets[below], frame[below] - frame[j])
            elif below:
                (c,) = below
                world[j] = _turn(base @ offsets[c], frame[c] - frame[j]) @ base
            else:
                world[j] = base
            rotations[t, j] = to_euler(base.T @ world[j])
    return Motion(MODEL_JOINTS, parents, offsets, positions[:, 0].copy(), rotations, frame_time)


def forward_kinematics(motion: Motion) -> F64:
    """(T, J, 3) joint positions of a motion, metres (BVH axes)."""
    local = from_euler(motion.rotations)  # (T, J, 3, 3)
    world = np.zeros_like(local)
    out = np.zeros((len(local), len(motion.names), 3))
    for j, p in enumerate(motion.parents):
        if p < 0:
            world[:, j], out[:, j] = local[:, j], motion.root_position
        else:
            world[:, j] = world[:, p] @ local[:, j]
            out[:, j] = out[:, p] + world[:, p] @ motion.offsets[j]
    return out


def write_bvh(motion: Motion) -> str:
    """The motion as BVH text: HIERARCHY (ROOT with position and rotation channels, JOINTs with
    rotation channels, an End Site after each leaf) and MOTION, one line per frame."""
    kids = _children(motion.parents)
    lines = ["HIERARCHY"]
    rotation = " ".join(ROTATION_CHANNELS)

    def joint(j: int, depth: int) -> None:
        pad = "  " * depth
        root = motion.parents[j] < 0
        lines.append(f"{pad}{'ROOT' if root else 'JOINT'} {motion.names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(f'{v:.6f}' for v in motion.offsets[j])}")
        channels = f"6 Xposition Yposition Zposition {rotation}" if root else f"3 {rotation}"
        lines.append(f"{pad}  CHANNELS {channels}")
        for c in kids[j]:
            joint(c, depth + 1)
        if not kids[j]:
            tip = END_SITE_SHARE * motion.offsets[j]
            end = " ".join(f"{v:.6f}" for v in tip)
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {end}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    joint(motion.parents.index(-1), 0)
    lines += ["MOTION", f"Frames: {len(motion.rotations)}", f"Frame Time: {motion.frame_time:.6f}"]
    order = _depth_first(motion.parents)
    for position, angles in zip(motion.root_position, motion.rotations, strict=True):
        values = [*position, *angles[order].ravel()]
        lines.append(" ".join(f"{v:.6f}" for v in values))
    return "\n".join(lines) + "\n"


def _depth_first(parents: tuple[int, ...]) -> list[int]:
    """The joints in the order a BVH hierarchy lists them (depth first, children in index order)."""
    kids, order = _children(parents), []
    stack = [parents.index(-1)]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(kids[j]))
    return order


def parse_bvh(text: str) -> Motion:
    """A Motion from BVH text with one ROOT (position channels then Z X Y rotations) and JOINTs of Z X
    Y rotations, in the order the file lists them; ValueError on anything else."""
    tokens = re.findall(r"[^\s{}]+|[{}]", text)
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    stack: list[int] = []
    i, end_site = 0, False
    while tokens[i] != "MOTION":
        word = tokens[i]
        if word in ("ROOT", "JOINT"):
            names.append(tokens[i + 1])
            parents.append(stack[-1] if stack else -1)
            i += 2
        elif word == "End":  # End Site: its offset is not a joint
            end_site, i = True, i + 2
        elif word == "{":
            stack.append(-2 if end_site else len(names) - 1)
            i += 1
        elif word == "}":
            end_site = False
            stack.pop()
            i += 1
        elif word == "OFFSET":
            if stack[-1] != -2:
                offsets.append([float(v) for v in tokens[i + 1 : i + 4]])
            i += 4
        elif word == "CHANNELS":
            count = int(tokens[i + 1])
            channels = tokens[i + 2 : i + 2 + count]
            if tuple(channels[-3:]) != ROTATION_CHANNELS:
                raise ValueError(
                    f"joint {names[-1]}: expected channels ending {ROTATION_CHANNELS}, got {channels}"
                )
            i += 2 + count
        else:
            i += 1
    frames, frame_time = int(tokens[i + 2]), float(tokens[i + 5])
    values = np.array(tokens[i + 6 :], dtype=np.float64).reshape(frames, 3 + 3 * len(names))
    return Motion(
        tuple(names),
        tuple(parents),
        np.array(offsets),
        values[:, :3],
        values[:, 3:].reshape(frames, len(names), 3),
        frame_time,
    )
