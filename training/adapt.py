"""Weakly supervised adaptation of a shipped model to a user's own 2D detections (`repnet adapt`).

No 3D of the user's is given or needed. The generator learns on two things that are never paired:
the user's 2D poses, and 3D poses drawn from the shipped pose prior (repnet.train.prior). The steps
are the Trainer's (repnet.train.trainer):

- the paper's terms on the user's 2D: reprojection through the predicted camera with missing
  joints' columns zeroed, the camera term and the KCS critic's Wasserstein term (weights 0.1 by
  default; at 1 they bend every answer to the detector's errors, docs/RESULTS.md), with the
  bone-length prior; the critic starts from the parent's and warms up before the generator moves.
- the synthetic task as an anchor, so that the model cannot forget: prior poses through random
  cameras, the target the parent's own answer to the clean 2D (anchor_target "parent": distillation;
  "truth": the prior's pose). In `residual_share` of them the 2D carries the user's detector error
  instead of white noise: the user's pose minus the reprojection K X of the model's answer to it (in
  units of the pose's spread), what no human pose explains (a hip put too low, a head top too
  high); residual_mode "mean" (default) adds the mean of those per joint, the detector's systematic
  offsets, "pose" one user pose's. They are measured again every `refresh_every` steps with the
  adapted model.

AdaptConfig holds every choice; a run checkpoints and resumes bit for bit (Adaptation).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from repnet.train import data, presets
from repnet.train.camera import masked_centre, project_weak_perspective
from repnet.train.checkpoint import read_state
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.export import generator_of
from repnet.train.model import LiftingGraph, RepNet, normalize_keypoints
from repnet.train.prior import PosePrior
from repnet.train.trainer import Terms, Trainer


@dataclass(frozen=True)
class AdaptConfig:
    """One adaptation run. steps and minutes stop it; they may change on resume, nothing else may."""

    # `repnet adapt` without --steps chooses 500 or 2,000 from the user's held-out 2D
    # (repnet.train.adapt_report.default_steps: clips of consecutive frames or spread poses).
    steps: int = 500
    minutes: float = 25.0  # wall-time limit of this call (checkpointed, --resume goes on); 0 = none
    lr: float = 3e-5  # constant: a stop at any step leaves a usable model
    batch_size: int = 256
    residual_share: float = 0.5  # synthetic poses with the user's detector error
    # "pose": each such pose gets the error of one user pose; "mean": the mean error per joint
    # over the user's poses (the detector's systematic offsets only).
    residual_mode: str = "mean"
    residual_min: float = 0.8  # those errors scaled by U(min, max)
    residual_max: float = 1.2
    refresh_every: int = 1000  # measure the user's errors again with the adapted model; 0 = never
    reprojection_weight: float = 0.1  # the paper's terms on the user's 2D
    camera_weight: float = 1.0
    adversarial_weight: float = 0.1
    critic_steps: int = 1
    critic_warmup: int = 20  # critic-only steps against the parent's answers before the generator moves
    anchor_weight: float = 2.0  # the synthetic task beside the paper's terms (when their weights > 0)
    bone_weight: float = 10.0  # the bone-length prior, on the answers to the user's 2D too
    # Temporal consistency of the user's sequences: the second difference of the answers to three
    # consecutive frames of one person (m), where the inputs say which frames those are.
    smoothness_weight: float = 0.0
    # The synthetic task's target: "parent", the parent's answer to the clean synthetic 2D
    # (distillation: the model keeps its answers, and learns to give them under the user's
    # errors); "truth", the prior's pose itself.
    anchor_target: str = "parent"
    holdout_fraction: float = 0.1
    prior_poses: int = 100_000
    seed: int = 0


# What may differ between a run and its resumption.
RESUMABLE = ("steps", "minutes")


def synthetic_settings() -> TrainConfig:
    """The synthetic task of the bundled model's last stage: its noise, mirroring, limb turns and
    occlusions (repnet.train.presets)."""
    return presets.get("repnet-h36m-v7").stages[-1].train


def train_config(config: AdaptConfig, threads: int) -> TrainConfig:
    """The Trainer's configuration for an adaptation."""
    paper = config.reprojection_weight > 0 or config.adversarial_weight > 0
    return replace(
        synthetic_settings(),
        seed=config.seed,
        threads=threads,
        device="cpu",
        batch_size=config.batch_size,
        lr=config.lr,
        schedule="constant",
        iterations=config.steps,
        stop_step=0,
        warm_start_steps=0 if paper else config.steps,
        synthetic_weight=config.anchor_weight if paper else 0.0,
        reprojection_weight=config.reprojection_weight,
        camera_weight=config.camera_weight,
        adversarial_weight=config.adversarial_weight,
        critic_steps=config.critic_steps,
        critic_fakes="generator",
        bone_weight=config.bone_weight,
        smoothness_weight=config.smoothness_weight,
        detector_error_prob=config.residual_share,
        detector_error_min=config.residual_min,
        detector_error_max=config.residual_max,
        init_from="",
    )


