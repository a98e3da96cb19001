"""Fixtures for training tests: a tiny synthetic dataset in the Human3.6M file layout."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from repnet.train import data, lineage
from repnet.train.config import TrainConfig

# A standing pose in the template frame (mm; x right, y down, z away from the camera).
STANDING = np.array(
    [
        [0, 0, 0],
        [-134, 0, 0],
        [-140, 440, 20],
        [-140, 870, 60],
        [134, 0, 0],
        [140, 440, 20],
        [140, 870, 60],
        [0, -230, 10],
        [0, -480, 0],
        [0, -580, -60],
        [0, -700, -10],
        [137, -431, 0],
        [200, -170, 0],
        [230, 70, -40],
        [-137, -431, 0],
        [-200, -170, 0],
        [-230, 70, -40],
    ],
    dtype=np.float64,
)


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera at centre looking at target, world Z up."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def synthetic_sequence(rng: np.random.Generator, frames: int) -> np.ndarray:
    """(frames, 17, 3) world poses (mm, Z up): the standing pose, perturbed and turned."""
    base = STANDING[:, [0, 2, 1]] * [1, 1, -1]  # template (x, y down, z) -> world (x, y, z up)
    angles = rng.uniform(-np.pi, np.pi, frames)
    c, s = np.cos(angles), np.sin(angles)
    rot = np.zeros((frames, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1
    poses = base + rng.normal(0, 25, (frames, 17, 3))
    poses = poses - poses[:, :1]
    return (poses @ rot.transpose(0, 2, 1) + [0, 0, 950]).astype(np.float32)


def camera_ring(
    subjects: tuple[str, ...],
    radius: float,
    height: float,
    first_angle: float,
    distortion: dict[str, list[float]] | None = None,
) -> dict[str, dict[str, dict[str, list[float]]]]:
    """cameras.json content: each subject's four cameras on a circle (mm) a quarter turn apart,
    looking at the person's chest; no lens distortion unless given ({"k": [3], "p": [2]})."""
    cameras: dict[str, dict[str, dict[str, list[float]]]] = {}
    for subject in subjects:
        cameras[subject] = {}
        for i, cam in enumerate(data.CAMERAS):
            a = first_angle + i * np.pi / 2
            centre = np.array([radius * np.cos(a), radius * np.sin(a), height])
            cameras[subject][cam] = {
                "R": look_at(centre, np.array([0.0, 0.0, 900.0])).tolist(),
                "T": centre.tolist(),
                "f": [1145.0, 1144.0],
                "c": [512.0, 515.0],
                **(distortion or {"k": [0.0, 0.0, 0.0], "p": [0.0, 0.0]}),
            }
    return cameras


