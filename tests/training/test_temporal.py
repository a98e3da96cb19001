"""The temporal model: its two forms agree, the exported window graph equals the training path at
every frame rate, causal answers ignore later frames, the export runs in onnxruntime, smoothing
lowers the acceleration error of a noisy clip, and the tiny preset trains, resumes and exports."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from repnet.core.errors import ModelLoadError
from repnet.runtime.lifter import Lifter
from repnet.runtime.loading import BUNDLED_MODEL, load_temporal_lifters
from repnet.runtime.temporal import TemporalLifter
from repnet.train import metrics, presets, temporal_train
from repnet.train.lineage import file_sha256
from repnet.train.temporal import GRID_FPS, TemporalConfig, TemporalGraph, TemporalNet, slots_needed
from repnet.train.temporal_data import clip_features, onnx_lift, padded_grid
from tests.training.conftest import STANDING

BUNDLED = Path(__file__).resolve().parents[2] / "service" / "models" / "repnet-h36m.onnx"


def _net(mode: str, seed: int = 0) -> TemporalNet:
    """A small net whose correction is not zero (a trained one's is not)."""
    torch.manual_seed(seed)
    net = TemporalNet(TemporalConfig(mode=mode, widths=(3, 3, 3), channels=32))
    torch.nn.init.normal_(net.out.weight, std=0.02)
    return net.eval()


def _moving_clip(frames: int, fps: float, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """A person turning slowly about the vertical: (n, J, 3) mm poses, (n, J, 2) px, visibility."""
    angles = np.linspace(0.0, 1.5, frames)
    c, s = np.cos(angles), np.sin(angles)
    turn = np.zeros((frames, 3, 3))
    turn[:, 0, 0], turn[:, 0, 2], turn[:, 1, 1], turn[:, 2, 0], turn[:, 2, 2] = c, s, 1.0, -s, c
    poses = (STANDING[None] @ turn.transpose(0, 2, 1)).astype(np.float32)
    points = (poses[..., :2] * 0.25 + [500.0, 450.0] + rng.normal(0, 0.5, (frames, 17, 2))).astype(np.float32)
    return poses, points, np.ones((frames, 17), np.float32)


@pytest.mark.parametrize("mode", ["causal", "offline"])
def test_the_dilated_and_the_strided_form_give_the_same_answers(mode: str) -> None:
    net = _net(mode)
    features = torch.randn(2, 105, net.config.window + 6)
    with torch.no_grad():
        whole = net(features)
        for start in (0, 3, 6):
            window = net(features[:, :, start : start + net.config.window], strided=True)
            torch.testing.assert_close(window[:, 0], whole[:, start], rtol=0, atol=1e-5)


@pytest.mark.parametrize("mode", ["causal", "offline"])
@pytest.mark.parametrize("fps", [25.0, 30.0, 50.0, 60.0])
def test_the_exported_window_graph_answers_as_the_training_path_at_every_rate(mode: str, fps: float) -> None:
    net = _net(mode)
    rng = np.random.default_rng(1)
    poses, points, visibility = _moving_clip(90, fps, rng)
    visibility[10:20, 3] = 0.0  # a hidden joint: its interpolation and mask
    frame = 45
    times = (np.arange(net.config.window) - net.config.target) / GRID_FPS + frame / fps
    with torch.no_grad():
        want = (
            net(torch.from_numpy(clip_features(poses, points, visibility, fps, times)).T[None])[0, 0] * 1000
        )
    slots = slots_needed(net.config, fps)
    first = frame - slots + 1 if mode == "causal" else frame - slots // 2
    index = np.clip(np.arange(first, first + slots), 0, len(poses) - 1)
    window = [torch.from_numpy(a[index])[None] for a in (poses, points, visibility)]
    with torch.no_grad():
        got = TemporalGraph(net)(*window, torch.tensor([fps]))[0]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-3)


def test_a_causal_answer_does_not_change_with_later_frames() -> None:
    net = _net("causal")
    rng = np.random.default_rng(2)
    poses, points, visibility = _moving_clip(60, 25.0, rng)
    grid = padded_grid(2 * 59 + 1, net.config)

    def answers(p: np.ndarray) -> np.ndarray:
        features = clip_features(p, points, visibility, 25.0, grid)
        with torch.no_grad():
            return net(torch.from_numpy(features).T[None])[0].numpy()

    before = answers(poses)
    changed = poses.copy()
    changed[31] += 80.0  # frame 31 is grid frame 62
    after = answers(changed)
    np.testing.assert_array_equal(after[: 2 * 30 + 1], before[: 2 * 30 + 1])  # up to frame 30's time
    assert np.abs(after[62] - before[62]).max() > 1e-3


def test_temporal_smoothing_lowers_the_acceleration_error_of_a_noisy_clip() -> None:
    """The bundled single-frame model on a clip with 6 px of detector noise, and both temporal
    models as they start training (their smoothing filter): less acceleration error, and no
    worse P-II."""
    rng = np.random.default_rng(3)
    poses, points, visibility = _moving_clip(100, 50.0, rng)
    noisy = (points + rng.normal(0.0, 6.0, points.shape)).astype(np.float32)
    single = onnx_lift(BUNDLED, 1)(noisy, visibility).astype(np.float64)
    truth = poses.astype(np.float64) - poses[:, :1]
    lone = metrics.acceleration_error(single, truth).mean()
    for mode in ("causal", "offline"):
        net = TemporalNet(TemporalConfig(mode=mode)).eval()
        features = clip_features(
            single.astype(np.float32), noisy, visibility, 50.0, padded_grid(100, net.config)
        )
        with torch.no_grad():
            smooth = net(torch.from_numpy(features).T[None])[0].numpy().astype(np.float64) * 1000
        assert metrics.acceleration_error(smooth, truth).mean() < 0.5 * lone, mode
        assert metrics.pa_mpjpe(smooth, truth) <= metrics.pa_mpjpe(single, truth) + 1.0, mode


def test_the_tiny_temporal_preset_trains_resumes_exports_and_loads_in_the_service(
    synthetic_h36m: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(Path(__file__).resolve().parents[2])  # the preset names the bundled model by its path
    preset = presets.temporal("tiny-temporal")
    args = ["--preset", preset.name, "--out-dir", str(tmp_path), "--data-dir", str(synthetic_h36m)]
    causal_id, causal = preset.models[0]
    # Interrupted in its third step, after its first checkpoint (step 2 of 4); run again, it resumes.
    real_terms = temporal_train.loss_terms
    calls: list[int] = []

    def stop_third(answers: torch.Tensor, truth: torch.Tensor) -> dict[str, torch.Tensor]:
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_terms(answers, truth)

    with monkeypatch.context() as patch:
        patch.setattr(temporal_train, "loss_terms", stop_third)
        with pytest.raises(KeyboardInterrupt):
            temporal_train.main([*args, "--model", causal_id])
    assert torch.load(tmp_path / causal_id / "last.pt", weights_only=False)["step"] == 2
    temporal_train.main(args)
    for model_id, config in preset.models:
        history = [
            json.loads(line) for line in (tmp_path / model_id / "history.jsonl").read_text().splitlines()
        ]
        assert [record["step"] for record in history] == [2, 4]
        assert {"sh25_accel", "sh50_pa_mpjpe", "gt25_bone_std"} <= set(history[-1])

        lifter = TemporalLifter.load(tmp_path / f"{model_id}.onnx")
        assert lifter.mode == config.mode and lifter.window == config.window
        assert json.loads(lifter.metadata["lineage"])["base_model"]["path"] == "repnet-h36m.onnx"
    # the same weights as one uninterrupted run of the causal model
    whole = tmp_path / "whole"
    temporal_train.main([*args[:2], "--out-dir", str(whole), *args[4:], "--model", causal_id])
    one = torch.load(whole / causal_id / "last.pt", weights_only=False)["net"]
    two = torch.load(tmp_path / causal_id / "last.pt", weights_only=False)["net"]
    assert all(torch.equal(one[k], two[k]) for k in one)
    assert causal.mode == "causal"


def test_a_refit_over_another_single_frame_model_names_it_and_runs_over_it_alone(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    mine = onnx.load(BUNDLED_MODEL)  # a single-frame model of another id (as `repnet adapt` writes one)
    for prop in mine.metadata_props:
        if prop.key == "model_id":
            prop.value = "mine"
    onnx.save(mine, base := tmp_path / "mine.onnx")
    preset = presets.temporal("tiny-temporal")
    causal_id = preset.models[0][0]
    args = ["--preset", preset.name, "--out-dir", str(tmp_path / "out"), "--data-dir", str(synthetic_h36m)]
    temporal_train.main([*args, "--model", causal_id, "--base-model", str(base)])
    refit = tmp_path / "out" / f"{causal_id}.onnx"
    meta = TemporalLifter.load(refit).metadata
    assert meta["base_model_id"] == "mine" and meta["base_model_sha256"] == file_sha256(base)
    assert json.loads(meta["lineage"])["base_model"]["path"] == "mine.onnx"
    lifter = Lifter.load(base)
    assert set(load_temporal_lifters(base, lifter, {"causal": refit})) == {"causal"}
    with pytest.raises(ModelLoadError, match="trained on the answers of the single-frame model"):
        load_temporal_lifters(BUNDLED_MODEL, Lifter.load(BUNDLED_MODEL), {"causal": refit})
