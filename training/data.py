"""Human3.6M loading: cameras, projection, template alignment, training pools and validation sets."""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from repnet.core import skeleton

TRAIN_SUBJECTS: tuple[str, ...] = ("S1", "S5", "S6", "S7", "S8")
TEST_SUBJECTS: tuple[str, ...] = ("S9", "S11")
CAMERAS: tuple[str, ...] = ("54138969", "55011271", "58860488", "60457274")
# S9 sequences whose ground truth is misaligned with the video (data README).
MISALIGNED: tuple[str, ...] = ("S9/Greeting", "S9/SittingDown 1", "S9/Waiting 1")

# A Stacked-Hourglass detection's joints, in MPII order: D = 16 (the model's J = 17).
MPII_JOINTS = 16
# MPII-16 (Stacked-Hourglass) joint feeding each Human3.6M-17 slot; -1: no source (masked).
MPII_TO_H36M: tuple[int, ...] = (6, 2, 1, 0, 3, 4, 5, -1, 7, 8, 9, 13, 14, 15, 12, 11, 10)

DATA_ENV = "REPNET_H36M_DIR"
CAMERAS_FILE = "cameras.json"
SH_TRAIN_FILE = "detections_sh_train.npz"  # Stacked-Hourglass detections of the training subjects


class DataNotFound(FileNotFoundError):
    """The Human3.6M directory is missing or incomplete."""


def resolve_data_dir(path: str | os.PathLike[str] | None = None) -> Path:
    """The Human3.6M directory: the argument, else $REPNET_H36M_DIR, else ../shared/data/h36m."""
    candidates: list[Path] = []
    if path:
        candidates.append(Path(path))
    elif os.environ.get(DATA_ENV):
        candidates.append(Path(os.environ[DATA_ENV]))
    else:
        repo = Path(__file__).resolve().parent.parent
        for folder in (repo.parent / "shared/data/h36m", Path.cwd().parent / "shared/data/h36m"):
            if folder.resolve() not in {c.resolve() for c in candidates}:  # the same folder once
                candidates.append(folder)
    for candidate in candidates:
        if (candidate / "poses_3d_train.npz").is_file():
            return candidate
    raise DataNotFound(
        f"Human3.6M data not found in {', '.join(map(str, candidates))}: pass --data-dir "
        f"or set {DATA_ENV} to the folder holding poses_3d_train.npz and cameras.json"
    )


@dataclass(frozen=True)
class Camera:
    """Human3.6M camera: X_cam = R (X_world - T), then pinhole with radial/tangential distortion."""

    R: np.ndarray  # (3, 3) world-to-camera rotation
    T: np.ndarray  # (3,) camera centre in world mm
    f: np.ndarray  # (2,) focal lengths in px
    c: np.ndarray  # (2,) principal point in px
    k: np.ndarray  # (3,) radial distortion
    p: np.ndarray  # (2,) tangential distortion


def load_cameras(data_dir: Path) -> dict[str, dict[str, Camera]]:
    """{subject: {camera id: Camera}} from cameras.json."""
    raw = json.loads((data_dir / CAMERAS_FILE).read_text())
    return {
        subject: {
            cam: Camera(**{key: np.asarray(val, dtype=np.float64) for key, val in params.items()})
            for cam, params in cams.items()
        }
        for subject, cams in raw.items()
    }


def load_poses(data_dir: Path, split: str) -> dict[str, np.ndarray]:
    """{"S1/Walking 1": (N, 17, 3) float32 world mm} for split "train" or "test"."""
    with np.load(data_dir / poses_file(split)) as npz:
        return {key: npz[key] for key in npz.files}


def action_name(sequence: str) -> str:
    """'Walking 1' -> 'Walking': the two takes of an action are reported together."""
    return re.sub(r"\s+\d+$", "", sequence)


def without_actions(poses: dict[str, np.ndarray], actions: str) -> dict[str, np.ndarray]:
    """`poses` ({"S1/Sitting 1": ...}) without the sequences of the comma-separated `actions`
    ("Sitting,SittingDown"; "" keeps every one). ValueError for an action the data lacks, naming
    those it has: a misspelt action would leave nothing out."""
    names = {name.strip() for name in actions.split(",") if name.strip()}
    present = {action_name(key.split("/", 1)[1]) for key in poses}
    if names - present:
        raise ValueError(
            f"expected actions among {', '.join(sorted(present))}, got {', '.join(sorted(names - present))}"
        )
    return {key: seq for key, seq in poses.items() if action_name(key.split("/", 1)[1]) not in names}


def load_detections(path: Path) -> dict[str, np.ndarray]:
    """{"S1/Walking 1/54138969": (N, D, 2) float32 px}, D = MPII_JOINTS in MPII order."""
    with np.load(path) as npz:
        return {key: npz[key] for key in npz.files}


