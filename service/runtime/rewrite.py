"""Rewrites of a model's graph at load that keep its answers and make onnxruntime's runs cheaper.

**A strided 1D convolution as one matrix product over the whole batch.** The temporal models are
temporal convolution networks whose layers read disjoint groups of frames (kernel = stride, no
padding: VideoPose3D's strided form). onnxruntime's Conv runs such a layer pose by pose, each a
product of a 256 x 768 weight with a handful of columns (9, 3, then 1 frame): every pose of a batch
reads the layer's weights again, so a batch of 16 costs nearly 16 poses. Turned frames-first (N, L, C),
each group of k frames is one row of C * k numbers, and the layer one MatMul of the batch's rows,
(N, L/k, C * k) x (C * k, C'), that reads the weights once a run. It is the same sum of the same
products, so the answers agree to float32 rounding (tests/service/test_rewrite.py).
"""

from __future__ import annotations

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
    inferred = shape_inference.infer_shapes(model)
    lengths = {
        info.name: [d.dim_value if d.HasField("dim_value") else None for d in info.type.tensor_type.shape.dim]
        for info in [*inferred.graph.value_info, *inferred.graph.input]
    }
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
