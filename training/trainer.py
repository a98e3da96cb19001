"""Trainer: the networks, their optimisers and one step of each training mode.

A run is a sequence of phases, each with its own step method, chosen once from the config:
critic-only (the generator frozen), the synthetic warm start (steps before warm_start_steps),
then the adversarial phase. The learning rate follows the step count alone (learning_rate).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from repnet.train import data, synthetic
from repnet.train.augment import (
    augment_visibility,
    corrupt_poses,
    sample_2d,
    with_detector_errors,
)
from repnet.train.camera import camera_frame, camera_scale
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.losses import (
    bone_lengths,
    bone_loss,
    camera_loss,
    critic_loss,
    pose_loss,
    reprojection_loss,
)
from repnet.train.model import MM_PER_UNIT, Critic, RepNet, normalize_keypoints

# The losses every step reports (0 where its mode has no such term), in the history's order.
TERMS = ("rep", "cam", "adv", "bone", "synthetic_pose", "w_dist", "smooth")
CRITIC_FAKES = ("generator", "corrupted")  # what a critic-only stage judges (TrainConfig.critic_fakes)
Terms = dict[str, torch.Tensor]


def pick_device(name: str) -> torch.device:
    """--device: "auto" takes CUDA when there is one, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def learning_rate(config: TrainConfig, step: int) -> float:
    """The learning rate at generator step `step`: a function of the step count only."""
    progress = min(step / max(config.iterations, 1), 1.0)
    if config.schedule == "cosine":
        cosine = 0.5 * (1 + math.cos(math.pi * progress))
        return config.lr * (config.lr_decay + (1 - config.lr_decay) * cosine)
    if config.schedule == "step":
        return config.lr * 0.1 ** min(int(progress * 4), 3)
    if config.schedule == "constant":
        return config.lr
    raise ValueError(f"schedule must be cosine, step or constant, got {config.schedule!r}")


def adversarial_weight(config: TrainConfig, step: int) -> float:
    """0 during the warm start, then ramped linearly to adversarial_weight."""
    if step < config.warm_start_steps:
        return 0.0
    if config.adversarial_ramp <= 0:
        return config.adversarial_weight
    ramp = (step - config.warm_start_steps + 1) / config.adversarial_ramp
    return config.adversarial_weight * min(1.0, ramp)


@dataclass(frozen=True)
class Phase:
    """Steps start..end-1 of a run and the step method that trains them."""

    name: str
    start: int
    end: int
    step: Callable[[int], Terms]