def world_to_camera(x_world: np.ndarray, cam: Camera) -> np.ndarray:
    """(..., 3) world mm -> (..., 3) camera mm (x right, y down, z forward)."""
    return ((x_world - cam.T) @ cam.R.T).astype(np.float32)


def project_to_pixels(x_world: np.ndarray, cam: Camera) -> np.ndarray:
    """(..., 3) world mm -> (..., 2) distorted pixel coordinates (data README formula)."""
    x_cam = (x_world - cam.T) @ cam.R.T
    xy = x_cam[..., :2] / x_cam[..., 2:3]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    k1, k2, k3 = cam.k
    p1, p2 = cam.p
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    tan = p1 * y + p2 * x
    xd = x * (radial + tan) + p2 * r2
    yd = y * (radial + tan) + p1 * r2
    return np.stack([cam.f[0] * xd + cam.c[0], cam.f[1] * yd + cam.c[1]], axis=-1).astype(np.float32)


def mpii_to_h36m(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, D, 2) MPII detections, D = MPII_JOINTS -> ((N, 17, 2) points, (N, 17) visibility);
    the spine, which MPII lacks, hidden."""
    if points.shape[1:] != (MPII_JOINTS, 2):
        raise ValueError(f"expected (N, {MPII_JOINTS}, 2) MPII detections, got {points.shape}")
    index = np.asarray(MPII_TO_H36M)
    out = points[:, np.maximum(index, 0)].astype(np.float32)
    visible = np.broadcast_to((index >= 0).astype(np.float32), out.shape[:2]).copy()
    out[:, index < 0] = 0.0
    return out, visible


def procrustes(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Similarity that best maps source onto target, per pose (Umeyama 1991).

    source, target -- (N, P, 3) sets of P points; returns scale (N,), rotation (N, 3, 3) and
    translation (N, 3) with target ~= scale * source @ R.T + t.
    """
    mu_s, mu_t = source.mean(axis=1, keepdims=True), target.mean(axis=1, keepdims=True)
    s0, t0 = source - mu_s, target - mu_t
    cov = np.einsum("npi,npj->nij", t0, s0)  # (N, 3, 3)
    u, sig, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    fix = np.ones_like(sig)
    fix[:, -1] = d
    rot = u @ (fix[:, :, None] * vt)
    var_s = (s0**2).sum(axis=(1, 2))
    scale = (sig * fix).sum(axis=1) / np.maximum(var_s, 1e-12)
    trans = mu_t[:, 0] - scale[:, None] * np.einsum("nij,nj->ni", rot, mu_s[:, 0])
    return scale, rot, trans


def align_to_template(poses: np.ndarray) -> np.ndarray:
    """(N, 17, 3) poses -> the same poses rotated and scaled onto the template torso.

    The fit uses the shoulders and hips only (RepNet preprocessing); the pelvis ends at the
    origin, so only the articulation of the body is left.
    """
    poses = poses.astype(np.float64)
    torso = poses[:, skeleton.TORSO_JOINTS]
    target = np.broadcast_to(skeleton.TEMPLATE_TORSO, torso.shape)
    scale, rot, _ = procrustes(torso, target)
    rooted = poses - poses[:, skeleton.ROOT : skeleton.ROOT + 1]
    return (scale[:, None, None] * rooted @ rot.transpose(0, 2, 1)).astype(np.float32)


