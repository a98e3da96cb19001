"""Frozen configuration dataclasses for the RepNet model and its training run."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RepNetConfig:
    """Network shape (Wandt & Rosenhahn 2019, Fig. 2 and 3)."""

    num_joints: int = 17
    width: int = 1000  # units of every generator layer
    num_blocks: int = 2  # residual blocks of two layers each, per generator branch
    # The authors' released code has a 100-unit pose path and a 1000-unit KCS path; the
    # previous default model had them the other way round (1000 / 100).
    critic_width: int = 100  # units of the critic's fully connected pose path
    kcs_width: int = 1000  # units of the layers after the KCS layer (paper figure: 100)
    leaky_slope: float = 0.01
    # Feed the visibility mask to the generator beside the normalised coordinates, so a
    # hidden joint is not mistaken for a joint at the centroid.
    visibility_input: bool = True
    # The authors' code: one trunk (Dense width and a residual block) feeds both branches, the
    # pose branch (num_blocks residual blocks, Dense width, then 3J) and the camera branch
    # (num_blocks residual blocks, then 6). False: two separate branches (the paper's figure).
    shared_trunk: bool = False


@dataclass(frozen=True)
class TrainConfig:
    """One training run.

    The defaults are an adversarial run from scratch (no warm start): batch 256, five critic
    updates per generator update that judge the last generator step's poses, Adam lr 1e-4 with
    betas (0.5, 0.9) on a cosine down to a tenth over 20,000 steps, Frobenius reprojection and
    camera losses, gradient-penalty weight 10. That is neither the paper's recipe (Wandt &
    Rosenhahn 2019: lr 0.001 with exponential decay) nor the authors' released script (batch 32,
    one critic update per generator update, Adam lr 1e-4 with betas (0.5, 0.9), L1 losses). A
    shipped model comes from a named preset (repnet.train.presets), which sets every field it needs.
    """

    data_dir: str = ""
    inputs: str = "gt"  # gt | sh | gt+sh
    out_dir: str = "runs/repnet"
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda
    threads: int = 0  # torch intra-op threads on the CPU; 0 = torch's default
    # torch.compile the generator: 15 % more samples/s in the warm start on this CPU
    # (bench.train_step --compile); the first steps wait for the compiler (~1 min).
    compile: bool = False
    iterations: int = 20000  # generator steps, warm start included; the schedule counts these
    max_minutes: float = 0.0  # stop (and checkpoint) after this wall time; 0 = no limit
    stop_step: int = 0  # stop (and checkpoint) at this step, schedule unchanged; 0 = at iterations
    batch_size: int = 256
    critic_steps: int = 5  # critic updates per generator update
    # The critic judges the poses of the last generator step instead of generating new ones
    # for each critic step: a generator pass costs four critic passes on the CPU.
    reuse_fakes: bool = True
    lr: float = 1e-4
    # The learning rate follows the step count alone (never the wall time), so a resumed run
    # continues the same schedule. cosine: from lr to lr * lr_decay over `iterations`;
    # step: divided by 10 after 1/4, 2/4 and 3/4 of them (the authors' epochs 5, 10, 15 of 20);
    # constant: lr throughout.
    schedule: str = "cosine"
    lr_decay: float = 0.1  # final learning rate as a fraction of lr (cosine)
    beta1: float = 0.5
    beta2: float = 0.9
    gp_weight: float = 10.0
    reprojection_weight: float = 1.0
    camera_weight: float = 1.0
    adversarial_weight: float = 1.0
    # Linear ramp of the adversarial weight from 0 over this many steps after the warm start,
    # so the critic learns before it pulls on a generator that already fits the 2D.
    adversarial_ramp: int = 0
    # fro: ||W - KX||_F and ||.||_F of the camera term (the paper's text); l1: the authors'
    # code, sum |W - KX| / 2J with per-joint weights and sum |entries| of the camera term.
    reprojection_norm: str = "fro"
    camera_norm: str = "fro"
    # Synthetic warm start: generator steps before the adversarial phase, supervised on the
    # unpaired training 3D poses projected through random cameras (never the real ones, and
    # never an image's 2D matched to its own 3D). 0 = the paper's recipe from scratch.
    warm_start_steps: int = 0
    # Weight of the same synthetic loss during the adversarial phase (0 = off).
    synthetic_weight: float = 0.0
    # Bone-length prior: mean |length - mean length of that bone over the real 3D poses| (m) of
    # the generated poses, all 16 bones; one person's bones keep their length and left equals
    # right, which the critic alone teaches slowly. 0 = off (the paper).
    bone_weight: float = 0.0
    # Temporal consistency on the 2D inputs' sequences (pool.triplets: three consecutive frames of
    # one person): mean |X(t-1) - 2 X(t) + X(t+1)| (m) of the answers turned into their cameras'
    # frames, `smoothness_batch` triplets a generator step of the adversarial phase. 0 = off.
    smoothness_weight: float = 0.0
    smoothness_batch: int = 64
    # Train the critic alone on the generator's poses, the generator frozen: a last stage that
    # fits the plausibility score to the generator that ships (resume from its checkpoint).
    critic_only: bool = False
    # What the critic-only stage takes for fakes: "generator" (its poses) or "corrupted" (real
    # poses with a limb stretched or shrunk, joints swapped or jittered). Against the generator
    # alone a critic learns the generator's signature (e.g. its too-regular bone lengths), not
    # what makes a pose implausible: garbage then scores as real. (Three more sources, the
    # generator's answers to noisy 2D, pairs and graded bones, were tried and ranked no better:
    # docs/RESULTS.md, "Plausibility"; they are gone with the code no preset used.)
    critic_fakes: str = "generator"
    # Weight of the synthetic camera's rotation as a target for the camera branch: mean |K / s -
    # the first two rows of the rotation from the template frame to the synthetic camera|. The
    # reprojection alone leaves K's rotation ~9 degrees off on validation (its P-I gap to P-II).
    camera_rotation_weight: float = 0.0
    # Which rotation that target is: "axis", into the synthetic camera's frame; "ray", into the
    # frame looking along the ray to the pelvis (what a centred input shows; synthetic.sample).
    camera_rotation_target: str = "axis"
    synthetic_noise_px: float = 8.0  # synthetic 2D gets N(0, sigma) px noise, sigma <= this per pose
    # sigma = synthetic_noise_px * u ** synthetic_noise_power, u ~ U(0, 1) per pose: 1 spreads sigma
    # evenly up to its largest value; 2 and 3 keep that largest value but make most poses cleaner
    # (mean sigma a third and a quarter of it instead of a half).
    synthetic_noise_power: float = 1.0
    # In this share of the synthetic poses, the 2D gets a real detector's error instead: the error
    # of a random Stacked-Hourglass detection of the training frames (detection minus projected
    # truth, in units of the pose's spread, times U(min, max)) and that detection's visibility. The
    # errors keep their shape: a wrist on the other wrist, a knee swapped, the head top off.
    detector_error_prob: float = 0.0
    detector_error_min: float = 0.6
    detector_error_max: float = 1.4
    # Share of the synthetic poses mirrored (left and right swapped) before they are seen.
    mirror_prob: float = 0.0
    # In limb_turn_prob of the synthetic poses, each forearm, upper arm, shin and thigh turns about
    # its joint by N(0, limb_turn_deg) degrees about a random axis (synthetic.turn_limbs): poses
    # near the training poses that the five training subjects never held. 0 = off.
    limb_turn_deg: float = 0.0
    limb_turn_prob: float = 0.5
    noise_px: float = 0.0  # std of Gaussian pixel noise added to the 2D inputs
    mask_prob: float = 0.5  # chance that a 2D sample has 1..mask_max random joints hidden
    mask_max: int = 3
    spine_mask_prob: float = 0.3  # extra chance to hide the spine, which detectors lack
    frame_step: int = 1  # use every n-th frame of the training sequences
    # Actions left out of the run altogether, comma-separated Human3.6M names ("Sitting,SittingDown";
    # "" none): their sequences give no 3D pose, no 2D input, no validation pose, and an export of
    # the run fits and calibrates its pose density without them (a parent that never saw them).
    exclude_actions: str = ""
    val_fraction: float = 0.1  # tail of each training sequence held out for validation
    val_size: int = 4000  # validation poses per evaluation
    # Also validate on the GT 2D validation poses plus N(0, this) px noise (fixed draw): "gt_noise".
    # 20 px here is the paper's sigma = 10 at its smaller image scale. 0 = off.
    val_noise_px: float = 20.0
    # Also validate on the GT 2D validation poses mirrored (image flipped about the principal
    # point, left and right swapped): "gt_mirror". The validation tail shares its people and
    # their habits with training; their mirror images are people the lifter has not seen.
    val_mirror: bool = True
    val_every: int = 500
    checkpoint_every: int = 500
    checkpoint_minutes: float = 10.0  # also checkpoint after this much wall time since the last
    log_every: int = 50
    # Start from the generator weights of this checkpoint (and its critic's, when the critic has
    # the same shape), at step 0 with fresh optimisers and schedule: ablations of the
    # adversarial phase that all start from one warm start. An exported .onnx works too
    # (repnet.train.checkpoint): a shipped model trains on when its run's checkpoints are gone.
    init_from: str = ""
