"""A preset's whole chain: every stage, an interruption and its resume, the export, and the
export -> service contract (the tiny model loads and lifts through repnet.runtime.lifter.Lifter)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from repnet.runtime.lifter import Lifter
from repnet.train import chain, checkpoint, presets, train
from repnet.train.trainer import Terms, Trainer
from tests.training.conftest import STANDING


def _run(out: Path, data_dir: Path, *extra: str) -> None:
    train.main(
        ["--preset", "tiny", "--out-dir", str(out), "--threads", "1", "--data-dir", str(data_dir), *extra]
    )


def _interrupting(after_calls: int) -> Callable[[Trainer, int], Terms]:
    """A synthetic_step that raises KeyboardInterrupt on its after_calls-th call, as a Ctrl-C would."""
    real = Trainer.synthetic_step
    calls = []

    def step(self: Trainer, step: int) -> Terms:
        calls.append(step)
        if len(calls) == after_calls:
            raise KeyboardInterrupt
        return real(self, step)

    return step


def _weights(path: Path) -> dict[str, Any]:
    state = checkpoint.load(path)
    return {f"generator.{k}": v for k, v in state["generator"].items()} | {
        f"critic.{k}": v for k, v in state["critic"].items()
    }


def test_the_tiny_preset_runs_its_chain_resumes_bit_for_bit_and_its_model_lifts_through_the_service(
    synthetic_h36m: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    _run(whole, synthetic_h36m)
    tiny = presets.get("tiny")
    for stage in tiny.all_stages:
        assert json.loads((whole / stage.name / chain.DONE).read_text())["step"] == stage.stop
    # Warm start 6 steps, then its extension interrupted at step 7, before its first checkpoint
    # (checkpoint_every 3: step 9); then, run again, "turned" at its step 5, after its step-3 one.
    for calls in (6 + 2, 4 + 6):
        with monkeypatch.context() as patch:
            patch.setattr(Trainer, "synthetic_step", _interrupting(calls))
            with pytest.raises(KeyboardInterrupt):
                _run(parts, synthetic_h36m)
        if calls == 6 + 2:
            assert not (parts / "longer" / "last.pt").exists()
    assert {p.name for p in parts.iterdir() if (p / chain.DONE).is_file()} == {"warm", "longer"}
    assert torch.load(parts / "turned" / "last.pt", weights_only=False)["step"] == 3
    done_before = {name: (parts / name / chain.DONE).stat().st_mtime_ns for name in ("warm", "longer")}
    _run(parts, synthetic_h36m)
    assert {name: (parts / name / chain.DONE).stat().st_mtime_ns for name in done_before} == done_before
    # The same weights as the chain never interrupted, stage by stage and in the exported model.
    for stage in tiny.all_stages:
        for name, value in _weights(whole / stage.name / "last.pt").items():
            assert torch.equal(value, _weights(parts / stage.name / "last.pt")[name]), (stage.name, name)
    model = parts / "tiny.onnx"
    for name, value in _weights(whole / "tiny.onnx").items():
        assert torch.equal(value, _weights(model)[name]), name

    lifter = Lifter.load(model)
    rng = np.random.default_rng(0)
    keypoints = (STANDING[None, :, :2] * 0.3 + 500 + rng.normal(0, 5, (4, 17, 2))).astype(np.float32)
    visibility = np.ones((4, 17), np.float32)
    visibility[1, 5] = 0
    prediction = lifter.lift(keypoints, visibility)
    assert prediction.pose_3d.shape == (4, 17, 3) and prediction.camera.shape == (4, 2, 3)
    assert prediction.plausibility is not None and prediction.plausibility.shape == (4,)
    assert np.isfinite(prediction.pose_3d).all()
    meta = lifter.info.metadata
    assert lifter.info.model_id == "tiny"
    for value in meta.values():  # nothing of this machine's paths in what /v1/model shows
        assert (
            str(tmp_path) not in value and str(synthetic_h36m) not in value and str(Path.home()) not in value
        )
    lineage = json.loads(meta["lineage"])
    assert [s["stage"] for s in lineage["generator"]] == ["warm", "longer", "turned"]
    assert [s["stage"] for s in lineage["critic"]] == ["critic"]
    turned = lineage["generator"][-1]
    assert turned["parent"]["how"] == "init_from" and turned["parent"]["path"] == "longer/best.pt"
    assert [entry["step"] for entry in turned["resumed"]] == [3]
    assert lineage["generator"][1]["parent"]["how"] == "extend"
    assert lineage["export"]["generator"]["path"] == "turned/last.pt"
    assert lineage["export"]["critic"]["path"] == "critic/last.pt"
    assert "--out-dir ." in lineage["export"]["command"]
    # The extension's history is the whole schedule's, as the run as shipped kept it.
    history = [
        json.loads(line)["step"] for line in (parts / "longer" / "history.jsonl").read_text().splitlines()
    ]
    assert history == [2, 4, 6, 8, 10]


def test_a_stage_waits_for_the_stages_it_starts_from_and_the_preset_for_its_own_flags(
    synthetic_h36m: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(chain.StageNotReady, match="turned starts from longer"):
        _run(tmp_path, synthetic_h36m, "--stage", "turned")
    _run(tmp_path, synthetic_h36m, "--stage", "warm")
    assert (tmp_path / "warm" / chain.DONE).is_file() and not (tmp_path / "tiny.onnx").exists()
    with pytest.raises(SystemExit):
        _run(tmp_path, synthetic_h36m, "--lr", "0.1")
    assert "only --out-dir, --threads, --device, --data-dir go with it, got --lr" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _run(tmp_path, synthetic_h36m, "--stage", "nope")
    assert "no stage 'nope'" in capsys.readouterr().err
    # A stage done under another configuration (the preset edited since) is not taken for done.
    done = tmp_path / "warm" / chain.DONE
    record = json.loads(done.read_text())
    record["train_config"]["lr"] = 0.5
    done.write_text(json.dumps(record))
    with pytest.raises(checkpoint.ConfigChanged, match="lr: 0.5 -> 0.001"):
        _run(tmp_path, synthetic_h36m, "--stage", "longer")


def test_list_presets_shows_each_stage_and_the_export(capsys: pytest.CaptureFixture[str]) -> None:
    train.main(["--list-presets"])
    out = capsys.readouterr().out
    assert "stretch5: 45,000-step schedule stopped at step 40,300" in out
    assert "stretch2: 120,000 steps, lr 0.001 cosine, goes on from stretch1/last.pt" in out
    assert "export: stretch7/last.pt with critic/last.pt's critic, mirror-averaged" in out


def test_a_chain_goes_on_from_a_seeded_stage_such_as_a_shipped_model(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    whole, seeded = tmp_path / "whole", tmp_path / "seeded"
    _run(whole, synthetic_h36m)
    shipped = whole / "tiny.onnx"
    with pytest.raises(ValueError, match="warm is extended by a later stage"):
        _run(seeded, synthetic_h36m, "--seed-stage", f"warm={shipped}")
    _run(seeded, synthetic_h36m, "--seed-stage", f"longer={shipped}")
    assert not (seeded / "warm").exists()  # nothing before the seed was trained
    done = json.loads((seeded / "longer" / chain.DONE).read_text())
    assert done["seeded_from"]["path"] == "tiny.onnx"
    assert done["step"] == presets.get("tiny").stage("longer").stop
    # "turned" started from the seed's generator: its first weights are the shipped file's.
    seed_weights = checkpoint.load(shipped)["generator"]
    turned_init = checkpoint.load(seeded / "longer" / "best.pt")["generator"]
    assert all(torch.equal(turned_init[k], v) for k, v in seed_weights.items())
    lineage = json.loads(Lifter.load(seeded / "tiny.onnx").info.metadata["lineage"])
    stages = [s.get("stage") for s in lineage["generator"]]
    assert stages[-2:] == ["longer", "turned"]
    assert lineage["generator"][-2]["seeded_from"]["path"] == "tiny.onnx"
    assert lineage["generator"][-1]["parent"]["path"] == "longer/best.pt"