def write_synthetic_h36m(folder: Path, seed: int = 0, frames: int = 120) -> Path:
    """Write poses_3d_{train,test}.npz, cameras.json and detections_sh_train.npz to folder."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    cameras = camera_ring(data.TRAIN_SUBJECTS + data.TEST_SUBJECTS, 4000.0, 1500.0, np.pi / 4)
    (folder / "cameras.json").write_text(json.dumps(cameras))
    train = {f"{s}/Walking": synthetic_sequence(rng, frames) for s in data.TRAIN_SUBJECTS}
    test = {
        f"{s}/{a}": synthetic_sequence(rng, frames // 2)
        for s in data.TEST_SUBJECTS
        for a in ("Walking", "Greeting")
    }
    np.savez(folder / "poses_3d_train.npz", **train)
    np.savez(folder / "poses_3d_test.npz", **test)
    detections = {}
    mpii_from_h36m = [3, 2, 1, 4, 5, 6, 0, 8, 9, 10, 16, 15, 14, 11, 12, 13]
    for key, seq in train.items():
        for cam_id in data.CAMERAS:
            cam = data.load_cameras(folder)[key.split("/")[0]][cam_id]
            px = data.project_to_pixels(seq, cam)[:, mpii_from_h36m]
            detections[f"{key}/{cam_id}"] = np.round(px + rng.normal(0, 3, px.shape)).astype(np.float32)
    np.savez(folder / "detections_sh_train.npz", **detections)
    return folder


# Test sequences and their frame counts: two takes of Walking, one misaligned sequence.
SEQUENCES = {"S9/Walking": 9, "S9/Walking 1": 7, "S9/Greeting": 6, "S11/Directions": 8, "S11/Eating 2": 5}
MISSING_DETECTIONS = "S11/Directions/54138969"  # as in the real data
MPII_FROM_H36M = [3, 2, 1, 4, 5, 6, 0, 8, 8, 10, 16, 15, 14, 11, 12, 13]  # data README


def write_test_h36m(folder: Path) -> Path:
    """poses_3d_{train,test}.npz and cameras.json of the test subjects, with distortion as in the
    real data: what repnet.train.evaluate reads."""
    rng = np.random.default_rng(3)
    folder.mkdir(parents=True, exist_ok=True)
    distortion = {"k": [-0.2, 0.24, -0.0015], "p": [-0.0009, -0.0002]}
    cameras = camera_ring(data.TEST_SUBJECTS, 4500.0, 1600.0, 0.3, distortion)
    (folder / "cameras.json").write_text(json.dumps(cameras))
    np.savez(folder / "poses_3d_train.npz", **{"S1/Walking": synthetic_sequence(rng, 4)})
    np.savez(folder / "poses_3d_test.npz", **{k: synthetic_sequence(rng, n) for k, n in SEQUENCES.items()})
    return folder


def write_detections(folder: Path, path: Path) -> Path:
    """MPII-16 detections from the GT projections, one camera sequence left out."""
    cameras = data.load_cameras(folder)
    detections = {}
    for key, world in data.load_poses(folder, "test").items():
        for cam_id in data.CAMERAS:
            if f"{key}/{cam_id}" != MISSING_DETECTIONS:
                px = data.project_to_pixels(world, cameras[key.split("/")[0]][cam_id])
                detections[f"{key}/{cam_id}"] = px[:, MPII_FROM_H36M]
    np.savez(path, **detections)
    return path


@pytest.fixture(scope="session", autouse=True)
def _cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Training's cache (file hashes) in a temporary folder, not the user's ~/.cache/repnet."""
    folder = tmp_path_factory.mktemp("repnet_cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(lineage.CACHE_ENV, str(folder))
        yield folder


@pytest.fixture(scope="session")
def h36m_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A test-subject folder for repnet.train.evaluate (write_test_h36m)."""
    return write_test_h36m(tmp_path_factory.mktemp("h36m_eval"))


@pytest.fixture(scope="session")
def synthetic_h36m(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_h36m(tmp_path_factory.mktemp("h36m"))


# Sequences of actions a run may leave out (TrainConfig.exclude_actions), each pose's right shin
# LONG_SHIN times its length: a bone no pose of the other actions has.
SITTING = ("S1/Sitting 1", "S5/SittingDown", "S8/Sitting")
LONG_SHIN = 2.5


@pytest.fixture(scope="session")
def sitting_h36m(synthetic_h36m: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """synthetic_h36m with SITTING sequences (3D and detections) beside its Walking ones."""
    folder = tmp_path_factory.mktemp("h36m_sitting")
    for name in ("cameras.json", "poses_3d_test.npz"):
        (folder / name).write_bytes((synthetic_h36m / name).read_bytes())
    rng = np.random.default_rng(5)
    sitting = {key: synthetic_sequence(rng, 60) for key in SITTING}
    for seq in sitting.values():
        seq[:, 3] = seq[:, 2] + LONG_SHIN * (seq[:, 3] - seq[:, 2])  # right knee -> right ankle
    np.savez(folder / "poses_3d_train.npz", **data.load_poses(synthetic_h36m, "train"), **sitting)
    cameras = data.load_cameras(folder)
    detections = data.load_detections(synthetic_h36m / data.SH_TRAIN_FILE)
    for key, seq in sitting.items():
        for cam_id, cam in cameras[key.split("/")[0]].items():
            detections[f"{key}/{cam_id}"] = data.project_to_pixels(seq, cam)[:, MPII_FROM_H36M]
    np.savez(folder / data.SH_TRAIN_FILE, **detections)
    return folder


def tiny_config(data_dir: Path, out: Path, iterations: int) -> TrainConfig:
    """A few quick steps on the synthetic dataset: batch 64, one critic step, validation every 20."""
    return TrainConfig(
        data_dir=str(data_dir),
        out_dir=str(out),
        inputs="gt+sh",
        iterations=iterations,
        batch_size=64,
        critic_steps=1,
        lr=1e-3,
        lr_decay=1.0,
        val_size=200,
        val_every=20,
        log_every=10,
        checkpoint_every=1000,
        threads=1,
    )


class Planted:
    """What a planted checkpoint carries: unpickling it calls Path.touch (any call could be made)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (Path.touch, (str(self.marker),))  # type: ignore[return-value]


def plant(path: Path, marker: Path) -> Path:
    """Overwrite the checkpoint at `path` with one whose unpickling touches `marker`."""
    torch.save({"step": 3, "trainer": Planted(marker)}, path)
    return path
