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
from repnet.runtime.rewrite import broadcasts_widened, convs_as_matmuls
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


def _binary_model(op: str, a: list[object], b: list[object]) -> onnx.ModelProto:
    node = helper.make_node(op, ["a", "b"], ["y"], "op")
    graph = helper.make_graph(
        [node],
        "g",
        [
            helper.make_tensor_value_info("a", TensorProto.FLOAT, a),
            helper.make_tensor_value_info("b", TensorProto.FLOAT, b),
        ],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


@pytest.mark.parametrize(
    ("op", "a", "b", "rewritten"),
    [
        ("Mul", ["N", 5, 17, 2], ["N", 5, 17, 1], 1),  # a mask over x and y
        ("Sub", ["N", 5, 17, 2], ["N", 5, 1, 2], 1),  # a centre over the joints
        ("Div", ["N", 5, 1, 1], ["N", 5, 17, 2], 0),  # two axes broadcast
        ("Add", ["N", 5, 17, 8], ["N", 5, 17, 1], 1),  # tiled to 8
        ("Add", ["N", 5, 3, 8], ["N", 5, 1, 8], 0),  # spans of 8 numbers: long enough as they are
        ("Mul", [1, 5, 17, 2], ["N", 5, 17, 2], 0),  # a leading axis
        ("Mul", ["N", 5, 17, "C"], ["N", 5, 17, 1], 0),  # an axis of unknown length
        ("Mul", ["N", 17, 2], [17, 1], 0),  # ranks differ
        ("Mul", ["N", 5, 17, 2], ["N", 5, 17, 2], 0),  # nothing broadcast
    ],
)
def test_a_broadcast_over_a_short_trailing_axis_is_tiled_and_answers_the_same_to_the_bit(
    op: str, a: list[object], b: list[object], rewritten: int
) -> None:
    model = _binary_model(op, a, b)
    before = model.SerializeToString()
    assert broadcasts_widened(model) == rewritten
    rng = np.random.default_rng(3)

    def draw(shape: list[object]) -> np.ndarray:
        sizes = [3 if d == "N" else 8 if d == "C" else d for d in shape]
        return rng.uniform(0.5, 2.0, sizes).astype(np.float32)

    feeds = {"a": draw(a), "b": draw(b)}
    got = _plain(model.SerializeToString()).run(None, feeds)[0]
    want = _plain(before).run(None, feeds)[0]
    assert got.shape == want.shape and np.array_equal(got, want)
    if not rewritten:
        assert model.SerializeToString() == before


def test_one_tiled_copy_serves_every_node_that_reads_the_operand() -> None:
    nodes = [
        helper.make_node("Mul", ["x", "m"], ["p"], "mask"),
        helper.make_node("Add", ["p", "m"], ["y"], "again"),
    ]
    shapes = {"x": ["N", 17, 2], "m": ["N", 17, 1]}
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info(k, TensorProto.FLOAT, v) for k, v in shapes.items()],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    assert broadcasts_widened(model) == 2
    assert [n.op_type for n in model.graph.node] == ["Concat", "Mul", "Add"]


@pytest.mark.parametrize("path", [BUNDLED_CAUSAL, BUNDLED_OFFLINE], ids=["causal", "offline"])
def test_the_temporal_models_input_rules_are_tiled(path: Path) -> None:
    model = onnx.load_from_string(read_model(path))
    # the mask over the window's keypoints and over the grid's, the centre, the masked centred
    # keypoints, and two divisions by a per-frame count
    assert broadcasts_widened(model) == 6