def hide_random_joints(
    points: np.ndarray, visible: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Copies of (N, J, 2) points and (N, J) visibility with `count` random non-root joints of
    every pose hidden (visibility 0, point 0): the occlusion rows of evaluation and validation."""
    non_root = np.array([j for j in range(points.shape[1]) if j != skeleton.ROOT])
    hidden = non_root[np.argsort(rng.random((len(points), len(non_root))), axis=1)[:, :count]]
    rows = np.arange(len(points))[:, None]
    points, visible = points.copy(), visible.copy()
    points[rows, hidden] = 0.0
    visible[rows, hidden] = 0.0
    return points, visible


@dataclass(frozen=True)
class TrainingPool:
    """What training draws from: M 3D poses and N 2D inputs of the training frames, never paired."""

    poses_aligned: np.ndarray  # (M, 17, 3) float32 template-aligned mm, pelvis at the origin
    points_2d: np.ndarray  # (N, 17, 2) float32 pixels
    visible: np.ndarray  # (N, 17) float32 in {0, 1}: the visibility of each 2D joint
    # poses_aligned before the alignment: world mm (Z up) with the pelvis at the origin; the
    # synthetic warm start projects these through random cameras.
    poses_world: np.ndarray | None = None
    # Real detector errors for synthetic 2D (TrainConfig.detector_error_prob): (E, J, 2) Stacked-
    # Hourglass detection minus projected truth over the pose's spread, and the detector's (E, J)
    # visibility, of the training frames (repnet.train.sequences.residuals).
    detector_errors: np.ndarray | None = None
    detector_visible: np.ndarray | None = None
    # (T, 3) rows of points_2d that are three consecutive frames of one person (the smoothness
    # term, TrainConfig.smoothness_weight); None: the inputs are not known to be sequences.
    triplets: np.ndarray | None = None


@dataclass(frozen=True)
class ValidationSet:
    """Held-out frames: N 2D inputs, each paired with its 3D pose in its camera's frame."""

    poses_camera: np.ndarray  # (N, 17, 3) float32 camera-frame mm
    points_2d: np.ndarray  # (N, 17, 2) float32 pixels
    visible: np.ndarray  # (N, 17) float32 in {0, 1}: the visibility of each 2D joint
    # (N, 2) focal lengths and principal points (px) of each pose's camera.
    focal: np.ndarray | None = None
    centre: np.ndarray | None = None


def sequence_split(n: int, val_fraction: float) -> int:
    """The first held-out frame of an n-frame sequence: its last val_fraction is validation."""
    return int(round(n * (1.0 - val_fraction)))


def poses_file(split: str) -> str:
    """The file of a split's 3D poses: poses_3d_train.npz or poses_3d_test.npz."""
    return f"poses_3d_{split}.npz"


def training_files(inputs: str) -> tuple[str, ...]:
    """The files of the data folder that build_training_sets reads for these inputs."""
    return (CAMERAS_FILE, poses_file("train")) + ((SH_TRAIN_FILE,) if "sh" in inputs.split("+") else ())


def build_training_sets(
    data_dir: Path, inputs: str, frame_step: int = 1, val_fraction: float = 0.1, exclude_actions: str = ""
) -> tuple[TrainingPool, dict[str, ValidationSet]]:
    """Training pools and validation sets from the training subjects S1 S5 S6 S7 S8.

    The last `val_fraction` of every sequence is held out for validation (contiguous, so
    neighbouring frames do not leak). Training 3D poses are template-aligned; training 2D
    poses come from every camera, by ground-truth projection ("gt"), Stacked-Hourglass
    detections ("sh") or both ("gt+sh"). Validation sets pair camera-frame 3D poses with
    2D inputs, one set per input kind. The sequences of exclude_actions (comma-separated action
    names, without_actions) are in neither.
    """
    kinds = inputs.split("+")
    if not kinds or any(kind not in ("gt", "sh") for kind in kinds):
        raise ValueError(f"inputs must be gt, sh or gt+sh, got {inputs!r}")
    cameras = load_cameras(data_dir)
    poses = without_actions(load_poses(data_dir, "train"), exclude_actions)
    detections = load_detections(data_dir / SH_TRAIN_FILE) if "sh" in kinds else {}
    train_3d: list[np.ndarray] = []
    train_2d: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"gt": [], "sh": []}
    val: dict[str, list[tuple[np.ndarray, ...]]] = {"gt": [], "sh": []}
    for key, seq in sorted(poses.items()):
        subject = key.split("/")[0]
        split = sequence_split(len(seq), val_fraction)
        train_3d.append(seq[:split:frame_step])
        for cam_id, cam in cameras[subject].items():
            gt_cam = world_to_camera(seq, cam)
            gt_px = project_to_pixels(seq, cam)
            ones = np.ones(gt_px.shape[:2], dtype=np.float32)
            focal = np.repeat(cam.f[None].astype(np.float32), len(seq), axis=0)
            centre = np.repeat(cam.c[None].astype(np.float32), len(seq), axis=0)
            if "gt" in kinds:
                train_2d["gt"].append((gt_px[:split:frame_step], ones[:split:frame_step]))
                val["gt"].append((gt_cam[split:], gt_px[split:], ones[split:], focal[split:], centre[split:]))
            det = detections.get(f"{key}/{cam_id}")
            if det is not None:
                n = min(len(det), len(seq))
                pts, vis = mpii_to_h36m(det[:n])
                train_2d["sh"].append((pts[: min(split, n) : frame_step], vis[: min(split, n) : frame_step]))
                val["sh"].append(
                    (gt_cam[split:n], pts[split:n], vis[split:n], focal[split:n], centre[split:n])
                )
    pairs = train_2d["gt"] + train_2d["sh"]
    world = np.concatenate(train_3d)
    train = TrainingPool(
        poses_aligned=align_to_template(world),
        points_2d=np.concatenate([p for p, _ in pairs]),
        visible=np.concatenate([v for _, v in pairs]),
        poses_world=(world - world[:, skeleton.ROOT : skeleton.ROOT + 1]).astype(np.float32),
    )
    val_sets = {}
    for kind, items in val.items():
        if items:
            poses_cam, points, visible, focal, centre = (np.concatenate(a) for a in zip(*items, strict=True))
            val_sets[kind] = ValidationSet(poses_cam, points, visible, focal=focal, centre=centre)
    return train, val_sets
