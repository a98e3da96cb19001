"""The graph rewrites at load (runtime.rewrite): a strided 1D convolution as one matrix product keeps
its answers, and nothing else is touched."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_OFFLINE
from repnet.runtime.rewrite import convs_as_matmuls
from repnet.runtime.session import SessionOptions, open_session, read_model, served_graph

DETECTOR = Path(__file__).parents[2] / "service" / "models" / "detector"


def _plain(data: bytes) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    return ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("path", [BUNDLED_CAUSAL, BUNDLED_OFFLINE], ids=["causal", "offline"])
def test_the_temporal_models_answer_as_their_files_do(path: Path) -> None:
    model = onnx.load_from_string(read_model(path))
    assert convs_as_matmuls(model) == 8  # every layer of the network; the grouped smoothing stays
    assert [n.op_type for n in model.graph.node].count("Conv") == 1
    served, stored = open_session(path, SessionOptions(intra_op_threads=1)), _plain(read_model(path))
    rng = np.random.default_rng(0)
    for n, slots in ((1, 49), (16, 49), (7, 81), (3, 121)):
        poses = (rng.normal(0, 300, (n, 1, 17, 3)) + rng.normal(0, 20, (n, slots, 17, 3))).astype(np.float32)
        feeds = {
            "poses": poses,
            "keypoints_2d": (poses[..., :2] * 0.5 + 500).astype(np.float32),
            "visibility": (rng.random((n, slots, 17)) > 0.1).astype(np.float32),
            "fps": rng.uniform(20, 60, n).astype(np.float32),
        }
        got, want = served.run(None, feeds)[0], stored.run(None, feeds)[0]
        # the same sums in another order: within a float32 step of each answer (mm)
        assert np.allclose(got, want, rtol=2.0**-22, atol=1e-4), float(np.abs(got - want).max())


def _conv_model(length: int, kernel: int, **attrs: object) -> onnx.ModelProto:
    rng = np.random.default_rng(1)
    weight = numpy_helper.from_array(rng.normal(size=(5, 4, kernel)).astype(np.float32), "w")
    bias = numpy_helper.from_array(rng.normal(size=5).astype(np.float32), "b")
    node = helper.make_node("Conv", ["x", "w", "b"], ["y"], "conv", kernel_shape=[kernel], **attrs)
    graph = helper.make_graph(
        [node],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 4, length])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 5, "L"])],
        [weight, bias],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


@pytest.mark.parametrize(
    ("length", "kernel", "attrs", "rewritten"),
    [
        (12, 3, {"strides": [3]}, 1),
        (12, 1, {}, 1),
        (10, 3, {"strides": [3]}, 0),  # the kernel does not divide the length
        (12, 3, {"strides": [1]}, 0),  # overlapping frames
        (12, 3, {"strides": [3], "pads": [1, 1]}, 0),
        (12, 3, {"strides": [3], "dilations": [2]}, 0),
    ],
)
def test_only_a_conv_of_disjoint_frame_groups_is_rewritten_and_it_answers_the_same(
    length: int, kernel: int, attrs: dict[str, object], rewritten: int
) -> None:
    model = _conv_model(length, kernel, **attrs)
    before = model.SerializeToString()
    assert convs_as_matmuls(model) == rewritten
    x = np.random.default_rng(2).normal(size=(3, 4, length)).astype(np.float32)
    got, want = (
        _plain(model.SerializeToString()).run(None, {"x": x})[0],
        _plain(before).run(None, {"x": x})[0],
    )
    assert got.shape == want.shape and np.allclose(got, want, atol=1e-5)
    if not rewritten:
        assert model.SerializeToString() == before


def test_a_model_with_nothing_to_cut_or_rewrite_is_served_as_its_bytes() -> None:
    for path in sorted(DETECTOR.glob("*.onnx")):  # 2D convolutions: not the temporal networks' layers
        data = read_model(path)
        assert served_graph(data) is data, path.name
