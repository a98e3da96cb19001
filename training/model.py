"""RepNet generator (pose and camera branches), critic with KCS path, and the exported graph."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from repnet.core import skeleton
from repnet.train.camera import masked_centre
from repnet.train.config import RepNetConfig
from repnet.train.losses import bone_lengths

# The generator works in metres so its outputs are O(1); the exported graph speaks mm.
MM_PER_UNIT = 1000.0


def normalize_keypoints(points: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """Centre (N, J, 2) pixel points on their visible joints and divide by their std.

    visible -- (N, J) in {0, 1}. Hidden joints come out as exactly 0, whatever their input
    values (NaN included), so they cannot influence anything downstream.
    """
    mask = visible.unsqueeze(-1) > 0.5  # (N, J, 1)
    points = torch.where(mask, points, torch.zeros_like(points))
    centred = masked_centre(points, visible)  # (N, J, 2)
    count = visible.sum(dim=1).clamp_min(1.0)  # (N,)
    std = torch.sqrt(centred.pow(2).sum(dim=(1, 2)) / (2 * count))  # (N,)
    return centred / std.clamp_min(1e-6)[:, None, None]


class ResidualBlock(nn.Module):
    """Two fully connected layers with leaky ReLU and an identity skip (Fig. 2)."""

    def __init__(self, width: int, slope: float) -> None:
        """Two width x width layers; slope: of the leaky ReLU."""
        super().__init__()
        self.fc1 = nn.Linear(width, width)
        self.fc2 = nn.Linear(width, width)
        self.act = nn.LeakyReLU(slope)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, width) -> (N, width)."""
        return x + self.act(self.fc2(self.act(self.fc1(x))))


def _branch(in_dim: int, out_dim: int, width: int, blocks: int, slope: float) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Linear(in_dim, width), nn.LeakyReLU(slope)]
    layers += [ResidualBlock(width, slope) for _ in range(blocks)]
    layers.append(nn.Linear(width, out_dim))
    return nn.Sequential(*layers)


