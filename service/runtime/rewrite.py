"""Rewrites of a model's graph at load that keep its answers and make onnxruntime's runs cheaper.

**A strided 1D convolution as one matrix product over the whole batch.** The temporal models are
temporal convolution networks whose layers read disjoint groups of frames (kernel = stride, no
padding: VideoPose3D's strided form). onnxruntime's Conv runs such a layer pose by pose, each a
product of a 256 x 768 weight with a handful of columns (9, 3, then 1 frame): every pose of a batch
reads the layer's weights again, so a batch of 16 costs nearly 16 poses. Turned frames-first (N, L, C),
each group of k frames is one row of C * k numbers, and the layer one MatMul of the batch's rows,
(N, L/k, C * k) x (C * k, C'), that reads the weights once a run. It is the same sum of the same
products, so the answers agree to float32 rounding (tests/service/test_rewrite.py).

**A broadcast over a short trailing axis made explicit.** The temporal models' input rules multiply
(N, T, 17, 2) keypoints by a (N, T, 17, 1) mask and subtract a (N, T, 1, 2) centre. onnxruntime
broadcasts such an operand span by span of the output's last one or two axes (2 or 34 numbers), at
about 6 ns a number, 10-25x its same-shape speed: three such nodes cost a causal run at batch 16 as
much as its first matrix product. The small operand, tiled to the other's size along that axis by
a Concat of its copies, gives the same numbers to the bit, at same-shape speed.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def convs_as_matmuls(model: Any) -> int:
    """Rewrite in place, in onnx `model`, every 1D Conv whose frames fall in disjoint groups (kernel
    = stride, no padding or dilation, one group, a constant weight, an input whose length shape
    inference knows and the kernel divides) as Reshape, Transpose, MatMul (+ Add of its bias) and
    Transpose back. Returns how many were rewritten."""
    import onnx
    from onnx import helper, numpy_helper, shape_inference

    graph = model.graph
    weights = {t.name: t for t in graph.initializer}
    lengths = _shapes(shape_inference.infer_shapes(model))
    nodes: list[Any] = []
    rewritten = 0
    for node in graph.node:
        found = _strided_conv(node, weights, lengths)
        if found is None:
            nodes.append(node)
            continue
        weight, bias, length = found
        out_channels, channels, k = weight.shape
        x, y = node.input[0], node.output[0]
        table = f"{node.name or y}/as_matmul"

        def t(part: str, table: str = table) -> str:
            return f"{table}/{part}"

        # row j * C + c of the folded weight is W[:, c, j]: the frames-first input's group of k frames
        folded = np.ascontiguousarray(weight.transpose(2, 1, 0).reshape(k * channels, out_channels))
        graph.initializer.append(numpy_helper.from_array(folded, t("weight")))
        rows = np.array([0, length // k, k * channels], np.int64)  # 0: the batch as it comes
        graph.initializer.append(numpy_helper.from_array(rows, t("rows")))
        nodes += [
            helper.make_node("Transpose", [x], [t("frames_first")], t("transpose"), perm=[0, 2, 1]),
            helper.make_node("Reshape", [t("frames_first"), t("rows")], [t("rows_of")], t("flatten")),
            helper.make_node("MatMul", [t("rows_of"), t("weight")], [t("product")], t("mm")),
        ]
        product = t("product")
        if bias is not None:
            graph.initializer.append(numpy_helper.from_array(bias.astype(np.float32), t("bias")))
            nodes.append(helper.make_node("Add", [product, t("bias")], [t("biased")], t("add")))
            product = t("biased")
        nodes.append(helper.make_node("Transpose", [product], [y], t("channels_first"), perm=[0, 2, 1]))
        rewritten += 1
    if rewritten:
        del graph.node[:]
        graph.node.extend(nodes)
        used = {name for node in graph.node for name in node.input}
        kept = [t for t in graph.initializer if t.name in used]
        del graph.initializer[:]
        graph.initializer.extend(kept)
        onnx.checker.check_model(model)
    return rewritten


ELEMENTWISE = ("Add", "Sub", "Mul", "Div")
MAX_TILES = 64  # an axis longer than this is not tiled (its spans are long enough already)
MAX_SPAN = 4  # nor one whose output spans (the numbers after the axis) are longer than this


def broadcasts_widened(model: Any) -> int:
    """Rewrite in place, in onnx `model`, every Add, Sub, Mul or Div whose operands have the same
    rank and differ on one of the last two axes only where one has 1 and the other a known d
    (2 <= d <= MAX_TILES, at most MAX_SPAN numbers after that axis): the 1-long operand is first tiled
    to d along that axis (a Concat of d copies, one per operand and axis). Returns how many nodes read
    a tiled operand."""
    from onnx import helper, shape_inference

    graph = model.graph
    shapes = _shapes(shape_inference.infer_shapes(model))
    nodes: list[Any] = []
    tiled: dict[tuple[str, int, int], str] = {}  # (operand, axis, d) -> its tiled name
    rewritten = 0
    for node in graph.node:
        found = _narrow_broadcast(node, shapes)
        if found is None:
            nodes.append(node)
            continue
        side, axis, d = found
        operand = node.input[side]
        key = (operand, axis, d)
        if key not in tiled:
            name = tiled[key] = f"{operand}/tiled_{axis}x{d}"
            nodes.append(helper.make_node("Concat", [operand] * d, [name], f"{name}/concat", axis=axis))
        inputs = list(node.input)
        inputs[side] = tiled[key]
        del node.input[:]
        node.input.extend(inputs)
        nodes.append(node)
        rewritten += 1
    if rewritten:  # a Concat of one tensor's copies: nothing a checker would find (and outputs
        # without shapes, which onnxruntime runs, stay loadable)
        del graph.node[:]
        graph.node.extend(nodes)
    return rewritten


def _shapes(inferred: Any) -> dict[str, list[int | None]]:
    """Each tensor's shape that shape inference found (None where a dimension is not a number)."""
    infos = [*inferred.graph.value_info, *inferred.graph.input]
    found = {
        info.name: [d.dim_value if d.HasField("dim_value") else None for d in info.type.tensor_type.shape.dim]
        for info in infos
        if info.type.tensor_type.HasField("shape")
    }
    for t in inferred.graph.initializer:
        found[t.name] = list(t.dims)
    return found