def split_holdout(counts: list[int], fraction: float) -> np.ndarray:
    """(sum(counts),) True for the poses held out: the last `fraction` of each input (contiguous,
    so neighbouring frames of a sequence do not leak), at least one of every input of two or more."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"holdout fraction must be in [0, 1), got {fraction}")
    masks = []
    for n in counts:
        held = int(round(n * fraction)) if fraction > 0 else 0
        held = min(max(held, 1 if fraction > 0 and n >= 2 else 0), n - 1 if n > 1 else 0)
        masks.append(np.arange(n) >= n - held)
    return np.concatenate(masks) if masks else np.zeros(0, dtype=bool)


def triplets_of(previous: np.ndarray) -> np.ndarray:
    """(T, 3) rows (p, t, n) of three consecutive frames of one person, from `previous` (N,): per
    row the row of the same person's frame before it, -1 where there is none."""
    following = np.full(len(previous), -1, dtype=np.int64)
    has = np.flatnonzero(previous >= 0)
    following[previous[has]] = has
    middle = np.flatnonzero((previous >= 0) & (following >= 0))
    return np.stack([previous[middle], middle, following[middle]], axis=1).astype(np.int64)


def answer(
    generator: RepNet, points: np.ndarray, visible: np.ndarray, mirror_average: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's (N, J, 3) pose (mm), (N, 2, 3) camera and (N, J, 2) residual W - K X of pixel
    (N, J, 2) points, the residual in units of the pose's spread (0 at hidden joints)."""
    training = generator.training
    graph = LiftingGraph(generator, mirror_average=mirror_average).eval()
    poses, cameras, residuals = [], [], []
    with torch.no_grad():
        for start in range(0, len(points), 4096):
            p = torch.from_numpy(points[start : start + 4096])
            v = torch.from_numpy(visible[start : start + 4096])
            pose, camera = graph(p, v)[:2]
            w = normalize_keypoints(p, v)
            reprojected = masked_centre(project_weak_perspective(camera, pose), v)  # the graph's K is per mm
            residuals.append(((w - reprojected) * v[..., None]).numpy())
            poses.append(pose.numpy())
            cameras.append(camera.numpy())
    generator.train(training)
    return np.concatenate(poses), np.concatenate(cameras), np.concatenate(residuals).astype(np.float32)


def digest(*arrays: np.ndarray) -> str:
    """sha256 of arrays' bytes (what a resumed run must find again)."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


class ConfigMismatch(ValueError):
    """--resume found a checkpoint of another run (other settings, inputs or parent)."""


class Adaptation:
    """An adaptation of `parent` (a checkpoint state: repnet.train.checkpoint.load) to the user's
    pixel points (N, J, 2) and visibility (N, J) of the training part (the holdout is not here).
    mirror_average -- the parent's export setting: its answers average each pose with its mirror.
    previous -- (N,) per pose the row of the same person's frame before it, -1 where none (None: the
      poses are not known to be sequences; the smoothness term then has nothing to judge)."""

    def __init__(
        self,
        config: AdaptConfig,
        parent: dict[str, Any],
        points: np.ndarray,
        visible: np.ndarray,
        mirror_average: bool,
        threads: int = 0,
        prior: PosePrior | None = None,
        previous: np.ndarray | None = None,
    ) -> None:
        self.config, self.mirror_average = config, mirror_average
        torch.manual_seed(config.seed)
        if threads:
            torch.set_num_threads(threads)
        self.points, self.visible = points.astype(np.float32), visible.astype(np.float32)
        prior = prior or PosePrior.load()
        world = prior.sample(config.prior_poses, np.random.default_rng(config.seed))
        pool = data.TrainingPool(
            poses_aligned=data.align_to_template(world),
            points_2d=self.points,
            visible=self.visible,
            poses_world=world,
            triplets=None if previous is None else triplets_of(previous),
        )
        model_config = RepNetConfig(**parent["model_config"])
        self.trainer = Trainer(
            train_config(config, threads),
            model_config,
            pool,
            torch.device("cpu"),
            torch.Generator().manual_seed(config.seed),
        )
        self.trainer.generator.load_state_dict(parent["generator"])
        if parent.get("critic"):
            self.trainer.critic.load_state_dict(parent["critic"])
        if config.anchor_target == "parent":
            self.trainer.teacher = LiftingGraph(generator_of(parent), mirror_average=mirror_average).eval()
        elif config.anchor_target != "truth":
            raise ValueError(f"anchor_target must be parent or truth, got {config.anchor_target!r}")
        self.step, self.elapsed = 0, 0.0
        self.inputs_sha = digest(self.points, self.visible, *(() if previous is None else (previous,)))
        # The detector errors are measured when the run starts (run), unless a checkpoint brings them.

    def refresh(self) -> None:
        """Measure the user's detector errors with the generator as it is now."""
        _, _, residuals = answer(self.trainer.generator, self.points, self.visible, self.mirror_average)
        if self.config.residual_mode == "mean":
            seen = self.visible.sum(axis=0)[:, None]  # (J, 1)
            mean = residuals.sum(axis=0) / np.maximum(seen, 1.0)
            residuals = np.broadcast_to(mean, residuals.shape) * self.visible[..., None]
        elif self.config.residual_mode != "pose":
            raise ValueError(f"residual_mode must be pose or mean, got {self.config.residual_mode!r}")
        self.trainer.pool = replace(
            self.trainer.pool, detector_errors=residuals, detector_visible=self.visible
        )

    def run(
        self,
        minutes: float,
        checkpoint: Path | None,
        every_s: float = 120.0,
        on_step: Callable[[int, Terms], None] | None = None,
    ) -> bool:
        """Train up to config.steps, or for `minutes` of wall time (0: no limit), checkpointing to
        `checkpoint` every `every_s` seconds and at the end; True when all steps are done."""
        config, trainer = self.config, self.trainer
        if trainer.pool.detector_errors is None:
            self.refresh()
        start = last_save = time.monotonic()
        base_elapsed = self.elapsed
        while self.step < config.steps:
            if minutes and time.monotonic() - start >= minutes * 60:
                break
            if config.refresh_every and self.step and self.step % config.refresh_every == 0:
                self.refresh()
            if self.step < config.critic_warmup:  # the generator frozen
                terms = trainer.critic_only_step(self.step)
            else:
                terms = trainer.step(self.step)
            self.step += 1
            self.elapsed = base_elapsed + time.monotonic() - start
            if on_step is not None:
                on_step(self.step, terms)
            if checkpoint is not None and time.monotonic() - last_save >= every_s:
                self.save(checkpoint)
                last_save = time.monotonic()
        self.elapsed = base_elapsed + time.monotonic() - start
        if checkpoint is not None:
            self.save(checkpoint)
        return self.step >= config.steps

    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed run needs to go on bit for bit."""
        return {
            "trainer": self.trainer.state_dict(),
            "step": self.step,
            "elapsed_s": self.elapsed,
            "config": asdict(self.config),
            "inputs_sha256": self.inputs_sha,
            "detector_errors": _tensor_or_none(self.trainer.pool.detector_errors),  # no numpy: weights_only
        }

    def save(self, path: Path) -> None:
        """Write the checkpoint atomically (a kill mid-write leaves the previous one)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        torch.save(self.state_dict(), tmp)
        tmp.replace(path)

    def load(self, path: Path) -> None:
        """Continue from a checkpoint that save wrote for the same settings and inputs."""
        state = read_state(path)
        mine, theirs = asdict(self.config), state["config"]
        changed = sorted(k for k in mine if k not in RESUMABLE and theirs.get(k) != mine[k])
        if changed:
            settings = ", ".join(f"{k}={theirs.get(k)}" for k in changed)
            raise ConfigMismatch(
                f"{path}: written with other settings ({settings}); pass the same ones, or start afresh "
                "without --resume"
            )
        if state["inputs_sha256"] != self.inputs_sha:
            raise ConfigMismatch(f"{path}: written for other input poses; start afresh without --resume")
        self.trainer.load_state_dict(state["trainer"])
        self.step, self.elapsed = int(state["step"]), float(state["elapsed_s"])
        errors = None if state["detector_errors"] is None else state["detector_errors"].numpy()
        self.trainer.pool = replace(self.trainer.pool, detector_errors=errors, detector_visible=self.visible)


def _tensor_or_none(array: np.ndarray | None) -> torch.Tensor | None:
    """`array` as a tensor (a checkpoint holds tensors and plain values only, so that torch.load
    reads it with weights_only=True and runs no code from the file)."""
    return None if array is None else torch.from_numpy(np.ascontiguousarray(array))
