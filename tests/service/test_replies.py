"""The reply: one declaration of its fields, checked against every carrier; geometry computed once."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from google.protobuf.descriptor import FieldDescriptor

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.cli.main import EXIT_OK, main
from repnet.client import http as client
from repnet.core import fields, geometry
from repnet.core.errors import ModelOutputError
from repnet.core.fields import ANY, FIELDS, NAMES
from repnet.core.formats import FORMATS, from_model_joints
from repnet.core.inputs import ModelInput, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.replies import IMPLAUSIBLE_BELOW, Replies, build_replies
from repnet.server.app import limits_of
from repnet.server.config import Settings
from repnet.server.http.responses import PoseResult
from tests.conftest import CENTRE_PX, FOCAL_PX, POSE_2D

INTRINSICS = (FOCAL_PX, FOCAL_PX, *CENTRE_PX)


def protos_of(replies: Replies) -> list[lifter_pb2.PoseResult]:
    """The replies as the proto PoseResults gRPC sends."""
    return [lifter_pb2.PoseResult(**f) for f in replies.proto_fields()]


def model_input(*intrinsics: tuple[float, float, float, float] | None) -> ModelInput:
    """POSE_2D moved across the image, once per item of `intrinsics` (the pose's camera, or None)."""
    poses = [
        PoseInput(POSE_2D + [300.0 * i, 40.0 * i], np.ones(17, bool), intrinsics=camera)
        for i, camera in enumerate(intrinsics)
    ]
    return prepare_poses(poses, limits_of(Settings())).check()


def replies_of(lifter: Lifter, inputs: ModelInput) -> Replies:
    return build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible))


def test_every_carrier_of_the_reply_has_exactly_the_declared_fields(tmp_path: Path) -> None:
    """FIELDS is the one declaration; the pydantic schema, the proto, the client and the CLI's output
    rows must carry the same names in the same order, and the client the same matrix shapes."""
    assert list(PoseResult.model_fields) == list(NAMES)
    assert [f.name for f in lifter_pb2.PoseResult.DESCRIPTOR.fields] == list(NAMES)
    assert client.LiftResult.pose_fields() == NAMES
    matrices = {f.name: f.shape for f in FIELDS if f.kind is float and len(f.shape) == 2}
    assert fields.MATRICES == matrices == {"pose_3d": (ANY, 3), "pose_3d_camera": (ANY, 3), "camera": (2, 3),
                                           "rotation": (3, 3), "reprojection": (ANY, 2)}  # fmt: skip
    path, out = tmp_path / "poses.json", tmp_path / "out.json"
    path.write_text(json.dumps({"keypoints": POSE_2D.tolist()}))
    assert main(["lift", str(path), "--local", "-o", str(out)]) == EXIT_OK
    (row,) = json.loads(out.read_text())["poses"]
    assert list(row) == ["frame", "person", "input", *NAMES]


def test_optional_fields_are_the_optional_ones_of_every_carrier() -> None:
    optional = {f.name for f in FIELDS if f.optional}
    assert optional == {name for name, info in PoseResult.model_fields.items() if not info.is_required()} - {
        "warnings"  # a list: empty, never absent
    }
    proto = lifter_pb2.PoseResult.DESCRIPTOR.fields_by_name
    # a repeated proto field has no presence: an optional vector is unset by being empty
    vectors = {f.name for f in FIELDS if f.optional and len(f.shape) == 1}
    assert vectors == {"root_camera_m"}
    assert optional - vectors == {name for name in NAMES if proto[name].has_presence}
    assert all(len(getattr(lifter_pb2.PoseResult(), name)) == 0 for name in vectors)  # repeated: empty


