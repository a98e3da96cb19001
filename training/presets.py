"""Named presets: one per shipped model, the whole chain of training stages that reproduces it.

A preset lists its stages in order (each a full TrainConfig and RepNetConfig, stopping on a step,
never on wall time), the stage that trains the plausibility critic, and what is exported: one
config per released checkpoint, as mmpose keeps them, written as data in the spirit of nanoGPT's
config/*.py. `python -m repnet.train.train --preset NAME` runs one (repnet.train.chain); the thread count,
device and folders are set on the command line, not here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal

from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.plausibility import DensityConfig, Score
from repnet.train.sequences import ClipConfig, ClipNoise
from repnet.train.temporal import TemporalConfig, TemporalTrainConfig


@dataclass(frozen=True)
class StageRef:
    """A checkpoint of an earlier stage: its best.pt (by validation P-II) or its last.pt."""

    stage: str
    checkpoint: Literal["best", "last"]

    def __str__(self) -> str:
        """The checkpoint's path in a preset's out-dir: "stretch2/best.pt"."""
        return f"{self.stage}/{self.checkpoint}.pt"


@dataclass(frozen=True)
class Stage:
    """One training run of a preset.

    train, model -- its whole configuration (out_dir, data_dir, threads, device and init_from are
    filled in when it runs); it stops at train.stop_step, else at train.iterations.
    init_from -- start from that checkpoint's weights at step 0, fresh optimisers and schedule.
    extends -- go on from that stage's last.pt with its whole state (weights, optimiser moments,
    random generators, step) along this stage's longer schedule: resuming it with --extend.
    Neither: from scratch.
    """

    name: str
    train: TrainConfig
    model: RepNetConfig
    init_from: StageRef | None = None
    extends: str | None = None

    def __post_init__(self) -> None:
        """Refuse a stage that starts two ways or stops on wall time."""
        if self.init_from is not None and self.extends is not None:
            raise ValueError(f"stage {self.name}: init_from or extends, not both")
        if self.train.max_minutes:
            raise ValueError(f"stage {self.name}: a preset stops on a step (stop_step), never on wall time")

    @property
    def stop(self) -> int:
        """The step at which the stage ends."""
        return min(self.train.iterations, self.train.stop_step or self.train.iterations)

    def parents(self) -> tuple[str, ...]:
        """The stages whose checkpoints this one starts from."""
        return tuple(name for name in (self.extends, self.init_from and self.init_from.stage) if name)

    def summary(self) -> str:
        """One line: steps, schedule and start."""
        steps = (
            f"{self.stop:,} steps"
            if self.stop == self.train.iterations
            else (f"{self.train.iterations:,}-step schedule stopped at step {self.stop:,}")
        )
        if self.extends:
            start = f"goes on from {self.extends}/last.pt (its whole state) from its step"
        elif self.init_from:
            start = f"from {self.init_from} at step 0"
        else:
            start = "from scratch"
        mode = "critic only, " if self.train.critic_only else ""
        return f"{self.name}: {mode}{steps}, lr {self.train.lr:g} {self.train.schedule}, {start}"


@dataclass(frozen=True)
class Preset:
    """A shipped model's recipe: generator stages in order, the critic's stage, and the export of
    export_from's generator with the critic stage's last.pt as its critic, and a plausibility
    output that ranks by `plausibility`: the pose density fitted by `density`, or the critic."""

    name: str
    description: str
    stages: tuple[Stage, ...]
    critic: Stage
    export_from: StageRef
    mirror_average: bool
    plausibility: Score = "density"
    density: DensityConfig = DensityConfig()

    def __post_init__(self) -> None:
        """Refuse a preset whose stages start from stages that do not run before them."""
        seen: set[str] = set()
        for stage in self.all_stages:
            if stage.name in seen or stage.name in ("", "export"):
                raise ValueError(f"preset {self.name}: stage name {stage.name!r} twice or reserved")
            unknown = [parent for parent in stage.parents() if parent not in seen]
            if unknown:
                raise ValueError(
                    f"preset {self.name}: stage {stage.name} starts from {unknown}, not before it"
                )
            seen.add(stage.name)
        if self.export_from.stage not in {stage.name for stage in self.stages}:
            raise ValueError(f"preset {self.name}: exports {self.export_from}, not one of its stages")
        if not self.critic.train.critic_only:
            raise ValueError(f"preset {self.name}: its critic stage {self.critic.name} is not critic_only")

    @property
    def all_stages(self) -> tuple[Stage, ...]:
        """The stages in the order they run: the generator's, then the critic's."""
        return (*self.stages, self.critic)

    def stage(self, name: str) -> Stage:
        """The stage of that name (KeyError naming the stages there are)."""
        for stage in self.all_stages:
            if stage.name == name:
                return stage
        raise KeyError(
            f"preset {self.name} has no stage {name!r}: {', '.join(s.name for s in self.all_stages)}"
        )


# repnet-h36m-v6, as run (tests/training/v6_commands_as_run.sh): seven stretches of the synthetic
# warm start with the bone prior, each on its own schedule, and v2's critic recipe.
_V6 = TrainConfig(
    inputs="gt+sh",
    seed=0,
    batch_size=256,
    schedule="cosine",
    bone_weight=3.0,
    val_size=4000,
    val_every=1000,
    log_every=50,
    checkpoint_every=2000,
    checkpoint_minutes=10.0,
)
_V6_MODEL = RepNetConfig(width=512)


def _warm_start(base: TrainConfig, lr: float, lr_decay: float, steps: int, **changes: Any) -> TrainConfig:
    """A stretch of synthetic warm start as long as its schedule: lr on a cosine down to lr * lr_decay
    over `steps`, with these other changes from base."""
    return replace(base, lr=lr, lr_decay=lr_decay, iterations=steps, warm_start_steps=steps, **changes)


_STRETCH_1 = _warm_start(_V6, 1e-3, 0.01, 60_000)
_STRETCH_2 = _warm_start(_V6, 1e-3, 0.01, 120_000)  # stretch 1's schedule, twice as long
# Half of the synthetic poses mirrored.
_STRETCH_3 = _warm_start(_V6, 3e-4, 0.0333, 100_000, mirror_prob=0.5, checkpoint_minutes=5.0)
# Synthetic pixel noise up to 20 px, most poses nearly clean: sigma = 20 px * u^3.
_STRETCH_4 = _warm_start(_STRETCH_3, 1e-4, 0.1, 30_000, synthetic_noise_px=20.0, synthetic_noise_power=3.0)
# u^4; the run as shipped stopped at step 40,300 of its 45,000-step schedule (on its wall-time limit).
_STRETCH_5 = _warm_start(_STRETCH_4, 5e-5, 0.02, 45_000, synthetic_noise_power=4.0, stop_step=40_300)
# Fewer occluded poses: 1-3 joints hidden in a quarter of them, not half.
_STRETCH_6 = replace(_STRETCH_5, stop_step=0, mask_prob=0.25)
# A restart at lr 1e-4 with turned limbs (N(0, 10 deg) about a random axis, in half of the poses).
_STRETCH_7 = _warm_start(_STRETCH_6, 1e-4, 0.01, 60_000, limb_turn_deg=10.0, limb_turn_prob=0.5)
# The plausibility critic, v2's recipe: a fresh critic against corrupted real poses, the generator
# unused (the run as shipped resumed another run's checkpoint and so began with its critic).
_CRITIC = TrainConfig(
    inputs="gt+sh",
    batch_size=256,
    lr=1e-4,
    schedule="constant",
    iterations=23_000,
    critic_only=True,
    critic_steps=1,
    critic_fakes="corrupted",
    val_every=1000,
    val_size=4000,
    log_every=50,
    checkpoint_every=1000,
)

REPNET_H36M_V6 = Preset(
    name="repnet-h36m-v6",
    description="the bundled model: seven stretches of synthetic warm start (~5 h on 2 CPU cores), "
    "then a critic against corrupted real poses; mirror-averaged export",
    stages=(
        Stage("stretch1", _STRETCH_1, _V6_MODEL),
        Stage("stretch2", _STRETCH_2, _V6_MODEL, extends="stretch1"),
        Stage("stretch3", _STRETCH_3, _V6_MODEL, init_from=StageRef("stretch2", "best")),
        Stage("stretch4", _STRETCH_4, _V6_MODEL, init_from=StageRef("stretch3", "best")),
        Stage("stretch5", _STRETCH_5, _V6_MODEL, init_from=StageRef("stretch4", "last")),
        Stage("stretch6", _STRETCH_6, _V6_MODEL, init_from=StageRef("stretch5", "last")),
        Stage("stretch7", _STRETCH_7, _V6_MODEL, init_from=StageRef("stretch6", "last")),
    ),
    critic=Stage("critic", _CRITIC, _V6_MODEL),
    export_from=StageRef("stretch7", "last"),
    mirror_average=True,
    plausibility="critic",
)
# repnet-h36m-v7: v6's generator and critic, plausibility by a pose density instead of the critic
# (it ranks the answers' errors better at every validation shift; docs/RESULTS.md). From the
# shipped v6 file: --seed-stage stretch7=v6.onnx --seed-stage critic=v6.onnx (docs/TRAINING.md).
REPNET_H36M_V7 = replace(
    REPNET_H36M_V6,
    name="repnet-h36m-v7",
    description="the bundled model: repnet-h36m-v6's generator and critic (seven stretches of synthetic "
    "warm start, ~5 h on 2 CPU cores, then a critic against corrupted real poses), plausibility by a "
    "pose density fitted to the training poses; mirror-averaged export",
    plausibility="density",
)

# repnet-h36m-nositting: a parent that never saw Sitting or SittingDown, for the adaptation benchmark's
# no-sitting shift (bench.adapt_h36m, issue 32): v6's last synthetic task (stretch7's noise, mirroring,
# occlusions and turned limbs) from scratch on stretch1's schedule cut to 40,000 steps, and v6's critic
# recipe cut to 3,000 steps; those actions are in no pool, validation set or pose density. About 40 min
# on one CPU thread (24 warm-start and 7 critic steps/s, and the export's density fit).
NO_SITTING = "Sitting,SittingDown"
REPNET_H36M_NOSITTING = Preset(
    name="repnet-h36m-nositting",
    description="a parent that never saw Sitting or SittingDown (bench.adapt_h36m --shift no-sitting): "
    "40,000 steps of v6's last synthetic task from scratch, 3,000 of its critic, pose density; ~40 min "
    "on one CPU thread",
    stages=(
        Stage("warm", _warm_start(_STRETCH_7, 1e-3, 0.01, 40_000, exclude_actions=NO_SITTING), _V6_MODEL),
    ),
    critic=Stage("critic", replace(_CRITIC, iterations=3_000, exclude_actions=NO_SITTING), _V6_MODEL),
    export_from=StageRef("warm", "last"),
    mirror_average=True,
)

# A few steps of every kind of stage on a tiny network, for the tests: a warm start, its extension,
# a stage from its best weights that stops early, the critic, the export.
_TINY = TrainConfig(
    inputs="gt+sh",
    batch_size=32,
    lr=1e-3,
    lr_decay=0.1,
    bone_weight=3.0,
    critic_steps=1,
    val_size=64,
    val_every=4,
    log_every=2,
    checkpoint_every=3,
)
_TINY_MODEL = RepNetConfig(width=32, critic_width=16, kcs_width=16)
_TINY_WARM = _warm_start(_TINY, 1e-3, 0.1, 6)
TINY = Preset(
    name="tiny",
    description="a few steps of every kind of stage on a tiny network (tests)",
    stages=(
        Stage("warm", _TINY_WARM, _TINY_MODEL),
        Stage("longer", _warm_start(_TINY, 1e-3, 0.1, 10), _TINY_MODEL, extends="warm"),
        Stage(  # its warm start ends at step 6: two adversarial steps, then the stop at step 8
            "turned",
            replace(_TINY_WARM, iterations=10, stop_step=8, mirror_prob=0.5, limb_turn_deg=10.0),
            _TINY_MODEL,
            init_from=StageRef("longer", "best"),
        ),
    ),
    critic=Stage(
        "critic",
        replace(
            _TINY,
            critic_only=True,
            critic_fakes="corrupted",
            schedule="constant",
            iterations=6,
        ),
        _TINY_MODEL,
    ),
    export_from=StageRef("turned", "last"),
    mirror_average=True,
    density=DensityConfig(frame_step=1, components=4, dims=8),
)

PRESETS: dict[str, Preset] = {
    preset.name: preset for preset in (REPNET_H36M_V7, REPNET_H36M_V6, REPNET_H36M_NOSITTING, TINY)
}


def get(name: str) -> Preset:
    """The preset of that name (KeyError naming the presets there are)."""
    if name not in PRESETS:
        raise KeyError(f"no preset {name!r}: {', '.join(PRESETS)}")
    return PRESETS[name]


@dataclass(frozen=True)
class TemporalPreset:
    """A shipped temporal model pair (repnet.train.temporal_train): the single-frame model whose answers
    they refine (a file of this repository), the synthetic clips, and one (model id, shape) per mode,
    each trained by `train`."""

    name: str
    description: str
    base_model: str
    base_model_id: str
    clips: ClipConfig
    train: TemporalTrainConfig
    models: tuple[tuple[str, TemporalConfig], ...]


REPNET_H36M_TEMPORAL_V1 = TemporalPreset(
    name="repnet-h36m-temporal-v1",
    description="causal and offline temporal models over repnet-h36m-v6's answers, 81 frames at 50 Hz",
    base_model="service/models/repnet-h36m.onnx",
    base_model_id="repnet-h36m-v6",
    clips=ClipConfig(draws=8, noise=ClipNoise(clean_prob=0.35)),
    train=TemporalTrainConfig(steps=3000, val_every=500),
    models=(
        ("repnet-h36m-temporal-causal-v1", TemporalConfig(mode="causal")),
        ("repnet-h36m-temporal-offline-v1", TemporalConfig(mode="offline")),
    ),
)
TINY_TEMPORAL = TemporalPreset(
    name="tiny-temporal",
    description="a few steps of small temporal models (tests)",
    base_model="service/models/repnet-h36m.onnx",
    base_model_id="repnet-h36m-v6",
    clips=ClipConfig(draws=1, noise=ClipNoise(clean_prob=0.5)),
    train=TemporalTrainConfig(steps=4, batch=2, outputs=8, val_every=2, checkpoint_every=2),
    models=(
        ("tiny-temporal-causal", TemporalConfig(mode="causal", widths=(3, 3), channels=16, causal_fit=5)),
        (
            "tiny-temporal-offline",
            TemporalConfig(mode="offline", widths=(3, 3), channels=16, smooth_sigma=1.0),
        ),
    ),
)
TEMPORAL_PRESETS: dict[str, TemporalPreset] = {p.name: p for p in (REPNET_H36M_TEMPORAL_V1, TINY_TEMPORAL)}


def temporal(name: str) -> TemporalPreset:
    """The temporal preset of that name (KeyError naming those there are)."""
    if name not in TEMPORAL_PRESETS:
        raise KeyError(f"no temporal preset {name!r}: {', '.join(TEMPORAL_PRESETS)}")
    return TEMPORAL_PRESETS[name]
