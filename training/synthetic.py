"""Synthetic warm start: unpaired training 3D poses seen through random perspective cameras.

The cameras are drawn here, not taken from Human3.6M, so no image's 2D is ever paired with its
own 3D pose: the generator learns what a body looks like from many views before the
adversarial phase adapts it to real 2D inputs. Training images of Human3.6M are 1000 px wide,
filmed from 4-6 m at about the height of the subject's chest; the ranges below cover that and
more.
"""

from __future__ import annotations

import math

import torch

from repnet.core import geometry, skeleton

FOCAL_PX = 1150.0
CENTRE_PX = 500.0
AZIMUTH_DEG = (-180.0, 180.0)  # turn of the body about the vertical
ELEVATION_DEG = (-10.0, 30.0)  # camera looking down (positive) or up at the pelvis
ROLL_STD_DEG = 3.0
DISTANCE_M = (3.5, 6.5)  # pelvis to camera, along the optical axis
OFFSET_M = (1.0, 0.5)  # largest sideways and vertical offset of the pelvis from the axis


def _uniform(low: float, high: float, n: int, gen: torch.Generator) -> torch.Tensor:
    return low + (high - low) * torch.rand(n, generator=gen, dtype=torch.float64)


def _rotation(axis: int, angle: torch.Tensor) -> torch.Tensor:
    """(N,) angles in radians -> (N, 3, 3) rotations about coordinate axis 0, 1 or 2."""
    c, s = torch.cos(angle), torch.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    rot = torch.zeros(angle.shape[0], 3, 3, dtype=angle.dtype)
    rot[:, axis, axis] = 1.0
    rot[:, i, i], rot[:, i, j], rot[:, j, i], rot[:, j, j] = c, -s, s, c
    return rot


def random_views(
    n: int, gen: torch.Generator, elevation_deg: tuple[float, float] = ELEVATION_DEG
) -> tuple[torch.Tensor, torch.Tensor]:
    """n random world-to-camera rotations (N, 3, 3) and pelvis positions (N, 3) in metres, the
    cameras looking down by U(elevation_deg) degrees.

    The camera frame is x right, y down, z forward (as Human3.6M's); the world is Z up.
    """
    deg = math.pi / 180.0
    azimuth = _uniform(*AZIMUTH_DEG, n, gen) * deg
    elevation = _uniform(*elevation_deg, n, gen) * deg
    roll = torch.randn(n, generator=gen, dtype=torch.float64) * ROLL_STD_DEG * deg
    # Level camera looking along world +Y: camera x = X, y = -Z, z = Y.
    level = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    rot = _rotation(2, roll) @ _rotation(0, elevation) @ level @ _rotation(2, azimuth)
    distance = _uniform(*DISTANCE_M, n, gen)
    offset_x = _uniform(-OFFSET_M[0], OFFSET_M[0], n, gen)
    offset_y = _uniform(-OFFSET_M[1], OFFSET_M[1], n, gen)
    return rot, torch.stack([offset_x, offset_y, distance], dim=1)


def to_camera(poses_world_mm: torch.Tensor, rot: torch.Tensor, position_m: torch.Tensor) -> torch.Tensor:
    """(N, J, 3) world poses (mm, pelvis at origin) -> the same in each camera's frame (metres, float64)."""
    return poses_world_mm.to(torch.float64) / 1000.0 @ rot.transpose(1, 2) + position_m[:, None]


def project(poses_world_mm: torch.Tensor, rot: torch.Tensor, position_m: torch.Tensor) -> torch.Tensor:
    """(N, J, 3) world poses (mm, pelvis at origin) -> (N, J, 2) pixels of a pinhole camera."""
    x_cam = to_camera(poses_world_mm, rot, position_m)
    return (FOCAL_PX * x_cam[..., :2] / x_cam[..., 2:3] + CENTRE_PX).to(torch.float32)


def _joint(name: str) -> int:
    return skeleton.JOINT_NAMES.index(name)


# Limb segments a synthetic pose may turn: (pivot joint, the joints that turn with it about it),
# forearms and shins before the upper arms and thighs. The hips and shoulders never move, so the
# pose's alignment to the template (on those four joints) is unchanged by a turn.
LIMB_SEGMENTS: tuple[tuple[int, tuple[int, ...]], ...] = tuple(
    (_joint(f"{side}_{pivot}"), tuple(_joint(f"{side}_{j}") for j in moved))
    for pivot, moved in (
        ("knee", ("ankle",)),
        ("elbow", ("wrist",)),
        ("hip", ("knee", "ankle")),
        ("shoulder", ("elbow", "wrist")),
    )
    for side in ("left", "right")
)


def random_turns(shape: tuple[int, ...], sigma_deg: float, gen: torch.Generator) -> torch.Tensor:
    """(*shape, 3, 3) float64 rotations about uniformly random axes by N(0, sigma_deg) angles."""
    axis = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    angle = torch.randn(*shape, generator=gen, dtype=torch.float64) * math.radians(sigma_deg)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*shape, 3, 3)
    sin, cos = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=torch.float64) + sin * cross + (1.0 - cos) * cross @ cross


