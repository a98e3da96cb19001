"""A broken model file stops `repnet serve` at start, exit status 1, with a message naming the fault.

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

import numpy as np
import pytest

from bench.server import ROOT
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.server.app import main

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


def _weights_overwritten(dtypes: tuple[type, ...]) -> Callable[[Path], None]:
    """The bundled model with every initializer of these dtypes overwritten with 0xFF bytes (NaN
    for floats): a valid ONNX file that loads but cannot answer."""

    def write(path: Path) -> None:
        model = onnx.load(str(BUNDLED_MODEL))
        for tensor in model.graph.initializer:
            array = onnx.numpy_helper.to_array(tensor)
            if array.dtype.type in dtypes:
                broken = np.frombuffer(b"\xff" * array.nbytes, dtype=array.dtype).reshape(array.shape)
                tensor.CopyFrom(onnx.numpy_helper.from_array(broken, tensor.name))
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


@pytest.mark.parametrize("dtypes", [(np.float32,), (np.float32, np.int64)], ids=["floats", "all"])
def test_a_model_that_loads_but_cannot_infer_refuses_to_start(
    dtypes: tuple[type, ...], tmp_path: Path
) -> None:
    """A child process: a server that started anyway would serve until the timeout."""
    path = tmp_path / "weights_0xff.onnx"
    _weights_overwritten(dtypes)(path)
    flags = ["--model-path", str(path), "--host", "127.0.0.1", "--http-port", "0", "--grpc-port", "0"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "repnet", "serve", *flags]
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, done.stderr[-2000:]
    (error,) = [line for line in (done.stderr + done.stdout).splitlines() if " ERROR " in line]
    assert f"cannot start: {path}: the model fails its check on 3 known poses" in error, error
    assert "non-finite output for poses [0, 1, 2]" in error and "Traceback" not in done.stderr


def test_a_directory_as_model_path_is_named_a_directory(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    assert main(["--model-path", str(tmp_path), "--http-port", "0", "--grpc-port", "0"]) == 1
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    assert record.getMessage() == f"cannot start: model path is a directory, not an ONNX file: {tmp_path}"


def test_model_path_from_the_environment_that_does_not_exist_exits_1(tmp_path: Path) -> None:
    absent = tmp_path / "absent" / "model.onnx"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "REPNET_MODEL_PATH": str(absent)}
    done = subprocess.run(
        [sys.executable, "-m", "repnet", "serve"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1
    assert f"cannot start: model file not found: {absent}" in done.stderr + done.stdout
    assert "Traceback" not in done.stderr