def test_each_field_has_its_declared_shape_and_kind_per_pose(lifter: Lifter) -> None:
    replies = replies_of(lifter, model_input(None, INTRINSICS, None))
    assert len(replies) == 3 and not replies.failed.any()
    for field in FIELDS:
        value = replies.columns[field.name]
        if field.kind is str and field.shape == ():  # one optional string per pose
            assert len(value) == 3 and all(v is None or isinstance(v, str) for v in value), field.name
            continue
        if field.kind is str:
            assert len(value) == 3 and all(isinstance(w, str) for row in value for w in row), field.name
            continue
        if field.optional and isinstance(value, list):  # per pose: a vector of its shape, or None
            assert len(value) == 3 and all(v is None or np.shape(v) == field.shape for v in value), field.name
            continue
        if value is None:
            assert field.optional, field.name
            continue
        shape = tuple(17 if s == ANY else s for s in field.shape)
        assert value.shape == (3, *shape), field.name
        assert value.dtype == (np.float32 if field.kind is float else np.bool_), field.name
    rows, protos = replies.to_json(), protos_of(replies)
    assert [list(r) for r in rows] == [list(NAMES)] * 3
    np.testing.assert_array_equal(np.reshape(protos[1].pose_3d_camera, (17, 3)), rows[1]["pose_3d_camera"])
    assert np.shape(rows[1]["rotation"]) == (3, 3) and len(protos[1].rotation) == 9


def test_pose_3d_camera_turns_along_the_ray_only_where_intrinsics_are_given(lifter: Lifter) -> None:
    inputs = model_input(None, INTRINSICS)
    columns = replies_of(lifter, inputs).columns
    pose, rotation = columns["pose_3d"].astype(np.float64), columns["rotation"].astype(np.float64)
    np.testing.assert_allclose(columns["pose_3d_camera"][0], pose[0] @ rotation[0].T, atol=1e-3)
    ray = geometry.ray_rotation(
        inputs.keypoints_2d[1:], inputs.visible[1:], np.full((1, 2), FOCAL_PX), CENTRE_PX[None]
    )
    turned = ray[0].astype(np.float64) @ rotation[1]
    np.testing.assert_allclose(columns["pose_3d_camera"][1], pose[1] @ turned.T, atol=1e-3)
    assert not np.allclose(columns["pose_3d_camera"][1], pose[1] @ rotation[1].T, atol=1.0)


def test_a_pose_whose_geometry_is_not_finite_fails_alone(lifter: Lifter) -> None:
    """A finite but absurd camera reprojects beyond float32: that pose fails as if the model had
    given NaN (ModelOutputError for it alone), the others are answered."""
    inputs = model_input(None, None, None)
    prediction = lifter.lift(inputs.keypoints_2d, inputs.visible)
    camera = prediction.camera.copy()
    camera[1] = 1e37
    replies = build_replies(inputs, replace(prediction, camera=camera))
    assert replies.failed.tolist() == [False, True, False]
    with pytest.raises(ModelOutputError) as failed:
        replies.check()
    assert failed.value.rows == (1,)
    model_failed = replace(prediction, failed=np.array([False, False, True]))
    assert build_replies(inputs, model_failed).failed.tolist() == [False, False, True]


def test_a_model_without_plausibility_leaves_it_out(lifter: Lifter) -> None:
    inputs = model_input(None)
    prediction = replace(lifter.lift(inputs.keypoints_2d, inputs.visible), plausibility=None)
    replies = build_replies(inputs, prediction)
    assert replies.to_json()[0]["plausibility"] is None
    assert not protos_of(replies)[0].HasField("plausibility")


def test_a_pose_below_the_plausibility_threshold_is_warned_with_its_figure(lifter: Lifter) -> None:
    inputs = model_input(None, None, None, None)
    prediction = lifter.lift(inputs.keypoints_2d, inputs.visible)
    scores = np.array([IMPLAUSIBLE_BELOW, 0.0084, 0.0, np.nan], np.float32)  # NaN: a failed pose's
    warnings = build_replies(inputs, replace(prediction, plausibility=scores)).columns["warnings"]
    assert warnings[0] == [] and warnings[3] == []
    assert warnings[1] == [
        "plausibility: the 3D pose looks implausible (plausibility 0.0084 < 0.01, below 99 % of the "
        "answers to real people's 2D): check the format and the keypoints"
    ]
    assert warnings[2][0].startswith("plausibility: the 3D pose looks implausible (plausibility 0 < 0.01")
    none = build_replies(inputs, replace(prediction, plausibility=None)).columns["warnings"]
    assert none == [[], [], [], []]  # a model without plausibility warns of nothing
    coco, present = from_model_joints(FORMATS["coco17"], POSE_2D[None])
    mixed = prepare_poses([PoseInput(coco[0], present[0])], limits_of(Settings())).check()  # read as h36m17
    reply = replies_of(lifter, mixed)
    assert reply.columns["plausibility"][0] < IMPLAUSIBLE_BELOW
    (only,) = reply.columns["warnings"][0]  # the mix-up's warning names the likelier cause alone
    assert only.startswith("format: these keypoints look like coco17, not h36m17")


