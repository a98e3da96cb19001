"""Frozen configuration dataclasses for the RepNet model and its training run."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RepNetConfig:
    """Network shape (Wandt & Rosenhahn 2019, Fig. 2 and 3)."""

    num_joints: int = 17
    width: int = 1000  # units of every generator layer
    num_blocks: int = 2  # residual blocks of two layers each, per generator branch
    critic_width: int = 1000  # units of the critic's fully connected pose path
    kcs_width: int = 100  # units of the layers after the KCS layer (paper: 100, authors' code: 1000)
    leaky_slope: float = 0.01
    # Feed the visibility mask to the generator beside the normalised coordinates, so a
    # missing joint is not mistaken for a joint at the centroid.
    visibility_input: bool = True


@dataclass(frozen=True)
class TrainConfig:
    """One training run. Defaults are those of the default model (docs/RESULTS.md)."""

    data_dir: str = ""
    inputs: str = "gt"  # gt | sh | gt+sh
    out_dir: str = "runs/repnet"
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda
    threads: int = 0  # torch intra-op threads on the CPU; 0 = torch's default
    iterations: int = 20000  # generator steps
    max_minutes: float = 0.0  # stop (and checkpoint) after this wall time; 0 = no limit
    batch_size: int = 256
    critic_steps: int = 5  # critic updates per generator update
    # The critic judges the poses of the last generator step instead of generating new ones
    # for each critic step: a generator pass costs four critic passes on the CPU.
    reuse_fakes: bool = True
    lr: float = 1e-4
    lr_decay: float = 0.1  # final learning rate as a fraction of lr (cosine)
    beta1: float = 0.5
    beta2: float = 0.9
    gp_weight: float = 10.0
    reprojection_weight: float = 1.0
    camera_weight: float = 1.0
    adversarial_weight: float = 1.0
    noise_px: float = 0.0  # std of Gaussian pixel noise added to the 2D inputs
    mask_prob: float = 0.5  # chance that a 2D sample has 1..mask_max random joints hidden
    mask_max: int = 3
    spine_mask_prob: float = 0.3  # extra chance to hide the spine, which detectors lack
    frame_step: int = 1  # use every n-th frame of the training sequences
    val_fraction: float = 0.1  # tail of each training sequence held out for validation
    val_size: int = 4000  # validation poses per evaluation
    val_every: int = 500
    checkpoint_every: int = 500
    log_every: int = 50