def _narrow_broadcast(node: Any, shapes: dict[str, list[int | None]]) -> tuple[int, int, int] | None:
    """(which operand, axis, d) of a node broadcasts_widened rewrites; None for any other node."""
    if node.op_type not in ELEMENTWISE or len(node.input) != 2:
        return None
    a, b = (shapes.get(name) for name in node.input)
    if a is None or b is None or len(a) != len(b) or len(a) < 2:
        return None
    differing = [i for i in range(len(a)) if a[i] != b[i] or a[i] is None]
    broadcast = [i for i in differing if 1 in (a[i], b[i])]
    if len(broadcast) != 1 or broadcast[0] < len(a) - 2:
        return None
    axis = broadcast[0]
    side = 0 if a[axis] == 1 else 1
    d = (b, a)[side][axis]
    after = [n for n in (b, a)[side][axis + 1 :] if n is not None]
    if d is None or not 2 <= d <= MAX_TILES or len(after) < len(a) - axis - 1 or math.prod(after) > MAX_SPAN:
        return None
    return side, axis - len(a), d


def _strided_conv(
    node: Any, weights: dict[str, Any], lengths: dict[str, list[int | None]]
) -> tuple[np.ndarray, np.ndarray | None, int] | None:
    """(weight (C', C, k), bias (C',) or None, input length) of a Conv that convs_as_matmuls rewrites;
    None for any other node."""
    from onnx import helper, numpy_helper

    if node.op_type != "Conv" or node.input[1] not in weights:
        return None
    if len(node.input) > 2 and node.input[2] and node.input[2] not in weights:
        return None
    weight = numpy_helper.to_array(weights[node.input[1]])
    if weight.ndim != 3 or weight.dtype != np.float32:
        return None
    k = int(weight.shape[2])
    attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
    plain = (
        attrs.get("group", 1) == 1
        and list(attrs.get("strides", [1])) == [k]
        and all(d == 1 for d in attrs.get("dilations", [1]))
        and all(p == 0 for p in attrs.get("pads", [0, 0]))
        and attrs.get("auto_pad", b"NOTSET") in (b"NOTSET", "NOTSET", b"VALID", "VALID")
    )
    shape = lengths.get(node.input[0])
    if not plain or shape is None or len(shape) != 3 or shape[1] not in (None, weight.shape[1]):
        return None
    length = shape[2]
    if length is None or length % k:
        return None
    bias = numpy_helper.to_array(weights[node.input[2]]) if len(node.input) > 2 and node.input[2] else None
    return weight, bias, int(length)