def turn_limbs(poses: torch.Tensor, turns: torch.Tensor) -> torch.Tensor:
    """(N, J, 3) poses with each LIMB_SEGMENTS segment turned about its pivot joint by the
    (N, len(LIMB_SEGMENTS), 3, 3) rotations `turns`: new poses from the same people, every bone
    keeping its length."""
    out = poses.to(torch.float64).clone()
    for segment, (pivot, moved) in enumerate(LIMB_SEGMENTS):
        centre = out[:, pivot : pivot + 1]
        out[:, list(moved)] = centre + (out[:, list(moved)] - centre) @ turns[:, segment].transpose(1, 2)
    return out.to(poses.dtype)


def mirror(poses: torch.Tensor) -> torch.Tensor:
    """(N, J, 3) poses -> their mirror images: x negated, left and right joints swapped.

    A mirrored body is a body (its bones keep their lengths); for template-aligned poses it is
    also exactly the alignment of the mirrored world pose, as the template torso is symmetric in x.
    """
    out = poses[:, list(skeleton.MIRROR)].clone()
    out[..., 0] = -out[..., 0]
    return out


def sample(
    poses_world_mm: torch.Tensor,
    poses_aligned_m: torch.Tensor,
    batch: int,
    noise_px: float,
    gen: torch.Generator,
    align_rotations: torch.Tensor | None = None,
    rotation_target: str | None = "axis",
    mirror_prob: float = 0.0,
    noise_power: float = 1.0,
    limb_turn_deg: float = 0.0,
    limb_turn_prob: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """A synthetic batch of N = `batch` poses: (N, J, 2) pixels with detector-like noise, the
    (N, J, 3) target (the same pose aligned to the template, metres: what the generator outputs)
    and, given the
    (M, 3, 3) rotations that aligned each world pose to the template, the (N, 3, 3) rotation
    from the template frame into the synthetic camera (what the camera K should hold).

    rotation_target "axis": into the camera frame itself; "ray": into the frame that looks along
    the ray from the camera to the pelvis, the one view a centred input can show (the camera
    frame is this turned by metrics.rotation_to_ray of the pelvis' direction); None: no rotation
    (align_rotations then serve the limb turns alone).

    mirror_prob -- the share of poses mirrored (mirror) before they are seen: the training
    subjects' poses are not left-right balanced (a phone in the right hand), and a lifter that
    learns them as they are lifts their mirror images worse.

    noise_px, noise_power -- each pose's pixels get N(0, sigma) noise, sigma = noise_px * u **
    noise_power with u ~ U(0, 1): E[sigma^2] = noise_px^2 / (2 noise_power + 1).

    limb_turn_deg, limb_turn_prob -- in that share of the poses, every forearm, upper arm, shin
    and thigh turns about its joint by N(0, limb_turn_deg) degrees about a random axis (turn_limbs),
    in the world pose and its aligned target alike: poses near the training poses that the
    training subjects never held. Needs align_rotations (the turn is drawn in the template frame)."""
    idx = torch.randint(0, poses_world_mm.shape[0], (batch,), generator=gen)
    rot, position = random_views(batch, gen)
    world, aligned = poses_world_mm[idx], poses_aligned_m[idx]
    if limb_turn_deg > 0:
        if align_rotations is None:
            raise ValueError("limb turns need the rotations that aligned the world poses (align_rotations)")
        turns = random_turns((batch, len(LIMB_SEGMENTS)), limb_turn_deg, gen)
        chosen = torch.rand(batch, generator=gen) < limb_turn_prob
        turns = torch.where(chosen[:, None, None, None], turns, torch.eye(3, dtype=turns.dtype))
        # aligned = s * world @ A^T: a turn R in the template frame is A^T R A in the world frame.
        align = align_rotations[idx].to(torch.float64)[:, None]  # (N, 1, 3, 3)
        world = turn_limbs(world, align.transpose(-1, -2) @ turns @ align)
        aligned = turn_limbs(aligned, turns.to(aligned.device))
    flip = None
    if mirror_prob > 0:
        flip = torch.rand(batch, generator=gen) < mirror_prob
        world = torch.where(flip[:, None, None], mirror(world), world)
        aligned = torch.where(flip.to(aligned.device)[:, None, None], mirror(aligned), aligned)
    pixels = project(world, rot, position)
    if noise_px > 0:
        sigma = noise_px * torch.rand(batch, 1, 1, generator=gen) ** noise_power
        pixels = pixels + sigma * torch.randn(pixels.shape, generator=gen)
    # aligned = s * world @ A^T, camera = world @ V^T, so camera = aligned @ (V A^T)^T / s.
    to_camera = None
    if align_rotations is not None and rotation_target is not None:
        template_to_world = align_rotations[idx].to(torch.float64).transpose(1, 2)
        if flip is not None:
            # Both poses mirrored in x: the aligning rotation becomes D A D, D = diag(-1, 1, 1).
            sign = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
            turned = sign[:, None] * template_to_world * sign
            template_to_world = torch.where(flip[:, None, None], turned, template_to_world)
        to_camera = rot @ template_to_world
        if rotation_target == "ray":
            ray = torch.from_numpy(geometry.rotation_to_ray(position.numpy()))
            to_camera = ray.transpose(1, 2) @ to_camera
        elif rotation_target != "axis":
            raise ValueError(f"rotation target must be axis or ray, got {rotation_target!r}")
        to_camera = to_camera.to(torch.float32)
    return pixels, aligned, to_camera
