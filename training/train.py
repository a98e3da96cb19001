"""Train RepNet (WGAN-GP with reprojection and camera losses) on Human3.6M; checkpoints and resume."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from training import checkpoint, data, metrics, skeleton, synthetic
from training.camera import camera_scale
from training.config import RepNetConfig, TrainConfig
from training.losses import bone_lengths, bone_loss, camera_loss, critic_loss, pose_loss, reprojection_loss
from training.model import MM_PER_UNIT, Critic, LiftingGraph, RepNet, normalize_keypoints

log = logging.getLogger(__name__)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def augment_visibility(visible: torch.Tensor, config: TrainConfig, gen: torch.Generator) -> torch.Tensor:
    """Hide 1..mask_max random non-root joints in a mask_prob share of the (N, J) masks, and the
    spine in another spine_mask_prob share, so that the network learns to lift occluded poses."""
    n, j = visible.shape
    dev = visible.device
    scores = torch.rand(n, j, generator=gen, device=dev)
    scores[:, skeleton.ROOT] = 2.0  # never picked
    count = torch.randint(1, config.mask_max + 1, (n, 1), generator=gen, device=dev)
    count = count * (torch.rand(n, 1, generator=gen, device=dev) < config.mask_prob)
    rank = scores.argsort(dim=1).argsort(dim=1)  # (N, J) rank of each joint's score
    hide = rank < count
    hide[:, skeleton.SPINE] |= torch.rand(n, generator=gen, device=dev) < config.spine_mask_prob
    return visible * (~hide).to(visible.dtype)


def sample_2d(
    pool: data.TrainingPool, config: TrainConfig, device: torch.device, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """A random normalised 2D batch: (B, J, 2) points and (B, J) visibility."""
    idx = torch.randint(0, pool.points_2d.shape[0], (config.batch_size,), generator=gen)
    points = torch.from_numpy(pool.points_2d[idx.numpy()]).to(device)
    visible = augment_visibility(torch.from_numpy(pool.visible[idx.numpy()]).to(device), config, gen)
    if config.noise_px > 0:
        points = points + config.noise_px * torch.randn(points.shape, generator=gen, device=device)
    return normalize_keypoints(points, visible), visible


# A bone over this many times its true mean length makes an answer "wild" (validation's wild_pct).
WILD_RATIO = 3.0


def validate(
    generator: RepNet, val: data.ValidationSet, device: torch.device, mirror_average: bool = False
) -> dict[str, float]:
    """Protocol I and II MPJPE, symmetry error and limb bone length std (mm) on a validation set;
    mirror_average: of the graph that averages each answer with the mirrored one (LiftingGraph)."""
    generator.eval()
    graph = LiftingGraph(generator, mirror_average=mirror_average)
    poses, cameras = [], []
    with torch.no_grad():
        for start in range(0, len(val.points_2d), 4096):
            sl = slice(start, start + 4096)
            pose, cam = graph(
                torch.from_numpy(val.points_2d[sl]).to(device), torch.from_numpy(val.visible[sl]).to(device)
            )[:2]
            poses.append(pose.cpu().numpy())
            cameras.append(cam.cpu().numpy())
    generator.train()
    pose, camera = np.concatenate(poses), np.concatenate(cameras)
    ray: dict[str, float] = {}
    if val.focal is not None and val.centre is not None:
        rotation = metrics.ray_rotation(val.points_2d, val.visible, val.focal, val.centre)
        pose_cam, pose_ray = metrics.camera_frames(pose, camera, rotation)
        ray["mpjpe_ray"] = metrics.mpjpe(pose_ray, val.poses_camera)
    else:
        pose_cam = metrics.to_camera_frame(pose, camera)
    lengths = bone_lengths(torch.from_numpy(pose)).numpy()  # (N, B) mm
    truth = bone_lengths(torch.from_numpy(val.poses_camera)).numpy().mean(axis=0)  # (B,)
    return {
        "mpjpe": metrics.mpjpe(pose_cam, val.poses_camera),
        **ray,
        "pa_mpjpe": metrics.pa_mpjpe(pose, val.poses_camera),
        "symmetry": float(metrics.symmetry_error(pose).mean()),
        "bone_std": float(metrics.limb_length_std(pose).mean()),
        "wild_pct": 100.0 * float(((lengths / truth).max(axis=1) > WILD_RATIO).mean()),
    }


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


def _subtrees() -> torch.Tensor:
    """(J, J) mask: row c marks joint c and every joint below it in the kinematic tree."""
    mask = torch.eye(skeleton.NUM_JOINTS, dtype=torch.bool)
    for joint in range(skeleton.NUM_JOINTS):  # parents come before their children
        parent = skeleton.PARENTS[joint]
        while parent >= 0:
            mask[parent, joint] = True
            parent = skeleton.PARENTS[parent]
    return mask


SUBTREES = _subtrees()
LIMB_CHILDREN = torch.tensor([child for _, child in metrics.LIMB_BONES])


def corrupt_poses(poses: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Implausible versions of (N, J, 3) real poses (metres), a third each way: one arm or leg
    bone 25-50 % longer or 20-40 % shorter (the joints below it moved along); two non-root
    joints swapped; every joint jittered by N(0, 3-8 cm)."""
    n = poses.shape[0]
    out = poses.clone()
    kind = torch.randint(0, 3, (n,), generator=gen)
    # 0: a limb bone stretched or shrunk
    child = LIMB_CHILDREN[torch.randint(0, len(LIMB_CHILDREN), (n,), generator=gen)]
    parent = torch.tensor(skeleton.PARENTS)[child]
    longer = torch.rand(n, generator=gen) < 0.5
    factor = torch.where(
        longer, 1.25 + 0.25 * torch.rand(n, generator=gen), 0.6 + 0.2 * torch.rand(n, generator=gen)
    )
    rows = torch.arange(n)
    bone = poses[rows, child] - poses[rows, parent]  # (N, 3)
    moved = SUBTREES[child].to(poses.dtype)  # (N, J)
    stretched = poses + (factor - 1)[:, None, None] * moved[:, :, None] * bone[:, None, :]
    # 1: two joints swapped
    a = torch.randint(1, skeleton.NUM_JOINTS, (n,), generator=gen)
    b = 1 + (a - 1 + torch.randint(1, skeleton.NUM_JOINTS - 1, (n,), generator=gen)) % (
        skeleton.NUM_JOINTS - 1
    )
    swapped = poses.clone()
    swapped[rows, a], swapped[rows, b] = poses[rows, b], poses[rows, a]
    # 2: jitter
    sigma = 0.03 + 0.05 * torch.rand(n, 1, 1, generator=gen)
    jittered = poses + sigma * torch.randn(poses.shape, generator=gen)
    out = torch.where((kind == 0)[:, None, None], stretched, out)
    out = torch.where((kind == 1)[:, None, None], swapped, out)
    out = torch.where((kind == 2)[:, None, None], jittered, out)
    return out - out[:, skeleton.ROOT : skeleton.ROOT + 1]


