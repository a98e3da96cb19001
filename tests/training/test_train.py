"""A few training steps on tiny synthetic data: losses fall, checkpoints resume."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from repnet.train import augment, checkpoint, data, metrics, train, trainer, validation
from repnet.train.config import RepNetConfig, TrainConfig
from repnet.train.model import RepNet
from tests.training.conftest import STANDING, tiny_config

TINY = RepNetConfig(width=64, critic_width=64, kcs_width=16)
CPU = torch.device("cpu")


def _config(data_dir: Path, out: Path, iterations: int) -> TrainConfig:
    return dataclasses.replace(tiny_config(data_dir, out, iterations), critic_steps=2, checkpoint_every=20)


def _history(out: Path) -> list[dict[str, float]]:
    return [json.loads(line) for line in (out / "history.jsonl").read_text().splitlines()]


def test_training_steps_reduce_reprojection_and_camera_losses(synthetic_h36m: Path, tmp_path: Path) -> None:
    best = train.train(_config(synthetic_h36m, tmp_path, 80), TINY)
    history = _history(tmp_path)
    assert history[-1]["rep"] < 0.6 * history[0]["rep"]
    assert history[-1]["cam"] < history[0]["cam"]
    assert "val_gt_pa_mpjpe" in history[-1] and "val_sh_mpjpe" in history[-1]
    assert "val_gt_noise_pa_mpjpe" in history[-1]  # GT 2D + N(0, 20 px)
    assert "val_gt_mirror_pa_mpjpe" in history[-1]  # GT 2D mirrored
    state = torch.load(best, weights_only=False)
    assert state["model_config"]["width"] == 64


def test_resume_continues_from_the_checkpoint(synthetic_h36m: Path, tmp_path: Path) -> None:
    train.train(_config(synthetic_h36m, tmp_path, 20), TINY)
    train.train(_config(synthetic_h36m, tmp_path, 40), TINY, resume=tmp_path / "last.pt", extend=True)
    steps = [record["step"] for record in _history(tmp_path)]
    assert steps == [10, 20, 30, 40]
    assert torch.load(tmp_path / "last.pt", weights_only=False)["step"] == 40


def test_resume_refuses_a_changed_configuration_and_names_every_changed_field(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    config = _config(synthetic_h36m, tmp_path, 10)
    train.train(config, TINY)
    # The README's old critic stage: a finished generator run resumed as a critic-only run.
    critic = dataclasses.replace(config, critic_only=True, iterations=30, lr=5e-4)
    with pytest.raises(checkpoint.ConfigChanged) as refused:
        train.train(critic, dataclasses.replace(TINY, width=32), resume="auto")
    message = str(refused.value)
    for change in (
        "critic_only: False -> True",
        "iterations: 10 -> 30",
        "lr: 0.001 -> 0.0005",
        "width: 64 -> 32",
    ):
        assert change in message
    assert "4 field(s)" in message and "--extend" in message
    assert torch.load(tmp_path / "last.pt", weights_only=False)["step"] == 10  # untouched
    # --extend lets the schedule grow, nothing else, and never shrink below the checkpoint's step.
    with pytest.raises(checkpoint.ConfigChanged, match="critic_only: False -> True"):
        train.train(critic, TINY, resume="auto", extend=True)
    with pytest.raises(checkpoint.ConfigChanged, match="at step 10"):
        train.train(dataclasses.replace(config, iterations=5), TINY, resume="auto", extend=True)


def test_a_resumed_run_may_change_only_how_it_runs() -> None:
    stored = {"train_config": dataclasses.asdict(TrainConfig()), "model_config": dataclasses.asdict(TINY)}
    runtime = dict(
        max_minutes=5.0,
        stop_step=7,
        threads=2,
        device="cpu",
        compile=True,
        checkpoint_every=3,
        checkpoint_minutes=1.0,
        log_every=1,
        out_dir="elsewhere",
        data_dir="/data",
        init_from="x.pt",
    )
    assert set(runtime) == checkpoint.RESUME_MAY_CHANGE
    assert checkpoint.config_changes(stored, TrainConfig(**runtime), TINY) == []
    longer = TrainConfig(iterations=40000, warm_start_steps=40000)
    assert checkpoint.config_changes(stored, longer, TINY) == [
        "iterations: 20000 -> 40000",
        "warm_start_steps: 0 -> 40000",
    ]
    assert checkpoint.config_changes(stored, longer, TINY, extend=True) == []
    # A field the checkpoint predates counts as its default.
    del stored["train_config"]["limb_turn_deg"]
    assert checkpoint.config_changes(stored, TrainConfig(), TINY) == []
    assert checkpoint.config_changes(stored, TrainConfig(limb_turn_deg=10.0), TINY) == [
        "limb_turn_deg: 0.0 -> 10.0"
    ]


def _recipe(data_dir: Path, out: Path) -> TrainConfig:
    """Warm start for 15 steps (mirrored poses, turned limbs), then the adversarial phase with the
    synthetic term; the schedule runs over 40 steps whatever stretch of them one call trains."""
    return dataclasses.replace(
        _config(data_dir, out, 40),
        warm_start_steps=15,
        synthetic_weight=0.5,
        mirror_prob=0.5,
        limb_turn_deg=15.0,
        adversarial_ramp=10,
        schedule="step",
        log_every=5,
        val_every=1000,
        checkpoint_every=1000,
        max_minutes=0.0,
    )


def _weights(path: Path) -> dict[str, torch.Tensor]:
    state = torch.load(path, weights_only=False)
    return {f"g.{k}": v for k, v in state["generator"].items()} | {
        f"c.{k}": v for k, v in state["critic"].items()
    }


def test_a_resumed_run_continues_bit_for_bit(synthetic_h36m: Path, tmp_path: Path) -> None:
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    config = _recipe(synthetic_h36m, whole)
    train.train(config, TINY)
    # The same run stopped at step 25 (mid adversarial ramp, after the warm start) and resumed
    # with --resume auto: the schedule position comes from the step count in the checkpoint.
    stopped = dataclasses.replace(config, out_dir=str(parts), stop_step=25)
    train.train(stopped, TINY)
    assert torch.load(parts / "last.pt", weights_only=False)["step"] == 25
    # A record written after the checkpoint by the interrupted run is dropped on resume.
    with (parts / "history.jsonl").open("a") as history:
        history.write(json.dumps({"step": 30, "rep": -1.0}) + "\n")
    train.train(dataclasses.replace(config, out_dir=str(parts)), TINY, resume="auto")
    assert _history(parts) == [
        {**r, "minutes": p["minutes"]} for r, p in zip(_history(whole), _history(parts), strict=True)
    ]
    for name, value in _weights(whole / "last.pt").items():
        assert torch.equal(value, _weights(parts / "last.pt")[name]), name


def test_the_mirrored_validation_set_is_the_mirror_image_seen_by_the_same_camera() -> None:
    rng = np.random.default_rng(0)
    poses = (STANDING[None] + rng.normal(0, 40, (5, 17, 3)) + [100, -200, 4500]).astype(np.float32)
    focal = np.array([[1145.0, 1144.0]] * 5, np.float32)
    centre = np.array(
        [[512.0, 515.0], [500.0, 500.0], [480.0, 520.0], [512.0, 515.0], [505.0, 498.0]], np.float32
    )

    def project(camera_mm: np.ndarray) -> np.ndarray:
        return (focal[:, None] * camera_mm[..., :2] / camera_mm[..., 2:3] + centre[:, None]).astype(
            np.float32
        )

    visible = np.ones((5, 17), np.float32)
    visible[1, 13] = 0
    val = data.ValidationSet(poses, project(poses), visible, focal=focal, centre=centre)
    mirrored = validation.mirrored(val)
    np.testing.assert_allclose(mirrored.points_2d, project(mirrored.poses_camera), atol=1e-3)
    assert mirrored.visible[1, 16] == 0 and mirrored.visible[1, 13] == 1  # left wrist -> right wrist
    np.testing.assert_allclose(
        metrics.symmetry_error(mirrored.poses_camera), metrics.symmetry_error(poses), atol=1e-3
    )
    twice = validation.mirrored(mirrored)
    np.testing.assert_allclose(twice.points_2d, val.points_2d, atol=1e-3)
    np.testing.assert_array_equal(twice.poses_camera, val.poses_camera)


def test_resume_auto_starts_fresh_without_a_checkpoint_and_a_named_one_must_exist(tmp_path: Path) -> None:
    assert checkpoint.resolve_resume("auto", tmp_path) is None
    (tmp_path / "last.pt").write_bytes(b"")
    assert checkpoint.resolve_resume("auto", tmp_path) == tmp_path / "last.pt"
    assert checkpoint.resolve_resume(None, tmp_path) is None
    with pytest.raises(FileNotFoundError, match="no such checkpoint"):
        checkpoint.resolve_resume(tmp_path / "missing.pt", tmp_path)


def test_schedules_follow_the_step_count_alone() -> None:
    step = TrainConfig(lr=1e-3, iterations=200, schedule="step", max_minutes=1.0)
    assert [trainer.learning_rate(step, s) for s in (0, 49, 50, 100, 150, 199)] == pytest.approx(
        [1e-3, 1e-3, 1e-4, 1e-5, 1e-6, 1e-6]
    )
    cosine = TrainConfig(lr=1e-3, iterations=100, schedule="cosine", lr_decay=0.1)
    assert trainer.learning_rate(cosine, 0) == pytest.approx(1e-3)
    assert trainer.learning_rate(cosine, 50) == pytest.approx(0.55e-3)
    assert trainer.learning_rate(cosine, 100) == pytest.approx(1e-4)
    ramp = TrainConfig(warm_start_steps=10, adversarial_ramp=4, adversarial_weight=0.5)
    assert [trainer.adversarial_weight(ramp, s) for s in (0, 9, 10, 11, 13, 50)] == [
        0,
        0,
        0.125,
        0.25,
        0.5,
        0.5,
    ]


def test_visibility_augmentation_hides_joints_but_never_the_root() -> None:
    config = TrainConfig(mask_prob=1.0, mask_max=3, spine_mask_prob=0.0)
    gen = torch.Generator().manual_seed(0)
    visible = augment.augment_visibility(torch.ones(500, 17), config, gen)
    hidden = (visible == 0).sum(dim=1)
    assert hidden.min() >= 1 and hidden.max() <= 3
    assert torch.all(visible[:, 0] == 1)


def test_critic_only_stage_trains_the_critic_and_leaves_the_generator(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    first = _config(synthetic_h36m, tmp_path / "gen", 20)
    train.train(first, TINY)
    # A stage of its own: it starts from the generator's checkpoint (and its critic) at step 0.
    stage = dataclasses.replace(
        first,
        out_dir=str(tmp_path / "critic"),
        iterations=30,
        critic_only=True,
        init_from=str(tmp_path / "gen" / "last.pt"),
    )
    train.train(stage, TINY)
    before = torch.load(tmp_path / "gen" / "last.pt", weights_only=False)
    after = torch.load(tmp_path / "critic" / "last.pt", weights_only=False)
    assert after["step"] == 30
    assert all(torch.equal(v, after["generator"][k]) for k, v in before["generator"].items())
    assert any(not torch.equal(v, after["critic"][k]) for k, v in before["critic"].items())


def test_a_critic_stage_from_scratch_does_not_report_its_untrained_generator(
    synthetic_h36m: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    config = dataclasses.replace(_config(synthetic_h36m, tmp_path, 6), critic_only=True)
    with caplog.at_level(logging.INFO, logger=train.log.name):
        train.train(config, TINY)
    said = [r.getMessage() for r in caplog.records]
    assert not [m for m in said if m.startswith("final validation")]
    assert "critic only, from scratch: the generator was never trained, so it is not validated" in said


def test_init_from_takes_the_weights_but_starts_at_step_zero(synthetic_h36m: Path, tmp_path: Path) -> None:
    first = _config(synthetic_h36m, tmp_path / "warm", 20)
    train.train(first, TINY)
    source = torch.load(tmp_path / "warm" / "last.pt", weights_only=False)
    arm = dataclasses.replace(
        first, out_dir=str(tmp_path / "arm"), iterations=10, init_from=str(tmp_path / "warm" / "last.pt")
    )
    stopped = dataclasses.replace(arm, stop_step=1)
    train.train(stopped, TINY)
    after_one = torch.load(tmp_path / "arm" / "last.pt", weights_only=False)
    assert after_one["step"] == 1
    # One Adam step from the source weights: close to them, not equal, and the optimiser fresh.
    for name, value in source["generator"].items():
        assert torch.allclose(value, after_one["generator"][name], atol=2e-3), name
    assert after_one["opt_g"]["state"][0]["step"] == 1
    for name, value in source["critic"].items():  # same shape: the critic comes along
        assert torch.allclose(value, after_one["critic"][name], atol=2e-2), name
    # A critic of another shape starts fresh; the generator still comes from the checkpoint.
    wide = dataclasses.replace(TINY, critic_width=32)
    other = dataclasses.replace(arm, out_dir=str(tmp_path / "other"), stop_step=1)
    train.train(other, wide)
    state = torch.load(tmp_path / "other" / "last.pt", weights_only=False)
    assert state["critic"]["pose_path.0.weight"].shape[0] == 32
    for name, value in source["generator"].items():
        assert torch.allclose(value, state["generator"][name], atol=2e-3), name
    # --resume auto then continues the arm from its own checkpoint, not from init_from.
    train.train(arm, TINY, resume="auto")
    assert torch.load(tmp_path / "arm" / "last.pt", weights_only=False)["step"] == 10


def test_corrupted_poses_break_one_thing_and_keep_the_root() -> None:
    gen = torch.Generator().manual_seed(0)
    real = torch.from_numpy(np.repeat(STANDING[None] / 1000, 600, axis=0)).float()
    fake = augment.corrupt_poses(real, gen)
    assert torch.all(fake[:, 0] == 0)
    limbs = [(p, c) for p, c in metrics.LIMB_BONES]
    lengths = torch.stack([(fake[:, c] - fake[:, p]).norm(dim=1) for p, c in limbs], dim=1)
    true = torch.stack([(real[:, c] - real[:, p]).norm(dim=1) for p, c in limbs], dim=1)
    ratio = lengths / true
    changed = ((fake - real).norm(dim=2) > 1e-6).sum(dim=1)
    assert torch.all(changed >= 1)  # every corrupted pose differs from its source
    # About a third: exactly one limb 25-50 % longer or 20-40 % shorter, the others untouched.
    off = ((ratio > 1.249) & (ratio < 1.501)) | ((ratio > 0.599) & (ratio < 0.801))
    same = (ratio - 1).abs() < 1e-4
    one_limb = (off.sum(dim=1) == 1) & (same.sum(dim=1) == len(limbs) - 1)
    assert 0.25 < one_limb.float().mean() < 0.42


def test_a_critic_trained_against_corrupted_poses_ranks_a_real_pose_above_a_stretched_limb() -> None:
    from repnet.train.model import Plausibility
    from repnet.train.plausibility import calibrate

    rng = np.random.default_rng(0)
    n = 4000
    # Real poses: the standing pose turned about the vertical, with a few mm of jitter.
    angles = rng.uniform(-np.pi, np.pi, n)
    c, s = np.cos(angles), np.sin(angles)
    turn = np.zeros((n, 3, 3))
    turn[:, 0, 0], turn[:, 0, 2], turn[:, 1, 1], turn[:, 2, 0], turn[:, 2, 2] = c, s, 1, -s, c
    poses = (STANDING[None] @ turn.transpose(0, 2, 1) + rng.normal(0, 5, (n, 17, 3))).astype(np.float32)
    poses -= poses[:, :1]
    pool = data.TrainingPool(poses, np.zeros((1, 17, 2), np.float32), np.ones((1, 17), np.float32))
    config = TrainConfig(batch_size=128, critic_only=True, critic_fakes="corrupted", lr=1e-3)
    torch.manual_seed(0)
    critic_trainer = trainer.Trainer(
        config, TINY, pool, torch.device("cpu"), torch.Generator().manual_seed(0)
    )
    for step in range(300):
        critic_trainer.step(step)
    critic = critic_trainer.critic.eval()
    table = torch.from_numpy(calibrate(critic, poses[:2000]))
    plausibility = Plausibility(critic, table)
    test = torch.from_numpy(poses[2000:2100]) / 1000
    for parent, child in metrics.LIMB_BONES:
        broken = test.clone()
        moved = augment.SUBTREES[child]
        broken[:, moved] += 0.3 * (test[:, child] - test[:, parent])[:, None]
        with torch.no_grad():
            assert torch.all(plausibility(test) > plausibility(broken)), (parent, child)


def test_a_compiled_generator_trains_and_saves_plain_weights(synthetic_h36m: Path, tmp_path: Path) -> None:
    config = dataclasses.replace(_config(synthetic_h36m, tmp_path, 10), compile=True, warm_start_steps=10)
    train.train(config, TINY)
    state = torch.load(tmp_path / "last.pt", weights_only=False)
    assert state["step"] == 10
    assert not any(key.startswith("_orig_mod") for key in state["generator"])  # loadable by export
    plain = RepNet(TINY)
    plain.load_state_dict(state["generator"])


def test_training_validate_rescores_a_checkpoint_on_the_runs_own_validation_sets(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    from repnet.train import validate

    best = train.train(dataclasses.replace(_config(synthetic_h36m, tmp_path, 20), mirror_prob=0.5), TINY)
    record = next(r for r in reversed(_history(tmp_path)) if "val_gt_pa_mpjpe" in r)
    assert torch.load(best, weights_only=False)["step"] == record["step"]
    figures = validate.score(best, (False, True), str(synthetic_h36m))
    for kind, row in figures["plain"].items():
        for name, value in row.items():
            assert value == pytest.approx(record[f"val_{kind}_{name}"], abs=0.011), (kind, name)
    # The mirror-averaged graph answers a mirrored input with the mirrored answer, so it scores
    # the mirrored set as it scores the set itself; the plain graph does not.
    averaged = figures["mirror_average"]
    for name in ("pa_mpjpe", "mpjpe", "symmetry"):
        assert averaged["gt_mirror"][name] == pytest.approx(averaged["gt"][name], abs=0.02), name
    assert figures["plain"]["gt_mirror"]["pa_mpjpe"] != pytest.approx(
        figures["plain"]["gt"]["pa_mpjpe"], abs=0.02
    )


def test_validation_counts_the_answers_with_a_bone_no_person_has() -> None:
    rng = np.random.default_rng(0)
    truth = (STANDING[None] + rng.normal(0, 10, (8, 17, 3))).astype(np.float32)
    answers = truth.copy()
    answers[:2, 13] = answers[:2, 12] + (answers[:2, 13] - answers[:2, 12]) * 4  # forearm 4x as long

    class Fixed(torch.nn.Module):
        def forward(self, points: torch.Tensor, visible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            camera = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).expand(len(points), 2, 3)
            return torch.from_numpy(answers) / 1000, camera

    points = np.ascontiguousarray(truth[..., :2])
    val = data.ValidationSet(truth, points, np.ones((8, 17), np.float32))
    figures = validation.validate(Fixed(), val, torch.device("cpu"))  # type: ignore[arg-type]
    assert figures["wild_pct"] == 25.0
    assert figures["pa_mpjpe"] > 0


def test_an_unknown_critic_fake_source_is_refused(synthetic_h36m: Path) -> None:
    pool, _ = data.build_training_sets(synthetic_h36m, "gt", 1, 0.1)
    with pytest.raises(ValueError, match="critic_fakes must be one of generator, corrupted"):
        trainer.Trainer(TrainConfig(critic_fakes="real"), TINY, pool, CPU, torch.Generator().manual_seed(0))