class RepNet(nn.Module):
    """Generator: normalised 2D pose -> 3D pose (metres, pelvis at origin) and camera K."""

    def __init__(self, config: RepNetConfig) -> None:
        """The pose and camera branches (and a shared trunk) of config's shape."""
        super().__init__()
        self.config = config
        j = config.num_joints
        in_dim = 3 * j if config.visibility_input else 2 * j
        w, blocks, slope = config.width, config.num_blocks, config.leaky_slope
        self.trunk: nn.Module = nn.Identity()
        if config.shared_trunk:
            self.trunk = nn.Sequential(nn.Linear(in_dim, w), nn.LeakyReLU(slope), ResidualBlock(w, slope))
            pose_layers: list[nn.Module] = [ResidualBlock(w, slope) for _ in range(blocks)]
            pose_layers += [nn.Linear(w, w), nn.LeakyReLU(slope), nn.Linear(w, 3 * j)]
            self.pose_branch = nn.Sequential(*pose_layers)
            camera_layers: list[nn.Module] = [ResidualBlock(w, slope) for _ in range(blocks)]
            self.camera_branch = nn.Sequential(*camera_layers, nn.Linear(w, 6))
        else:
            self.pose_branch = _branch(in_dim, 3 * j, w, blocks, slope)
            self.camera_branch = _branch(in_dim, 6, w, blocks, slope)

    def forward(self, points: torch.Tensor, visible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """points -- (N, J, 2) normalised (normalize_keypoints), visible -- (N, J).

        Returns pose (N, J, 3) in metres with the pelvis at the origin, and camera (N, 2, 3)
        mapping it onto the normalised input up to a translation.
        """
        n, j = visible.shape
        x = points.reshape(n, 2 * j)
        if self.config.visibility_input:
            x = torch.cat([x, visible], dim=1)  # (N, 3J)
        x = self.trunk(x)
        pose = self.pose_branch(x).reshape(n, j, 3)
        pose = pose - pose[:, skeleton.ROOT : skeleton.ROOT + 1]
        camera = self.camera_branch(x).reshape(n, 2, 3)
        return pose, camera


class KCS(nn.Module):
    """Kinematic chain space layer: Psi = B^T B (Wandt & Rosenhahn 2019, Eq. 7) of the bone
    vectors B = X C (Eq. 5-6), C the bone matrix (skeleton.bone_matrix)."""

    bones: torch.Tensor  # buffer: (J, B) C

    def __init__(self) -> None:
        """The skeleton's bone matrix as a buffer."""
        super().__init__()
        self.register_buffer("bones", torch.from_numpy(skeleton.bone_matrix()))

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        """(N, J, 3) pose -> (N, B, B) Psi; its diagonal holds the squared bone lengths."""
        bones = torch.einsum("njd,jb->nbd", pose, self.bones)  # (N, B, 3): B = X C, one row per bone
        return bones @ bones.transpose(1, 2)


class Critic(nn.Module):
    """WGAN critic: a fully connected pose path and a KCS path merged before the output."""

    def __init__(self, config: RepNetConfig) -> None:
        """Paths of config's critic_width and kcs_width."""
        super().__init__()
        j, w, kcs, slope = config.num_joints, config.critic_width, config.kcs_width, config.leaky_slope
        act = nn.LeakyReLU(slope)
        self.pose_path = nn.Sequential(
            nn.Linear(3 * j, w), act, ResidualBlock(w, slope), nn.Linear(w, 100), act
        )
        self.kcs = KCS()
        nb = skeleton.NUM_BONES
        # Dense kcs_width, then twice more with a skip from the first (the authors' code).
        self.kcs_path = nn.Sequential(nn.Linear(nb * nb, kcs), act, ResidualBlock(kcs, slope))
        self.head = nn.Sequential(nn.Linear(100 + kcs, 100), act, nn.Linear(100, 1))

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        """(N, J, 3) pose in metres -> (N,) critic score (higher = more real)."""
        n = pose.shape[0]
        by_pose = self.pose_path(pose.reshape(n, -1))  # (N, 100)
        by_kcs = self.kcs_path(self.kcs(pose).reshape(n, -1))  # (N, kcs_width)
        return self.head(torch.cat([by_pose, by_kcs], dim=1)).squeeze(1)


def load_critic(state: dict[str, Any]) -> Critic:
    """The trained critic of a checkpoint's (or an exported model's) state: checkpoint.load."""
    critic = Critic(RepNetConfig(**state["model_config"]))
    critic.load_state_dict(state["critic"])
    return critic.eval()


class Plausibility(nn.Module):
    """A pose score calibrated to [0, 1]: its percentile among real validation poses.

    score -- (N, J, 3) pose in metres -> (N,), higher = more like a real pose: the pose density
    (repnet.train.density), or in models exported before it the critic.
    table -- the score of real poses, sorted; a pose scores the share of them it reaches or beats,
    so 0.5 is a typical real pose and 0.01 one that 99 % of them beat.
    bone_range -- optional (2, B) shortest and longest length (metres) a real pose's bones may
    have: a pose with any bone outside scores 0. A score extrapolates: far outside the real poses
    (a limb metres long, which a generator can give for a wild input) a critic can score higher
    than any real pose; no human has such a bone, whatever the score says.
    """

    table: torch.Tensor  # buffer: (1, levels)

    def __init__(self, score: nn.Module, table: torch.Tensor, bone_range: torch.Tensor | None = None) -> None:
        """The score, its calibration table and the bone range as buffers."""
        super().__init__()
        self.score = score
        self.register_buffer("table", table.reshape(1, -1).to(torch.float32))
        self.bone_range: torch.Tensor | None
        if bone_range is None:
            self.bone_range = None
        else:
            self.register_buffer("bone_range", bone_range.reshape(2, -1).to(torch.float32))

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        """(N, J, 3) pose in metres -> (N,) plausibility."""
        score = self.score(pose).unsqueeze(1)  # (N, 1)
        percentile = (score >= self.table).to(pose.dtype).mean(dim=1)
        if self.bone_range is None:
            return percentile
        lengths = bone_lengths(pose)  # (N, B), as plausibility.bone_range measured the real ones
        inside = (lengths >= self.bone_range[0]) & (lengths <= self.bone_range[1])
        return percentile * inside.all(dim=1).to(pose.dtype)


class LiftingGraph(nn.Module):
    """What is exported: pixels and visibility in, pose_3d (mm) and camera out (ONNX contract),
    and with a calibrated Plausibility also plausibility (N,) in [0, 1], with a critic its raw score.

    mirror_average -- also lift the mirror image of every input (x negated, left and right
    swapped), mirror that answer back and average the two (test-time flip augmentation): the
    graph then answers a mirrored input with exactly the mirrored pose and camera.
    critic -- also output the adversarial critic's raw score of each answer ("critic", (N,),
    unbounded): the service does not read it; the file carries the critic so that `repnet adapt`
    can go on training against it (checkpoint.from_onnx).
    """

    flip_points: torch.Tensor  # buffers: (2,), (3,) and (2, 3) signs of a mirror image
    flip_pose: torch.Tensor
    flip_camera: torch.Tensor

    def __init__(
        self,
        generator: RepNet,
        plausibility: Plausibility | None = None,
        mirror_average: bool = False,
        critic: Critic | None = None,
    ) -> None:
        """The graph around a generator, with a calibrated plausibility and the critic when given."""
        super().__init__()
        self.generator = generator
        self.plausibility = plausibility
        self.mirror_average = mirror_average
        self.critic = critic
        # Mirroring flips the sign of x: of pose_3d's first column and of K's (x, .) and (., x)
        # entries, K' = diag(-1, 1) K diag(-1, 1, 1).
        self.register_buffer("flip_points", torch.tensor([-1.0, 1.0]), persistent=False)
        self.register_buffer("flip_pose", torch.tensor([-1.0, 1.0, 1.0]), persistent=False)
        self.register_buffer(
            "flip_camera", torch.tensor([[1.0, -1.0, -1.0], [-1.0, 1.0, 1.0]]), persistent=False
        )

    def lift(self, points: torch.Tensor, visible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The generator on normalised points, averaged with its mirrored answer (mirror_average)."""
        if not self.mirror_average:
            return self.generator(points, visible)
        n, swap = points.shape[0], list(skeleton.MIRROR)
        both_points = torch.cat([points, points[:, swap] * self.flip_points])
        pose, camera = self.generator(both_points, torch.cat([visible, visible[:, swap]]))
        pose_back = pose[n:][:, swap] * self.flip_pose
        camera_back = camera[n:] * self.flip_camera
        return (pose[:n] + pose_back) / 2, (camera[:n] + camera_back) / 2

    def forward(self, keypoints_2d: torch.Tensor, visibility: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(N, J, 2) px, (N, J) visibility -> pose_3d (N, J, 3) mm, camera (N, 2, 3)
        [, plausibility (N,)] [, critic (N,)]."""
        visible = (visibility > 0.5).to(keypoints_2d.dtype)
        pose, camera = self.lift(normalize_keypoints(keypoints_2d, visible), visible)
        outputs = [pose * MM_PER_UNIT, camera / MM_PER_UNIT]
        if self.plausibility is not None:
            outputs.append(self.plausibility(pose))
        if self.critic is not None:
            outputs.append(self.critic(pose))
        return tuple(outputs)
