"""A broken model file stops `python -m service` at start, exit status 1, with a message naming the fault.

tests/service/test_main.py covers a missing --model-path and a truncated file (as a child
process); these are the other ways a model can be wrong.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from bench.server import ROOT
from service.__main__ import main
from service.config import BUNDLED_MODEL

onnx = pytest.importorskip("onnx")


def _empty(path: Path) -> None:
    path.write_bytes(b"")


def _not_onnx(path: Path) -> None:
    path.write_text("this is not a model\n" * 100)


def _wrong_io(path: Path) -> None:
    """A valid ONNX file that is not a lifting model: y = x."""
    h = onnx.helper
    graph = h.make_graph(
        [h.make_node("Identity", ["x"], ["y"])],
        "identity",
        [h.make_tensor_value_info("x", onnx.TensorProto.FLOAT, ["N", 3])],
        [h.make_tensor_value_info("y", onnx.TensorProto.FLOAT, ["N", 3])],
    )
    model = h.make_model(graph, opset_imports=[h.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))


def _with_metadata(change: Callable[[dict[str, str]], object]) -> Callable[[Path], None]:
    """The bundled model with its metadata changed."""

    def write(path: Path) -> None:
        model = onnx.load(str(BUNDLED_MODEL))
        meta = {p.key: p.value for p in model.metadata_props}
        change(meta)
        del model.metadata_props[:]
        onnx.helper.set_model_props(model, meta)
        onnx.save(model, str(path))

    return write


CASES = {
    "empty_file": (_empty, "cannot load model"),
    "not_onnx": (_not_onnx, "cannot load model"),
    "wrong_inputs_and_outputs": (_wrong_io, "expected inputs ['keypoints_2d', 'visibility'] and outputs"),
    "no_joint_names": (_with_metadata(lambda m: m.pop("joint_names")), "metadata 'joint_names' must be"),
    "joint_count_not_the_graph": (
        _with_metadata(lambda m: m.update(joint_names=json.dumps(json.loads(m["joint_names"])[:16]))),
        "expected keypoints_2d (N, 16, 2)",
    ),
    "other_skeleton": (
        _with_metadata(lambda m: m.update(joint_names=json.dumps(json.loads(m["joint_names"])[::-1]))),
        "are not the h36m17 joints",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_broken_model_fails_at_start_with_a_clear_message(
    case: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    write, message = CASES[case]
    path = tmp_path / f"{case}.onnx"
    write(path)
    assert main(["--model-path", str(path), "--http-port", "0", "--grpc-port", "0"]) == 1
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    text = record.getMessage()
    assert text.startswith("cannot start:") and str(path) in text and message in text, text
    assert record.exc_info is None  # a message, not a traceback


def test_model_path_from_the_environment_that_does_not_exist_exits_1(tmp_path: Path) -> None:
    absent = tmp_path / "absent" / "model.onnx"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "REPNET_MODEL_PATH": str(absent)}
    done = subprocess.run(
        [sys.executable, "-m", "service"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 1
    assert f"cannot start: model file not found: {absent}" in done.stderr + done.stdout
    assert "Traceback" not in done.stderr
