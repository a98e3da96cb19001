"""ONNX export: the contract (names, shapes, dynamic N, metadata) and torch/onnxruntime parity."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from repnet.cli.main import main as repnet
from repnet.core import skeleton
from repnet.train import checkpoint, data, export, metadata, train
from repnet.train import plausibility as plausibility_of
from repnet.train.config import RepNetConfig
from repnet.train.density import PoseDensity
from repnet.train.losses import bone_lengths
from repnet.train.model import Critic, Plausibility, RepNet
from repnet.train.plausibility import DensityConfig
from tests.training.conftest import LONG_SHIN, SITTING, STANDING, tiny_config


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory: pytest.TempPathFactory) -> tuple[RepNet, Path]:
    torch.manual_seed(0)
    generator = RepNet(RepNetConfig(width=32, critic_width=32, kcs_width=8)).eval()
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    meta = metadata.build_metadata(
        generator.config, "tiny-test", "python -m repnet.train.train --x", "synthetic", {"pa_mpjpe": 1.0}
    )
    export.export_onnx(generator, path, meta)
    return generator, path


def test_onnx_has_the_service_contract(tiny_onnx: tuple[RepNet, Path]) -> None:
    _, path = tiny_onnx
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    inputs = [(i.name, i.shape[1:]) for i in session.get_inputs()]
    assert inputs == [("keypoints_2d", [17, 2]), ("visibility", [17])]
    assert [o.name for o in session.get_outputs()] == ["pose_3d", "camera"]
    meta = session.get_modelmeta().custom_metadata_map
    assert json.loads(meta["joint_names"]) == list(skeleton.JOINT_NAMES)
    assert json.loads(meta["evaluation"]) == {"pa_mpjpe": 1.0}
    assert "research" in meta["licence"] and meta["model_id"] == "tiny-test"
    for n in (1, 5):
        points = np.full((n, 17, 2), 10, np.float32) + STANDING[:, :2].astype(np.float32)
        pose, camera = session.run(None, {"keypoints_2d": points, "visibility": np.ones((n, 17), np.float32)})
        assert pose.shape == (n, 17, 3) and camera.shape == (n, 2, 3)


def test_torch_and_onnxruntime_agree_on_real_poses(tiny_onnx: tuple[RepNet, Path]) -> None:
    generator, path = tiny_onnx
    try:
        data_dir = data.resolve_data_dir()
    except data.DataNotFound as err:
        pytest.skip(f"Human3.6M not present, parity on real poses skipped: {err}")
    cam = data.load_cameras(data_dir)["S9"]["54138969"]
    world = data.load_poses(data_dir, "test")["S9/Walking"][::50]
    points = data.project_to_pixels(world, cam)
    visible = np.ones(points.shape[:2], np.float32)
    visible[::3, 7] = 0
    assert export.check_parity(generator, path, points, visible) <= 0.01


def test_plausibility_output_is_the_calibrated_percentile_of_the_critic(tmp_path: Path) -> None:
    torch.manual_seed(1)
    config = RepNetConfig(width=32, critic_width=32, kcs_width=8)
    generator, critic = RepNet(config).eval(), Critic(config).eval()
    rng = np.random.default_rng(0)
    real = (STANDING[None] + rng.normal(0, 20, (400, 17, 3))).astype(np.float32)
    table = plausibility_of.calibrate(critic, real, levels=101)
    assert table.shape == (101,) and np.all(np.diff(table) >= 0)
    path = tmp_path / "plausible.onnx"
    entries = plausibility_of.metadata("critic", table, None)
    meta = metadata.build_metadata(config, "tiny-plausible", plausibility=entries)
    export.export_onnx(generator, path, meta, Plausibility(critic, torch.from_numpy(table)))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [o.name for o in session.get_outputs()] == ["pose_3d", "camera", "plausibility"]
    calibration = json.loads(session.get_modelmeta().custom_metadata_map["plausibility_calibration"])
    assert calibration["levels"] == 101 and len(calibration["scores_at_quantiles"]) == 101
    assert calibration["score"] == "critic"
    points = (rng.normal(0, 100, (64, 17, 2)) + 500).astype(np.float32)
    pose, _, plausibility = session.run(None, {"keypoints_2d": points, "visibility": np.ones((64, 17), "f4")})
    assert plausibility.shape == (64,) and np.all((plausibility >= 0) & (plausibility <= 1))
    # The same number as the critic's score looked up in the table by hand.
    with torch.no_grad():
        scores = critic(torch.from_numpy(pose) / 1000).numpy()
    np.testing.assert_allclose(plausibility, (scores[:, None] >= table[None]).mean(axis=1), atol=1e-6)
    # Real poses spread over [0, 1] around 0.5.
    with torch.no_grad():
        real_plausibility = Plausibility(critic, torch.from_numpy(table))(
            torch.from_numpy(real) / 1000
        ).numpy()
    assert 0.4 < real_plausibility.mean() < 0.6


def test_export_takes_the_critic_from_another_checkpoint(synthetic_h36m: Path, tmp_path: Path) -> None:
    """--critic-checkpoint: the generator of one run, the critic of another; plausibility by the
    pose density (the default) fitted to the training poses, calibrated on the validation poses."""
    tiny = RepNetConfig(width=32, critic_width=16, kcs_width=8)

    def run(name: str, seed: int) -> Path:
        config = dataclasses.replace(
            tiny_config(synthetic_h36m, tmp_path / name, 4), inputs="gt", batch_size=16, seed=seed
        )
        train.train(config, tiny, command=f"run {name}")
        return tmp_path / name / "last.pt"

    gen_ckpt, critic_ckpt = run("gen", 0), run("critic", 1)
    out = tmp_path / "mixed.onnx"
    export.main(
        [
            "--checkpoint",
            str(gen_ckpt),
            "--critic-checkpoint",
            str(critic_ckpt),
            "--output",
            str(out),
            "--data-dir",
            str(synthetic_h36m),
        ]
    )
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert [o.name for o in session.get_outputs()] == ["pose_3d", "camera", "plausibility", "critic"]
    meta = session.get_modelmeta().custom_metadata_map
    assert meta["train_command"] == "generator: run gen; critic: run critic"
    points = (np.random.default_rng(0).normal(0, 100, (8, 17, 2)) + 500).astype(np.float32)
    pose, _, plausible, critic_score = session.run(
        None, {"keypoints_2d": points, "visibility": np.ones((8, 17), "f4")}
    )
    critic = export.load_critic(torch.load(critic_ckpt, weights_only=False))
    with torch.no_grad():
        np.testing.assert_allclose(critic_score, critic(torch.from_numpy(pose) / 1000).numpy(), atol=1e-5)
    # The plausibility: the file's density, looked up in its table by hand, 0 outside the bone range.
    calibration = json.loads(meta["plausibility_calibration"])
    assert calibration["score"] == "density"
    table = np.asarray(calibration["scores_at_quantiles"], np.float32)
    state = checkpoint.load(out)
    assert state["critic"].keys() == critic.state_dict().keys()
    with torch.no_grad():
        density = PoseDensity.of_state(state["density"])(torch.from_numpy(pose) / 1000).numpy()
    bones = calibration["bone_length_range_mm"]
    lengths = bone_lengths(torch.from_numpy(pose)).numpy()  # mm
    inside = np.all((lengths >= bones["shortest"]) & (lengths <= bones["longest"]), axis=1)
    expected = (density[:, None] >= table[None]).mean(axis=1) * inside
    np.testing.assert_allclose(plausible, expected, atol=1e-6)
    generator, _ = export.load_generator(gen_ckpt)
    assert export.check_parity(generator, out, points, np.ones((8, 17), np.float32)) <= 0.01


def test_a_mirror_averaged_export_keeps_the_contract_and_answers_mirrors_with_mirrors(tmp_path: Path) -> None:
    torch.manual_seed(0)
    generator = RepNet(RepNetConfig(width=32, critic_width=32, kcs_width=8)).eval()
    path = tmp_path / "mirror.onnx"
    meta = metadata.build_metadata(generator.config, "m", mirror_average=True)
    export.export_onnx(generator, path, meta, None, mirror_average=True)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert json.loads(session.get_modelmeta().custom_metadata_map["mirror_average"]) is True
    rng = np.random.default_rng(1)
    points = (STANDING[None, :, :2] * 0.3 + 400 + rng.normal(0, 8, (6, 17, 2))).astype(np.float32)
    visible = np.ones((6, 17), np.float32)
    visible[2, [5, 12]] = 0
    assert export.check_parity(generator, path, points, visible, mirror_average=True) <= 0.01
    swap = list(skeleton.MIRROR)
    mirrored = points[:, swap].copy()
    mirrored[..., 0] = 1000.0 - mirrored[..., 0]
    pose, camera = session.run(None, {"keypoints_2d": points, "visibility": visible})
    pose_m, camera_m = session.run(None, {"keypoints_2d": mirrored, "visibility": visible[:, swap].copy()})
    np.testing.assert_allclose(pose_m, pose[:, swap] * [-1, 1, 1], atol=1e-2)
    np.testing.assert_allclose(camera_m, camera * [[1, -1, -1], [-1, 1, 1]], atol=1e-7, rtol=1e-4)
    # The plain export of the same generator is a different graph: it has no such symmetry.
    plain = tmp_path / "plain.onnx"
    export.export_onnx(generator, plain, metadata.build_metadata(generator.config, "p"))
    plain_meta = ort.InferenceSession(str(plain)).get_modelmeta().custom_metadata_map
    assert json.loads(plain_meta["mirror_average"]) is False


def test_a_pose_with_a_bone_no_human_has_scores_zero_whatever_the_critic_says() -> None:
    torch.manual_seed(0)
    critic = Critic(RepNetConfig(critic_width=16, kcs_width=8)).eval()
    rng = np.random.default_rng(0)
    real = (STANDING[None] + rng.normal(0, 10, (200, 17, 3))).astype(np.float32)
    bones = plausibility_of.bone_range(real)
    lengths = bone_lengths(torch.from_numpy(real) / 1000).numpy()
    np.testing.assert_allclose(bones[1], lengths.max(axis=0) * plausibility_of.BONE_MARGIN, rtol=1e-6)
    # A critic that extrapolates: the bigger the pose, the higher it scores (what a trained one
    # can do far from the real poses).
    critic.forward = lambda pose: pose.abs().sum(dim=(1, 2))  # type: ignore[method-assign]
    table = plausibility_of.calibrate(critic, real, levels=101)
    giant = real[:4].copy()
    giant[:, 13] = giant[:, 12] + (giant[:, 13] - giant[:, 12]) * 4  # a forearm 4x as long
    poses = torch.from_numpy(np.concatenate([real[:4], giant]) / 1000)
    unguarded = Plausibility(critic, torch.from_numpy(table))(poses).numpy()
    guarded = Plausibility(critic, torch.from_numpy(table), torch.from_numpy(bones))(poses).numpy()
    assert np.all(unguarded[4:] == 1.0)
    np.testing.assert_array_equal(guarded[:4], unguarded[:4])  # real poses keep their score
    assert np.all(guarded[4:] == 0.0)


def test_a_run_without_some_actions_exports_a_parent_whose_density_never_saw_them_and_adapt_takes_it(
    synthetic_h36m: Path, sitting_h36m: Path, tmp_path: Path
) -> None:
    """The export reads the run's exclude_actions: the density and its calibration are those of the
    data without the sitting sequences, and `repnet adapt` adapts the file on those sequences' 2D."""
    tiny, density = RepNetConfig(width=32, critic_width=16, kcs_width=8), DensityConfig(1, 4, 8)
    config = dataclasses.replace(
        tiny_config(sitting_h36m, tmp_path / "run", 4),
        inputs="gt",
        batch_size=16,
        exclude_actions="Sitting,SittingDown",
    )
    train.train(config, tiny, command="run")
    parent = tmp_path / "nositting.onnx"
    export.export_model(
        tmp_path / "run" / "last.pt", parent, density=density, mirror_average=True, data_dir=str(sitting_h36m)
    )
    meta = checkpoint.read_metadata(parent)
    assert (
        meta["training_data"]
        == "Human3.6M S1 S5 S6 S7 S8 without the actions Sitting,SittingDown, 2D inputs: gt"
    )
    assert checkpoint.load(parent)["train_config"] == {
        "inputs": "gt",
        "exclude_actions": "Sitting,SittingDown",
    }
    critic = export.load_critic(checkpoint.load(tmp_path / "run" / "last.pt"))
    _, _, without = export.calibrated_plausibility(critic, density, synthetic_h36m, 0.1)
    assert meta["plausibility_calibration"] == without["plausibility_calibration"]
    longest = json.loads(meta["plausibility_calibration"])["bone_length_range_mm"]["longest"]
    shin = skeleton.BONES.index((2, 3))  # right knee -> right ankle, LONG_SHIN times longer when sitting
    assert longest[shin] < np.linalg.norm(STANDING[3] - STANDING[2]) * LONG_SHIN
    # The parent adapted on the sitting sequences' GT 2D, as bench.adapt_h36m --shift no-sitting does.
    cameras = data.load_cameras(sitting_h36m)
    poses = data.load_poses(sitting_h36m, "train")
    seen = [data.project_to_pixels(poses[k], cameras[k.split("/")[0]][data.CAMERAS[0]]) for k in SITTING]
    np.savez(tmp_path / "sitting.npz", keypoints=np.concatenate(seen), format="h36m17")
    out = tmp_path / "adapted.onnx"
    command = ["adapt", str(tmp_path / "sitting.npz"), "-o", str(out), "--model", str(parent), "--steps", "2"]
    command += ["--force", "--threads", "1", "--prior-poses", "2000", "--run-dir", str(tmp_path / "adapt")]
    assert repnet(command) == 0
    assert checkpoint.read_metadata(out)["training_data"].startswith(meta["training_data"])