class Trainer:
    """The networks, their optimisers and one step per mode; train() adds data, logs and checkpoints.

    pool -- the TrainingPool (template-aligned 3D, 2D inputs, world poses for the synthetic
    warm start); gen -- the generator every random draw of the steps comes from.
    """

    def __init__(
        self,
        config: TrainConfig,
        model_config: RepNetConfig,
        pool: data.TrainingPool,
        device: torch.device,
        gen: torch.Generator,
    ) -> None:
        """Build the networks and optimisers on `device`, and choose each phase's step method."""
        self.config, self.pool, self.device, self.gen = config, pool, device, gen
        self.real_pool = torch.from_numpy(pool.poses_aligned / MM_PER_UNIT).to(device)  # (M, J, 3) metres
        world = pool.poses_world if pool.poses_world is not None else pool.poses_aligned
        self.world_pool = torch.from_numpy(world)  # (M, J, 3) mm, world frame
        self.mean_bones = bone_lengths(self.real_pool).mean(dim=0)  # (B,) metres
        # The rotation that aligned each world pose to the template (exact: a similarity).
        self.align_rotations: torch.Tensor | None = None
        if config.camera_rotation_weight > 0 or config.limb_turn_deg > 0:
            _, rotations, _ = data.procrustes(world.astype(np.float64), pool.poses_aligned.astype(np.float64))
            self.align_rotations = torch.from_numpy(rotations)
        self.generator = RepNet(model_config).to(device)
        self.critic = Critic(model_config).to(device)
        # The generator's forward and backward as one compiled graph (config.compile); the critic
        # stays eager: its gradient penalty needs a double backward, which torch.compile lacks.
        self.generate: Any = torch.compile(self.generator) if config.compile else self.generator
        betas = (config.beta1, config.beta2)
        # The fused kernel: 3-7 % more samples/s than the default Adam on this CPU (bench.train_step).
        fused = device.type in ("cpu", "cuda")
        self.opt_g = torch.optim.Adam(self.generator.parameters(), lr=config.lr, betas=betas, fused=fused)
        self.opt_c = torch.optim.Adam(self.critic.parameters(), lr=config.lr, betas=betas, fused=fused)
        # Poses of the last generator step, judged by the next critic steps (reuse_fakes).
        self.fakes: torch.Tensor | None = None
        if config.critic_fakes not in CRITIC_FAKES:
            raise ValueError(
                f"critic_fakes must be one of {', '.join(CRITIC_FAKES)}, got {config.critic_fakes!r}"
            )
        self.phases = self._phases()
        # A frozen model whose answers to the synthetic 2D (before detector errors and occlusions)
        # replace the synthetic truth as the target: distillation (repnet.train.adapt); None: the truth.
        self.teacher: torch.nn.Module | None = None

    def _phases(self) -> tuple[Phase, ...]:
        """The run's phases in order, each with the step method chosen for it."""
        config = self.config
        if config.critic_only:
            return (Phase("critic only", 0, config.iterations, self.critic_only_step),)
        warm = config.warm_start_steps
        return (
            Phase("synthetic warm start", 0, warm, self.synthetic_step),
            Phase("adversarial", warm, max(warm, config.iterations), self.adversarial_step),
        )

    def phase_at(self, step: int) -> Phase:
        """The phase that trains generator step `step` (the last one for steps past the end)."""
        return [phase for phase in self.phases if phase.start <= step][-1]

    def run(self, phase: Phase, step: int) -> Terms:
        """Generator step number `step` (0-based) by the phase's method at the step's learning
        rate; returns the losses."""
        lr = learning_rate(self.config, step)
        for opt in (self.opt_g, self.opt_c):
            for group in opt.param_groups:
                group["lr"] = lr
        return phase.step(step)

    def step(self, step: int) -> Terms:
        """Generator step number `step` in whichever phase it falls (benchmarks and tests; train()
        runs each phase's steps with run)."""
        return self.run(self.phase_at(step), step)

    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed run needs to continue bit for bit."""
        return {
            "generator": self.generator.state_dict(),
            "critic": self.critic.state_dict(),
            "opt_g": self.opt_g.state_dict(),
            "opt_c": self.opt_c.state_dict(),
            "rng": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "fakes": self.fakes,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what state_dict saved."""
        self.generator.load_state_dict(state["generator"])
        self.critic.load_state_dict(state["critic"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.opt_c.load_state_dict(state["opt_c"])
        self.gen.set_state(state["rng"])
        if "torch_rng" in state:
            torch.set_rng_state(state["torch_rng"])
        self.fakes = state.get("fakes")

    def _zero_terms(self) -> Terms:
        zero = torch.zeros((), device=self.device)
        return dict.fromkeys(TERMS, zero)

    def _update_generator(self, loss: torch.Tensor) -> None:
        self.opt_g.zero_grad(set_to_none=True)
        loss.backward()  # type: ignore[no-untyped-call]
        self.opt_g.step()

    def critic_only_step(self, step: int) -> Terms:
        """critic_steps critic updates against critic_fakes, the generator frozen."""
        terms = self._zero_terms()
        for _ in range(self.config.critic_steps):
            # "corrupted": real poses with a limb stretched or shrunk, joints swapped or jittered;
            # "generator": None, critic_step generates fresh poses for every update
            corrupted = self.config.critic_fakes == "corrupted"
            self.fakes = (
                corrupt_poses(self.real_batch(self.config.batch_size), self.gen) if corrupted else None
            )
            terms["w_dist"] = self.critic_step()
        self.fakes = None
        return terms

    def synthetic_step(self, step: int) -> Terms:
        """A warm-start step: the generator supervised on a synthetic batch, with the bone prior."""
        terms = self._zero_terms()
        terms["synthetic_pose"], fit, synthetic_pose = self.synthetic_terms()
        terms["bone"] = bone_loss(synthetic_pose, self.mean_bones)
        self._update_generator(terms["synthetic_pose"] + fit + self.config.bone_weight * terms["bone"])
        self.fakes = None
        return terms

    def adversarial_step(self, step: int) -> Terms:
        """critic_steps critic updates, then the generator on real 2D: reprojection, camera,
        adversarial and bone terms (and the synthetic term when synthetic_weight > 0)."""
        config = self.config
        terms = self._zero_terms()
        for _ in range(config.critic_steps):
            terms["w_dist"] = self.critic_step()
        points, visible = sample_2d(self.pool, config, self.device, self.gen)
        pose, camera = self.generate(points, visible)
        terms["rep"] = reprojection_loss(points, visible, pose, camera, config.reprojection_norm)
        terms["cam"] = camera_loss(camera, config.camera_norm)
        terms["adv"] = -self.critic(pose).mean()
        terms["bone"] = bone_loss(pose, self.mean_bones)
        loss_g = (
            config.reprojection_weight * terms["rep"]
            + config.camera_weight * terms["cam"]
            + adversarial_weight(config, step) * terms["adv"]
            + config.bone_weight * terms["bone"]
        )
        if config.synthetic_weight > 0:
            terms["synthetic_pose"], fit, _ = self.synthetic_terms()
            loss_g = loss_g + config.synthetic_weight * (terms["synthetic_pose"] + fit)
        if config.smoothness_weight > 0 and self.pool.triplets is not None and len(self.pool.triplets):
            terms["smooth"] = self.smoothness_term()
            loss_g = loss_g + config.smoothness_weight * terms["smooth"]
        self._update_generator(loss_g)
        # The next critic steps judge these poses: no generator pass of their own.
        self.fakes = pose.detach() if config.reuse_fakes else None
        return terms

    def smoothness_term(self) -> torch.Tensor:
        """Mean |X(t-1) - 2 X(t) + X(t+1)| (m) over joints of the answers to smoothness_batch of
        the pool's triplets of consecutive frames, each answer turned into its camera's frame (the
        rotation in K), so that a person turning is not read as the pose moving."""
        triplets = self.pool.triplets
        assert triplets is not None
        pick = torch.randint(0, len(triplets), (self.config.smoothness_batch,), generator=self.gen).numpy()
        rows = triplets[pick].T.reshape(-1)  # the first frames, then the second ones, then the third
        visible = torch.from_numpy(self.pool.visible[rows]).to(self.device)
        points = normalize_keypoints(torch.from_numpy(self.pool.points_2d[rows]).to(self.device), visible)
        pose, camera = self.generate(points, visible)
        seen = camera_frame(pose, camera).reshape(3, -1, *pose.shape[1:])  # (3, B, J, 3)
        return (seen[0] - 2 * seen[1] + seen[2]).norm(dim=-1).mean()

    def real_batch(self, n: int) -> torch.Tensor:
        """n real poses drawn from real_pool with the run's random generator."""
        idx = torch.randint(0, len(self.real_pool), (n,), generator=self.gen)
        return self.real_pool[idx.to(self.device)]

    def synthetic_terms(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Warm-start loss on a synthetic batch: the pose error, and the reprojection of the
        true pose through the predicted camera plus the camera term (which teach the camera),
        and the generated poses."""
        config = self.config
        pixels, target, to_camera = synthetic.sample(
            self.world_pool,
            self.real_pool,
            config.batch_size,
            config.synthetic_noise_px,
            self.gen,
            self.align_rotations,
            config.camera_rotation_target if config.camera_rotation_weight > 0 else None,
            config.mirror_prob,
            config.synthetic_noise_power,
            config.limb_turn_deg,
            config.limb_turn_prob,
        )
        if self.teacher is not None:
            with torch.no_grad():
                every = torch.ones(pixels.shape[:2], device=self.device)
                target = self.teacher(pixels.to(self.device), every)[0] / MM_PER_UNIT
        visible = augment_visibility(torch.ones(pixels.shape[:2]), config, self.gen)
        pixels, visible = with_detector_errors(pixels, visible, self.pool, config, self.gen)
        visible = visible.to(self.device)
        points = normalize_keypoints(pixels.to(self.device), visible)
        pose, camera = self.generate(points, visible)
        fit = reprojection_loss(points, visible, target, camera, config.reprojection_norm)
        if to_camera is not None:
            rows = camera / camera_scale(camera).clamp_min(1e-6)[:, None, None]
            fit = fit + config.camera_rotation_weight * (rows - to_camera[:, :2].to(self.device)).abs().mean()
        return (
            pose_loss(pose, target),
            fit + config.camera_weight * camera_loss(camera, config.camera_norm),
            pose,
        )

    def critic_step(self) -> torch.Tensor:
        """One WGAN-GP update of the critic; returns the Wasserstein estimate."""
        config = self.config
        if self.fakes is None:
            points, visible = sample_2d(self.pool, config, self.device, self.gen)
            with torch.no_grad():
                self.fakes, _ = self.generate(points, visible)
        real = self.real_batch(config.batch_size)
        loss_c, wasserstein = critic_loss(self.critic, real, self.fakes, config.gp_weight)
        self.opt_c.zero_grad(set_to_none=True)
        loss_c.backward()  # type: ignore[no-untyped-call]
        self.opt_c.step()
        if not config.reuse_fakes:
            self.fakes = None
        return wasserstein
