"""Lifter on the bundled ONNX model: loading, the contract, outputs, masking and misuse."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from repnet.core import geometry
from repnet.core.errors import InvalidKeypoints, ModelLoadError
from repnet.runtime.lifter import Lifter, without_build_paths
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.server.config import Settings
from tests.conftest import POSE_2D, load_model


def test_bundled_model_metadata_is_read(lifter: Lifter) -> None:
    info = lifter.info
    assert info.model_id and info.skeleton == "h36m17"
    assert info.joint_names[0] == "pelvis" and len(info.joint_names) == 17 and len(info.parents) == 17
    assert "licence" in info.metadata and isinstance(info.evaluation, dict)


def test_lift_returns_every_output_with_its_shape(lifter: Lifter) -> None:
    points = np.stack([POSE_2D, POSE_2D * 0.7 + 30]).astype(np.float32)
    prediction = lifter.lift(points, np.ones((2, 17), np.float32))
    assert len(prediction) == 2
    for name, shape in {"pose_3d": (2, 17, 3), "camera": (2, 2, 3)}.items():
        value = getattr(prediction, name)
        assert value.shape == shape and value.dtype == np.float32 and np.isfinite(value).all(), name
    assert prediction.failed.shape == (2,) and not prediction.failed.any()
    second = prediction.slice(1, 2)
    assert len(second) == 1 and np.array_equal(second.camera[0], prediction.camera[1])
    joined = type(prediction).join([prediction.slice(0, 1), second])
    assert np.array_equal(joined.pose_3d, prediction.pose_3d) and np.array_equal(
        joined.failed, prediction.failed
    )


def test_coordinates_of_invisible_joints_are_ignored(lifter: Lifter) -> None:
    visible = np.ones((1, 17), bool)
    visible[0, 12] = False
    clean = POSE_2D[None].astype(np.float32)
    poisoned = clean.copy()
    poisoned[0, 12] = [np.nan, 3e38]
    a, b = lifter.lift(clean, visible), lifter.lift(poisoned, visible)
    np.testing.assert_array_equal(a.pose_3d, b.pose_3d)
    np.testing.assert_array_equal(a.camera, b.camera)
    np.testing.assert_array_equal(
        geometry.reproject(a.camera, a.pose_3d, clean, visible),
        geometry.reproject(b.camera, b.pose_3d, poisoned, visible),
    )


def test_lift_rejects_wrong_joint_count(lifter: Lifter) -> None:
    with pytest.raises(InvalidKeypoints, match=r"expected shape \(N, 17, 2\), got \(4, 16, 2\)"):
        lifter.lift(np.zeros((4, 16, 2), np.float32), np.ones((4, 16), np.float32))


def test_lift_rejects_mismatched_visibility_and_non_finite_points(lifter: Lifter) -> None:
    with pytest.raises(InvalidKeypoints, match="visibility: expected shape"):
        lifter.lift(POSE_2D[None].astype(np.float32), np.ones((1, 16), np.float32))
    bad = POSE_2D[None].astype(np.float32)
    bad[0, 0, 0] = np.inf
    with pytest.raises(InvalidKeypoints, match="finite"):
        lifter.lift(bad, np.ones((1, 17), np.float32))


def test_load_reports_a_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ModelLoadError, match="model file not found"):
        load_model(tmp_path / "nope.onnx")


def test_load_reports_a_corrupt_file(tmp_path: Path) -> None:
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(BUNDLED_MODEL.read_bytes()[:5000])
    with pytest.raises(ModelLoadError, match="cannot load model"):
        load_model(corrupt)


def test_load_reports_a_model_with_another_contract(tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 17, 2])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 17, 2])
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "other", [x], [y])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"joint_names": '["a"]'})
    path = tmp_path / "other.onnx"
    onnx.save(model, str(path))
    with pytest.raises(ModelLoadError, match=r"expected inputs \['keypoints_2d', 'visibility'\]"):
        load_model(path)


@pytest.mark.parametrize("spinning", [True, False])
def test_load_sets_whether_onnxruntime_threads_spin(spinning: bool) -> None:
    lifter = Lifter.load(BUNDLED_MODEL, Settings(intra_op_threads=1, intra_op_spinning=spinning))
    entry = lifter.session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning")
    assert entry == ("1" if spinning else "0")


def test_build_paths_are_cut_to_what_means_something_elsewhere() -> None:
    command = (
        "generator: python -m repnet.train.train --out-dir /root/.cache/repnet/runs/s5_r2_limbs "
        "--init-from=/root/.cache/repnet/runs/s5_mask25/last.pt --data /data/h36m/poses.npz; see "
        "https://example.org/a/b and runs/x/last.pt"
    )
    assert without_build_paths(command) == (
        "generator: python -m repnet.train.train --out-dir runs/s5_r2_limbs "
        "--init-from=runs/s5_mask25/last.pt "
        "--data poses.npz; see https://example.org/a/b and runs/x/last.pt"
    )


def test_public_metadata_shows_no_path_of_the_build_machine(lifter: Lifter) -> None:
    public = lifter.info.public_metadata
    assert public.keys() == lifter.info.metadata.keys()
    assert not any("/root/" in value or "/.cache/" in value for value in public.values())
    if "/root/.cache/repnet/runs/" in lifter.info.metadata.get("train_command", ""):  # the bundled v6
        assert "--out-dir runs/s5_r2_limbs" in public["train_command"]
