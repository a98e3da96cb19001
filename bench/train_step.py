"""Training throughput against this machine's fp32 matmul roof, per recipe (a benchmark: it prints).

For each recipe: samples/s (2D samples through the generator per second), the matrix-product
FLOPs of one step (counted op by op as it runs: mm, addmm, bmm, with the gradient penalty's
double backward) and the rate that makes, as a share of the roof: the best rate of a plain
(batch, 1000) x (1000, 1000) matmul at the same batch, with the same threads.
Data are random arrays of the right shapes: the step does not depend on them.

    python -m bench.train_step --threads 2 --seconds 20 --out runs/bench/train_step.json

--only picks recipes by a part of their name; --compile adds each with the generator under
torch.compile (the critic's gradient penalty needs a double backward, which it lacks);
--profile N prints where the time of N steps of each recipe goes (torch.profiler, by op).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from bench.stats import write_json
from repnet.core import skeleton
from repnet.train import data
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.trainer import Trainer

J = skeleton.NUM_JOINTS


@dataclass(frozen=True)
class Recipe:
    """One training step to time: its name and configurations."""

    name: str
    config: TrainConfig
    model: RepNetConfig


# The previous default (repnet-h36m-v1): 5 critic steps per generator step on reused fakes,
# critic 1000 wide on the pose path, 100 on the KCS path.
V1 = Recipe(
    "v1: 5 critic steps, critic 1000/100, batch 256",
    TrainConfig(batch_size=256, critic_steps=5),
    RepNetConfig(critic_width=1000, kcs_width=100),
)
RECIPES: tuple[Recipe, ...] = (
    V1,
    Recipe(
        "authors: 1:1, critic 100/1000, L1, batch 32",
        TrainConfig(batch_size=32, critic_steps=1, reprojection_norm="l1", camera_norm="l1"),
        RepNetConfig(),
    ),
    Recipe("1:1, critic 100/1000, batch 256", TrainConfig(batch_size=256, critic_steps=1), RepNetConfig()),
    Recipe(
        "synthetic warm start, batch 256", TrainConfig(batch_size=256, warm_start_steps=10**9), RepNetConfig()
    ),
    Recipe(
        "1:1 + synthetic term, batch 256",
        TrainConfig(batch_size=256, critic_steps=1, synthetic_weight=1.0),
        RepNetConfig(),
    ),
    Recipe(
        "synthetic warm start, generator 512, batch 256",
        TrainConfig(batch_size=256, warm_start_steps=10**9),
        RepNetConfig(width=512),
    ),
    Recipe(
        "synthetic warm start, shared trunk, batch 256",
        TrainConfig(batch_size=256, warm_start_steps=10**9),
        RepNetConfig(shared_trunk=True),
    ),
    Recipe(
        "1:1 + synthetic term, generator 512, batch 256",
        TrainConfig(batch_size=256, critic_steps=1, synthetic_weight=1.0),
        RepNetConfig(width=512),
    ),
)


class MatmulFlops(TorchDispatchMode):
    """Counts the FLOPs of the matrix products run under it (2 per multiply-add)."""

    def __init__(self) -> None:
        super().__init__()
        self.flops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        name = func.overloadpacket.__name__
        if name in ("mm", "bmm", "addmm", "baddbmm"):
            a, b = (args[1], args[2]) if name in ("addmm", "baddbmm") else (args[0], args[1])
            batch = a.shape[0] if a.dim() == 3 else 1
            self.flops += 2 * batch * a.shape[-2] * a.shape[-1] * b.shape[-1]
        return func(*args, **(kwargs or {}))


def random_pool(rng: np.random.Generator, n: int = 20000) -> data.TrainingPool:
    """A training pool of n random poses (the step's cost does not depend on the data)."""
    poses = rng.normal(0, 300, (n, J, 3)).astype(np.float32)
    poses -= poses[:, :1]
    points = rng.uniform(300, 700, (n, J, 2)).astype(np.float32)
    return data.TrainingPool(poses, points, np.ones((n, J), np.float32), poses_world=poses)


def matmul_roof(batch: int, seconds: float) -> float:
    """Best GFLOP/s of a (batch, 1000) x (1000, 1000) float32 matmul over a few timed bursts."""
    a, w = torch.randn(batch, 1000), torch.randn(1000, 1000)
    best = 0.0
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t = time.perf_counter()
        for _ in range(10):
            a @ w
        best = max(best, 10 * 2 * batch * 1000 * 1000 / (time.perf_counter() - t) / 1e9)
    return best


def _trainer(recipe: Recipe, compile_model: bool = False) -> Trainer:
    """The recipe's Trainer on random data, seed 0; compile_model: the generator under torch.compile."""
    config = dataclasses.replace(recipe.config, compile=compile_model)
    pool = random_pool(np.random.default_rng(0))
    return Trainer(config, recipe.model, pool, torch.device("cpu"), torch.Generator().manual_seed(0))


def measure(recipe: Recipe, seconds: float, compile_model: bool = False) -> dict[str, float | str]:
    """Samples per second of the recipe's step over `seconds`, after a few warm-up steps."""
    trainer = _trainer(recipe, compile_model)
    for step in range(3):  # warm-up (and the compiler's first runs)
        trainer.step(step)
    with MatmulFlops() as counter:
        trainer.step(3)
    flops = counter.flops
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or steps < 3:
        trainer.step(4 + steps)
        steps += 1
    dt = (time.perf_counter() - start) / steps
    return {
        "recipe": recipe.name + (" (torch.compile)" if compile_model else ""),
        "batch": recipe.config.batch_size,
        "ms_per_step": 1e3 * dt,
        "samples_per_s": recipe.config.batch_size / dt,
        "gflop_per_step": flops / 1e9,
        "gflop_per_s": flops / dt / 1e9,
    }


def profile(recipe: Recipe, steps: int, top: int = 12) -> None:
    """Print the ops that take the most CPU time over `steps` steps of `recipe` (torch.profiler)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    trainer = _trainer(recipe)
    for step in range(3):  # warm-up
        trainer.step(step)
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        for step in range(steps):
            trainer.step(3 + step)
    print(f"profile of {steps} steps: {recipe.name}")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=top))


def main(argv: list[str] | None = None) -> None:
    """python -m bench.train_step: time each recipe's step and print the table."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=20.0, help="timed seconds per recipe")
    parser.add_argument("--compile", action="store_true", help="also measure each recipe under torch.compile")
    parser.add_argument("--only", default="", help="measure only recipes whose name contains this")
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="profile N steps of each recipe")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    recipes = [r for r in RECIPES if args.only in r.name]
    if not recipes:
        parser.error(f"--only {args.only!r}: no recipe name contains it")
    if args.profile:
        for recipe in recipes:
            profile(recipe, args.profile)
        return
    roofs = {b: matmul_roof(b, 3.0) for b in sorted({r.config.batch_size for r in recipes})}
    rows = []
    for recipe in recipes:
        for compiled in (False, True) if args.compile else (False,):
            row = measure(recipe, args.seconds, compiled)
            row["roof_gflop_per_s"] = roofs[recipe.config.batch_size]
            row["share_of_roof"] = float(row["gflop_per_s"]) / roofs[recipe.config.batch_size]
            rows.append(row)
            print(
                f"{row['recipe']:<55} {row['samples_per_s']:8.0f} samples/s"
                f"  {row['ms_per_step']:7.1f} ms/step"
                f"  {row['gflop_per_step']:6.2f} GFLOP/step  {row['gflop_per_s']:6.1f} GFLOP/s"
                f" = {row['share_of_roof']:.2f} of the roof ({row['roof_gflop_per_s']:.0f})",
                flush=True,
            )
    if args.out:
        write_json(args.out, {"threads": args.threads, "roof_gflop_per_s": roofs, "rows": rows})


if __name__ == "__main__":
    main()