def test_replies_refuse_columns_other_than_the_declared_fields() -> None:
    with pytest.raises(ValueError, match="expected the reply fields"):
        Replies({"pose_3d": np.zeros((1, 17, 3))}, np.zeros(1, bool))


def test_a_prediction_is_only_the_models_outputs() -> None:
    assert [f for f in Prediction.__dataclass_fields__] == ["pose_3d", "camera", "failed", "plausibility"]


def test_root_camera_m_places_a_known_pose_where_it_stood(lifter: Lifter) -> None:
    """A pose seen through a pinhole camera at a known root: the answer, scaled to the pose's own
    skeleton height, is placed near that root; without intrinsics there is no root."""
    pose = lifter.lift(POSE_2D[None].astype(np.float32), np.ones((1, 17), bool)).pose_3d[0].astype(np.float64)
    root = np.array([400.0, 250.0, 5200.0])  # mm, off the optical axis
    world = pose + root  # the model's own answer as the person: its reprojection is the input
    pixels = world[:, :2] / world[:, 2:] * FOCAL_PX + np.asarray(CENTRE_PX)
    height = float(geometry.skeleton_height(pose[None])[0]) / 1000.0
    poses = [
        PoseInput(pixels, np.ones(17, bool), intrinsics=INTRINSICS),
        PoseInput(pixels, np.ones(17, bool), intrinsics=INTRINSICS, person_height_m=1.25 * height),
        PoseInput(pixels, np.ones(17, bool)),
    ]
    replies = replies_of(lifter, prepare_poses(poses, limits_of(Settings())).check())
    rows = replies.to_json()
    assert [r["root_height_source"] for r in rows] == ["template", "given", None]
    template, given = np.array(rows[0]["root_camera_m"]), np.array(rows[1]["root_camera_m"])
    assert np.linalg.norm(template * 1000 - root) < 0.05 * root[2]
    # a quarter taller than the answer: a quarter farther along the same ray
    np.testing.assert_allclose(given, 1.25 * template, rtol=1e-3)
    assert rows[2]["root_camera_m"] is None and not protos_of(replies)[2].root_camera_m
    assert len(protos_of(replies)[0].root_camera_m) == 3


def test_root_translation_inverts_a_pinhole_projection() -> None:
    rng = np.random.default_rng(0)
    pose = rng.normal(0, 300, (4, 17, 3))
    pose -= pose[:, :1]
    root = np.array([[0, 0, 3000], [-500, 200, 4000], [900, -100, 6000], [10, 10, 2500.0]])
    world = pose + root[:, None]
    camera = np.array([[1000.0, 1010.0, 500.0, 480.0]] * 4)
    pixels = world[..., :2] / world[..., 2:] * camera[:, None, :2] + camera[:, None, 2:]
    visible = np.ones((4, 17), bool)
    visible[1, 3:9] = False  # hidden joints are left out
    pixels[1, 3:9] = np.nan
    np.testing.assert_allclose(geometry.root_translation(pixels, visible, pose, camera), root, atol=1e-6)
    visible[2, 1:] = False  # one joint cannot place a root
    assert np.isnan(geometry.root_translation(pixels, visible, pose, camera)[2]).all()


def test_the_protos_pose_result_has_each_fields_kind_shape_and_presence() -> None:
    """core.fields against the proto's descriptor: float, bool or string; repeated unless a scalar;
    a scalar that may be absent has presence (`optional`)."""
    kinds = {
        float: FieldDescriptor.TYPE_FLOAT,
        bool: FieldDescriptor.TYPE_BOOL,
        str: FieldDescriptor.TYPE_STRING,
    }
    by_name = lifter_pb2.PoseResult.DESCRIPTOR.fields_by_name
    for field in FIELDS:
        proto = by_name[field.name]
        assert proto.type == kinds[field.kind], field.name
        assert proto.is_repeated == bool(field.shape), field.name
        if not field.shape:
            assert proto.has_presence == field.optional, field.name
