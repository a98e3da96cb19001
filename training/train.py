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

from training import data, metrics, skeleton
from training.config import RepNetConfig, TrainConfig
from training.losses import camera_loss, critic_loss, reprojection_loss
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
    pool: data.LiftingSet, config: TrainConfig, device: torch.device, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """A random normalised 2D batch: (B, J, 2) points and (B, J) visibility."""
    idx = torch.randint(0, pool.points_2d.shape[0], (config.batch_size,), generator=gen)
    points = torch.from_numpy(pool.points_2d[idx.numpy()]).to(device)
    visible = augment_visibility(torch.from_numpy(pool.visible[idx.numpy()]).to(device), config, gen)
    if config.noise_px > 0:
        points = points + config.noise_px * torch.randn(points.shape, generator=gen, device=device)
    return normalize_keypoints(points, visible), visible


def validate(generator: RepNet, val: data.LiftingSet, device: torch.device) -> dict[str, float]:
    """Protocol I and II MPJPE (mm) and symmetry error of the generator on a validation set."""
    generator.eval()
    graph = LiftingGraph(generator)
    poses, cameras = [], []
    with torch.no_grad():
        for start in range(0, len(val.points_2d), 4096):
            sl = slice(start, start + 4096)
            pose, cam = graph(
                torch.from_numpy(val.points_2d[sl]).to(device), torch.from_numpy(val.visible[sl]).to(device)
            )
            poses.append(pose.cpu().numpy())
            cameras.append(cam.cpu().numpy())
    generator.train()
    pose, camera = np.concatenate(poses), np.concatenate(cameras)
    return {
        "mpjpe": metrics.mpjpe(metrics.to_camera_frame(pose, camera), val.poses_3d),
        "pa_mpjpe": metrics.pa_mpjpe(pose, val.poses_3d),
        "symmetry": float(metrics.symmetry_error(pose).mean()),
    }


def learning_rate(config: TrainConfig, step: int, elapsed_s: float) -> float:
    """Cosine decay from lr to lr * lr_decay over the run's iterations or wall time."""
    progress = step / config.iterations
    if config.max_minutes > 0:
        progress = max(progress, elapsed_s / (60 * config.max_minutes))
    progress = min(progress, 1.0)
    return config.lr * (config.lr_decay + (1 - config.lr_decay) * 0.5 * (1 + math.cos(math.pi * progress)))