def resolve_resume(resume: str | Path | None, out_dir: Path) -> Path | None:
    """--resume: a checkpoint path, or "auto" for out_dir/last.pt when it exists (else a fresh start)."""
    if resume is None or str(resume) == "":
        return None
    if str(resume) == "auto":
        last = out_dir / "last.pt"
        return last if last.is_file() else None
    path = Path(resume)
    if not path.is_file():
        raise FileNotFoundError(f"--resume {path}: no such checkpoint")
    return path


class Trainer:
    """The networks, their optimisers and one training step; train() adds data, logs and checkpoints.

    pool -- the TrainingPool (template-aligned 3D, 2D inputs, world poses for the synthetic
    warm start); gen -- the generator every random draw of the step comes from.
    """

    def __init__(
        self,
        config: TrainConfig,
        model_config: RepNetConfig,
        pool: data.TrainingPool,
        device: torch.device,
        gen: torch.Generator,
    ) -> None:
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

    def state_dict(self) -> dict[str, Any]:
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
        self.generator.load_state_dict(state["generator"])
        self.critic.load_state_dict(state["critic"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.opt_c.load_state_dict(state["opt_c"])
        self.gen.set_state(state["rng"])
        if "torch_rng" in state:
            torch.set_rng_state(state["torch_rng"])
        self.fakes = state.get("fakes")

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
        visible = augment_visibility(torch.ones(pixels.shape[:2]), config, self.gen).to(self.device)
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
        idx = torch.randint(0, len(self.real_pool), (config.batch_size,), generator=self.gen).to(self.device)
        loss_c, wasserstein = critic_loss(self.critic, self.real_pool[idx], self.fakes, config.gp_weight)
        self.opt_c.zero_grad(set_to_none=True)
        loss_c.backward()
        self.opt_c.step()
        if not config.reuse_fakes:
            self.fakes = None
        return wasserstein

    def step(self, step: int) -> dict[str, torch.Tensor]:
        """Generator step number `step` (0-based), after its critic steps; returns the losses."""
        config = self.config
        lr = learning_rate(config, step)
        for opt in (self.opt_g, self.opt_c):
            for group in opt.param_groups:
                group["lr"] = lr
        zero = torch.zeros((), device=self.device)
        terms = dict.fromkeys(("rep", "cam", "adv", "bone", "synthetic_pose", "w_dist"), zero)
        if config.critic_only:
            for _ in range(config.critic_steps):
                self.fakes = None  # fresh poses of the frozen generator for every update
                if config.critic_fakes == "corrupted":
                    idx = torch.randint(0, len(self.real_pool), (config.batch_size,), generator=self.gen)
                    self.fakes = corrupt_poses(self.real_pool[idx.to(self.device)], self.gen)
                elif config.critic_fakes != "generator":
                    raise ValueError(
                        f"critic_fakes must be generator or corrupted, got {config.critic_fakes!r}"
                    )
                terms["w_dist"] = self.critic_step()
            self.fakes = None
            return terms
        if step < config.warm_start_steps:
            terms["synthetic_pose"], fit, synthetic_pose = self.synthetic_terms()
            terms["bone"] = bone_loss(synthetic_pose, self.mean_bones)
            loss_g = terms["synthetic_pose"] + fit + config.bone_weight * terms["bone"]
            pose = None
        else:
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
        self.opt_g.zero_grad(set_to_none=True)
        loss_g.backward()
        self.opt_g.step()
        # The next critic steps judge these poses: no generator pass of their own.
        self.fakes = pose.detach() if (config.reuse_fakes and pose is not None) else None
        return terms


def train(
    config: TrainConfig,
    model_config: RepNetConfig,
    resume: str | Path | None = None,
    command: str = "",
) -> Path:
    """Run training; returns the path of the best checkpoint (by validation PA-MPJPE).

    resume -- a checkpoint, or "auto" for out_dir/last.pt if there is one. A resumed run
    continues bit for bit: weights, optimiser moments, every random generator, the step
    count (which alone drives the schedules) and the poses the next critic step judges.
    """
    torch.manual_seed(config.seed)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = pick_device(config.device)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    resume_path = resolve_resume(resume, out)
    data_dir = data.resolve_data_dir(config.data_dir or None)
    pool, val_sets = data.build_training_sets(data_dir, config.inputs, config.frame_step, config.val_fraction)
    val_sets = validation_sets(config, val_sets)
    log.info(
        "training on %s: %d 3D poses, %d 2D poses, device %s",
        config.inputs,
        len(pool.poses_aligned),
        len(pool.points_2d),
        device,
    )
    trainer = Trainer(config, model_config, pool, device, torch.Generator().manual_seed(config.seed))
    step, elapsed, best = 0, 0.0, math.inf
    if config.init_from and resume_path is None:
        state = checkpoint.load(config.init_from)
        trainer.generator.load_state_dict(state["generator"])
        own = trainer.critic.state_dict()
        same_critic = state["critic"].keys() == own.keys() and all(
            v.shape == own[k].shape for k, v in state["critic"].items()
        )
        if same_critic:
            trainer.critic.load_state_dict(state["critic"])
        log.info(
            "initialised the generator%s from %s (its step %d); starting at step 0",
            " and the critic" if same_critic else " (the critic's shape differs: a fresh critic)",
            config.init_from,
            state["step"],
        )
    if resume_path is not None:
        state = torch.load(resume_path, map_location=device, weights_only=False)
        trainer.load_state_dict(state)
        step, elapsed, best = state["step"], state["elapsed_s"], state["best"]
        _truncate_history(out / "history.jsonl", step)
        log.info("resumed from %s at step %d (%.1f min)", resume_path, step, elapsed / 60)

    def save(path: Path) -> None:
        tmp = path.with_suffix(".tmp")
        torch.save(
            {
                **trainer.state_dict(),
                "step": step,
                "elapsed_s": elapsed,
                "best": best,
                "command": command,
                "model_config": asdict(model_config),
                "train_config": asdict(config),
            },
            tmp,
        )
        tmp.replace(path)  # never a half-written checkpoint, even if killed mid-save

    history = (out / "history.jsonl").open("a")
    bar = tqdm(total=config.iterations, initial=step, desc="train", mininterval=10, file=sys.stderr)
    start = time.monotonic() - elapsed
    last_save = time.monotonic()
    stop = min(config.iterations, config.stop_step or config.iterations)
    while step < stop and not (config.max_minutes and elapsed >= 60 * config.max_minutes):
        terms = trainer.step(step)
        step += 1
        elapsed = time.monotonic() - start
        bar.update(1)
        if step % config.log_every == 0:
            record: dict[str, Any] = {
                "step": step,
                "minutes": round(elapsed / 60, 2),
                "lr": learning_rate(config, step - 1),
                "adv_weight": adversarial_weight(config, step - 1),
                **{name: value.item() for name, value in terms.items()},
            }
            bar.set_postfix({k: f"{record[k]:.3f}" for k in ("rep", "cam", "w_dist", "synthetic_pose")})
            if step % config.val_every == 0:
                for kind, val in val_sets.items():
                    for name, value in validate(trainer.generator, val, device).items():
                        record[f"val_{kind}_{name}"] = round(value, 2)
                score = record[f"val_{next(iter(val_sets))}_pa_mpjpe"]
                if score < best:
                    best = score
                    save(out / "best.pt")
                log.info(json.dumps(record))
            history.write(json.dumps(record) + "\n")
            history.flush()
        due = time.monotonic() - last_save >= 60 * config.checkpoint_minutes
        if step % config.checkpoint_every == 0 or due:
            save(out / "last.pt")
            last_save = time.monotonic()
    bar.close()
    save(out / "last.pt")
    for kind, val in val_sets.items():
        log.info("final validation on %s: %s", kind, validate(trainer.generator, val, device))
    if not (out / "best.pt").exists():
        save(out / "best.pt")
    return out / "best.pt"


def validation_sets(
    config: TrainConfig, held_out: dict[str, data.ValidationSet]
) -> dict[str, data.ValidationSet]:
    """The sets a run validates on, from build_training_sets' held-out tails: val_size poses of each
    input kind, and of GT 2D also with noise (gt_noise) and mirrored (gt_mirror). The same draw
    for the same seed, so runs and training.validate score the same poses."""
    rng = np.random.default_rng(config.seed)
    sets = {kind: _subsample(val, config.val_size, rng) for kind, val in held_out.items()}
    if config.val_noise_px > 0 and "gt" in sets:
        sets["gt_noise"] = with_noise(sets["gt"], config.val_noise_px, rng)
    if config.val_mirror and "gt" in sets:
        sets["gt_mirror"] = _mirrored(sets["gt"])
    return sets


def _truncate_history(path: Path, step: int) -> None:
    """Drop the records an interrupted run wrote after the checkpoint it resumes from."""
    if not path.is_file():
        return
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    kept = [line for line in lines if json.loads(line)["step"] <= step]
    path.write_text("".join(line + "\n" for line in kept))


def _subsample(val: data.ValidationSet, size: int, rng: np.random.Generator) -> data.ValidationSet:
    idx = np.sort(rng.choice(len(val.points_2d), size=min(size, len(val.points_2d)), replace=False))
    arrays = {f.name: getattr(val, f.name) for f in dataclasses.fields(val)}
    return data.ValidationSet(**{name: None if a is None else a[idx] for name, a in arrays.items()})


def with_noise(val: data.ValidationSet, sigma_px: float, rng: np.random.Generator) -> data.ValidationSet:
    """The same validation poses with N(0, sigma_px) px added to their 2D points."""
    noise = rng.normal(0.0, sigma_px, val.points_2d.shape).astype(val.points_2d.dtype)
    return dataclasses.replace(val, points_2d=val.points_2d + noise)


def with_hidden_joints(
    val: data.ValidationSet, count: int, rng: np.random.Generator
) -> data.ValidationSet:
    """The same validation poses with `count` random non-root joints of each hidden."""
    points, visible = data.hide_random_joints(val.points_2d, val.visible, count, rng)
    return dataclasses.replace(val, points_2d=points, visible=visible)


def _mirrored(val: data.ValidationSet) -> data.ValidationSet:
    """The validation poses mirrored: 2D flipped about each camera's principal point, 3D (camera
    frame) flipped in x, left and right joints swapped in both."""
    if val.centre is None:
        raise ValueError("mirroring a validation set needs its principal points")
    swap = list(skeleton.MIRROR)
    points = val.points_2d[:, swap].copy()
    points[..., 0] = 2 * val.centre[:, None, 0] - points[..., 0]
    poses = val.poses_camera[:, swap].copy()
    poses[..., 0] = -poses[..., 0]
    return dataclasses.replace(val, poses_camera=poses, points_2d=points, visible=val.visible[:, swap].copy())


def _add_flags(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    for field in dataclasses.fields(cls):
        flag = "--" + prefix + field.name.replace("_", "-")
        kind = type(field.default)
        if kind is bool:
            parser.add_argument(flag, type=lambda s: s.lower() in ("1", "true", "yes"), default=field.default)
        else:
            parser.add_argument(flag, type=kind, default=field.default)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    _add_flags(parser, TrainConfig)
    _add_flags(parser, RepNetConfig)
    parser.add_argument(
        "--resume",
        default="",
        help="checkpoint to continue from (e.g. runs/x/last.pt), or 'auto': out-dir/last.pt when it exists",
    )
    args = parser.parse_args(argv)
    values = vars(args)
    config = TrainConfig(**{f.name: values[f.name] for f in dataclasses.fields(TrainConfig)})
    model_config = RepNetConfig(**{f.name: values[f.name] for f in dataclasses.fields(RepNetConfig)})
    Path(config.out_dir).mkdir(parents=True, exist_ok=True)
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(message)s",
        handlers=[logging.StreamHandler(), logging.FileHandler(Path(config.out_dir) / "train.log")],
    )
    command = "python -m training.train " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    best = train(config, model_config, resume=args.resume, command=command)
    log.info("best checkpoint: %s", best)


if __name__ == "__main__":
    main()
