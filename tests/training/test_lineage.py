"""Lineage: path-free commands, cached file hashes, and the stages a checkpoint and a model record."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

import onnx
import pytest
import torch

from repnet.train import checkpoint, data, export, lineage, train
from repnet.train.config import RepNetConfig
from tests.training.conftest import tiny_config

TINY = RepNetConfig(width=32, critic_width=16, kcs_width=8)


def test_path_free_writes_paths_inside_the_root_relative_and_the_others_as_basenames(tmp_path: Path) -> None:
    root = tmp_path / "runs"
    command = (
        f"python -m repnet.train.train --out-dir {root}/s7 --init-from {root}/s6/last.pt "
        f"--data-dir=/data/h36m --x ~/.cache/repnet/v5.onnx --inputs gt+sh --out {root} --y runs/rel"
    )
    assert lineage.path_free(command, root) == (
        "python -m repnet.train.train --out-dir s7 --init-from s6/last.pt --data-dir=h36m --x v5.onnx "
        "--inputs gt+sh --out . --y runs/rel"
    )
    assert (
        lineage.path_free("generator: run /a/gen; critic: run b", None) == "generator: run gen; critic: run b"
    )
    assert (
        lineage.command_line(["--out-dir", str(root / "a")], root)
        == "python -m repnet.train.train --out-dir a"
    )


def test_a_file_is_hashed_once_and_again_when_it_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "poses.npz"
    path.write_bytes(b"first")
    reads = []
    real = hashlib.sha256

    def counted(*args: Any) -> Any:
        reads.append(1)
        return real(*args)

    monkeypatch.setattr(lineage.hashlib, "sha256", counted)
    assert lineage.file_sha256(path) == real(b"first").hexdigest()
    assert lineage.file_sha256(path) == real(b"first").hexdigest()
    assert len(reads) == 1  # the second time from the cache
    path.write_bytes(b"second, longer")
    assert lineage.file_sha256(path) == real(b"second, longer").hexdigest()
    assert len(reads) == 2
    assert str(path) in (lineage.cache_dir() / "sha256.json").read_text()


def _lineage(path: Path) -> list[dict[str, Any]]:
    stages: list[dict[str, Any]] = torch.load(path, weights_only=False)["lineage"]
    return stages


def test_a_run_records_its_stage_and_a_resume_an_extension_and_an_init_from_add_to_it(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    first = dataclasses.replace(
        tiny_config(synthetic_h36m, tmp_path / "first", 4), inputs="gt", batch_size=16
    )
    train.train(dataclasses.replace(first, stop_step=2), TINY, command=f"train --out-dir {tmp_path}/first")
    (stage,) = _lineage(tmp_path / "first" / "last.pt")
    assert stage["command"] == "train --out-dir first" and stage["parent"] is None
    files = data.training_files("gt")
    assert stage["data"] == {
        name: hashlib.sha256((synthetic_h36m / name).read_bytes()).hexdigest() for name in files
    }
    assert stage["torch"] == torch.__version__ and (
        stage["git"]["commit"] is None or len(stage["git"]["commit"]) == 40
    )
    assert (stage["first_step"], stage["steps"]) == (0, 2)
    # Resumed in its own folder: the same stage, one resume more.
    stopped = hashlib.sha256((tmp_path / "first" / "last.pt").read_bytes()).hexdigest()
    train.train(first, TINY, resume="auto", command="again")
    (stage,) = _lineage(tmp_path / "first" / "last.pt")
    assert stage["resumed"] == [{"step": 2, "sha256": stopped, "command": "again"}] and stage["steps"] == 4
    # Extended from another folder: a stage of its own, whose parent is that checkpoint.
    longer = dataclasses.replace(first, out_dir=str(tmp_path / "longer"), iterations=6)
    train.train(longer, TINY, resume=tmp_path / "first" / "last.pt", extend=True, preset="p", stage="longer")
    old, new = _lineage(tmp_path / "longer" / "last.pt")
    assert old == stage
    assert (new["preset"], new["stage"], new["first_step"], new["steps"]) == ("p", "longer", 4, 6)
    sha = hashlib.sha256((tmp_path / "first" / "last.pt").read_bytes()).hexdigest()
    parent = {"how": "extend", "path": "first/last.pt", "sha256": sha, "command": "train --out-dir first"}
    assert new["parent"] == parent
    # Exported, then trained on from the model file: the model's stages come along.
    model = tmp_path / "model.onnx"
    export.export_model(
        tmp_path / "longer" / "last.pt", model, data_dir=str(synthetic_h36m), command="export"
    )
    meta = checkpoint.load(model)
    assert [s.get("stage") for s in meta["lineage"]["generator"]] == [None, "longer"]
    assert meta["lineage"]["critic"] is None  # the generator's checkpoint's own critic
    assert meta["lineage"]["export"]["generator"]["path"] == "longer/last.pt"
    arm = dataclasses.replace(first, out_dir=str(tmp_path / "arm"), init_from=str(model), iterations=1)
    train.train(arm, TINY)
    *before, own = _lineage(tmp_path / "arm" / "last.pt")
    assert before == meta["lineage"]["generator"]
    assert own["parent"]["how"] == "init_from" and own["parent"]["path"] == "model.onnx"
    assert own["parent"]["sha256"] == hashlib.sha256(model.read_bytes()).hexdigest()


def test_a_model_exported_from_a_checkpoint_without_lineage_records_its_command_without_paths(
    synthetic_h36m: Path, tmp_path: Path
) -> None:
    config = dataclasses.replace(tiny_config(synthetic_h36m, tmp_path / "old", 1), inputs="gt", batch_size=16)
    train.train(config, TINY)
    state = torch.load(tmp_path / "old" / "last.pt", weights_only=False)
    del state["lineage"]
    state["command"] = f"python -m repnet.train.train --out-dir {tmp_path}/old --data-dir {synthetic_h36m}"
    torch.save(state, tmp_path / "old" / "last.pt")
    model = tmp_path / "model.onnx"
    export.main(
        ["--checkpoint", str(tmp_path / "old" / "last.pt"), "--output", str(model)]
        + ["--data-dir", str(synthetic_h36m)]
    )
    meta = {p.key: p.value for p in onnx.load(str(model)).metadata_props}
    assert (
        meta["train_command"]
        == f"python -m repnet.train.train --out-dir old --data-dir {synthetic_h36m.name}"
    )
    found = json.loads(meta["lineage"])
    assert found["generator"] == [
        {"command": f"python -m repnet.train.train --out-dir old --data-dir {synthetic_h36m.name}"}
    ]
    assert found["export"]["command"].startswith(
        "python -m repnet.train.export --checkpoint old/last.pt --output "
    )
    assert all(str(tmp_path) not in value for value in meta.values())