def train(
    config: TrainConfig, model_config: RepNetConfig, resume: Path | None = None, command: str = ""
) -> Path:
    """Run training; returns the path of the best checkpoint (by validation PA-MPJPE)."""
    torch.manual_seed(config.seed)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = pick_device(config.device)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data_dir = data.resolve_data_dir(config.data_dir or None)
    pool, val_sets = data.build_training_sets(data_dir, config.inputs, config.frame_step, config.val_fraction)
    rng = np.random.default_rng(config.seed)
    val_sets = {k: _subsample(v, config.val_size, rng) for k, v in val_sets.items()}
    real_pool = torch.from_numpy(pool.poses_3d / MM_PER_UNIT).to(device)  # (M, J, 3) metres
    log.info(
        "training on %s: %d 3D poses, %d 2D poses, device %s",
        config.inputs,
        len(real_pool),
        len(pool.points_2d),
        device,
    )

    generator, critic = RepNet(model_config).to(device), Critic(model_config).to(device)
    betas = (config.beta1, config.beta2)
    opt_g = torch.optim.Adam(generator.parameters(), lr=config.lr, betas=betas)
    opt_c = torch.optim.Adam(critic.parameters(), lr=config.lr, betas=betas)
    gen = torch.Generator().manual_seed(config.seed)
    step, elapsed, best = 0, 0.0, math.inf
    if resume is not None:
        state = torch.load(resume, map_location=device, weights_only=False)
        generator.load_state_dict(state["generator"])
        critic.load_state_dict(state["critic"])
        opt_g.load_state_dict(state["opt_g"])
        opt_c.load_state_dict(state["opt_c"])
        gen.set_state(state["rng"])
        step, elapsed, best = state["step"], state["elapsed_s"], state["best"]
        log.info("resumed from %s at step %d (%.1f min)", resume, step, elapsed / 60)

    def save(path: Path) -> None:
        torch.save(
            {
                "generator": generator.state_dict(),
                "critic": critic.state_dict(),
                "opt_g": opt_g.state_dict(),
                "opt_c": opt_c.state_dict(),
                "rng": gen.get_state(),
                "step": step,
                "elapsed_s": elapsed,
                "best": best,
                "command": command,
                "model_config": asdict(model_config),
                "train_config": asdict(config),
            },
            path,
        )

    history = (out / "history.jsonl").open("a")
    bar = tqdm(total=config.iterations, initial=step, desc="train", mininterval=10, file=sys.stderr)
    start = time.monotonic() - elapsed
    fakes: torch.Tensor | None = None
    while step < config.iterations and not (config.max_minutes and elapsed >= 60 * config.max_minutes):
        lr = learning_rate(config, step, elapsed)
        for opt in (opt_g, opt_c):
            for group in opt.param_groups:
                group["lr"] = lr
        for _ in range(config.critic_steps):
            if fakes is None:
                points, visible = sample_2d(pool, config, device, gen)
                with torch.no_grad():
                    fakes, _ = generator(points, visible)
            real = real_pool[torch.randint(0, len(real_pool), (config.batch_size,), generator=gen).to(device)]
            loss_c, wasserstein = critic_loss(critic, real, fakes, config.gp_weight)
            opt_c.zero_grad(set_to_none=True)
            loss_c.backward()
            opt_c.step()
            fakes = fakes if config.reuse_fakes else None
        points, visible = sample_2d(pool, config, device, gen)
        pose, camera = generator(points, visible)
        loss_rep = reprojection_loss(points, visible, pose, camera)
        loss_cam = camera_loss(camera)
        loss_adv = -critic(pose).mean()
        loss_g = (
            config.reprojection_weight * loss_rep
            + config.camera_weight * loss_cam
            + config.adversarial_weight * loss_adv
        )
        opt_g.zero_grad(set_to_none=True)
        loss_g.backward()
        opt_g.step()
        # The next critic steps judge these poses: no generator pass of their own.
        fakes = pose.detach() if config.reuse_fakes else None
        step += 1
        elapsed = time.monotonic() - start
        bar.update(1)
        if step % config.log_every == 0:
            record: dict[str, Any] = {
                "step": step,
                "minutes": round(elapsed / 60, 2),
                "lr": lr,
                "rep": loss_rep.item(),
                "cam": loss_cam.item(),
                "adv": loss_adv.item(),
                "w_dist": wasserstein.item(),
            }
            bar.set_postfix({k: f"{record[k]:.3f}" for k in ("rep", "cam", "w_dist")})
            if step % config.val_every == 0:
                for kind, val in val_sets.items():
                    for name, value in validate(generator, val, device).items():
                        record[f"val_{kind}_{name}"] = round(value, 2)
                score = record[f"val_{next(iter(val_sets))}_pa_mpjpe"]
                if score < best:
                    best = score
                    save(out / "best.pt")
                log.info(json.dumps(record))
            history.write(json.dumps(record) + "\n")
            history.flush()
        if step % config.checkpoint_every == 0:
            save(out / "last.pt")
    bar.close()
    save(out / "last.pt")
    for kind, val in val_sets.items():
        log.info("final validation on %s: %s", kind, validate(generator, val, device))
    if not (out / "best.pt").exists():
        save(out / "best.pt")
    return out / "best.pt"


def _subsample(val: data.LiftingSet, size: int, rng: np.random.Generator) -> data.LiftingSet:
    idx = np.sort(rng.choice(len(val.points_2d), size=min(size, len(val.points_2d)), replace=False))
    return data.LiftingSet(val.poses_3d[idx], val.points_2d[idx], val.visible[idx])


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
    parser.add_argument("--resume", type=Path, help="checkpoint to continue from (e.g. runs/x/last.pt)")
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
