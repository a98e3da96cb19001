"""Shape checks at the start of the training math: internal invariants (VideoPose3D's asserts)."""

from __future__ import annotations

import torch


def check_shape(tensor: torch.Tensor, expected: tuple[int | None, ...], name: str) -> None:
    """Assert that `tensor` has the shape `expected`, None matching any size.

    Skipped while torch exports a graph to ONNX: there a size is a traced value, and a Python
    comparison of it would be frozen into the graph as a constant.
    """
    if torch.onnx.is_in_onnx_export():
        return
    actual = tuple(tensor.shape)
    matches = len(actual) == len(expected) and all(
        e is None or a == e for a, e in zip(actual, expected, strict=True)
    )
    wanted = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
    assert matches, f"expected {name} of shape {wanted}, got {actual}"
