"""The optional `plausibility` model output, followed through every module that carries it: Lifter,
LiftBatcher batching, HTTP, gRPC (unary and stream), the clients, the CLI and the metrics. A model with
the output is built here from the bundled graph, so the plumbing does not wait for a trained one."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest
from prometheus_client import CollectorRegistry

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.cli.main import EXIT_OK, main
from repnet.client.stream import StreamClient
from repnet.core.errors import ModelLoadError
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import PLAUSIBILITY_CALIBRATION, Lifter
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.server.app import build_app, build_grpc_server
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from tests.conftest import POSE_2D, POSE_3D, TestClient, load_model, project

onnx = pytest.importorskip("onnx")  # the dev extra has it; service tests need no torch
from onnx import TensorProto, helper  # noqa: E402

CALIBRATION = {"method": "percentile", "reference": "test poses", "quantiles": [0.0, 0.5, 1.0]}
SPREAD_MM = 100.0  # the test output: sigmoid(mean(pose_3d) / SPREAD_MM), a known value per pose


def expected_plausibility(pose_3d: np.ndarray) -> np.ndarray:
    """What the test model's extra output computes from its (N, J, 3) pose_3d, written in numpy."""
    return np.asarray(1.0 / (1.0 + np.exp(-pose_3d.mean(axis=(1, 2)) / SPREAD_MM)))


def _without_plausibility() -> onnx.ModelProto:
    """The bundled model with its own plausibility output, if any, taken out (its nodes stay,
    unused, under another name) and the metadata that describes it dropped."""
    model = onnx.load(str(BUNDLED_MODEL))
    for output in [o for o in model.graph.output if o.name == "plausibility"]:
        model.graph.output.remove(output)
    for node in model.graph.node:
        node.output[:] = ["bundled_plausibility" if n == "plausibility" else n for n in node.output]
    kept = [(e.key, e.value) for e in model.metadata_props if not e.key.startswith("plausibility")]
    del model.metadata_props[:]
    for key, value in kept:
        model.metadata_props.add(key=key, value=value)
    return model


def build_plain(path: Path) -> Path:
    """The bundled model without a plausibility output."""
    model = _without_plausibility()
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def build_model(path: Path, shape: list[int | str] | None = None) -> Path:
    """The bundled model with (instead of its own, if it has one) an output `plausibility` (N,) =
    sigmoid(mean(pose_3d) / 100) and the `plausibility_calibration` metadata entry; `shape`
    overrides the declared shape."""
    model = _without_plausibility()
    graph = model.graph
    graph.initializer.append(helper.make_tensor("plaus_spread", TensorProto.FLOAT, [], [SPREAD_MM]))
    graph.node.extend([
        helper.make_node("ReduceMean", ["pose_3d"], ["plaus_mean"], axes=[1, 2], keepdims=0),
        helper.make_node("Div", ["plaus_mean", "plaus_spread"], ["plaus_logit"]),
        helper.make_node("Sigmoid", ["plaus_logit"], ["plaus_raw"]),
    ])  # fmt: skip
    declared = shape or ["N"]
    if len(declared) == 1:
        graph.node.append(helper.make_node("Identity", ["plaus_raw"], ["plausibility"]))
    else:
        graph.initializer.append(helper.make_tensor("plaus_shape", TensorProto.INT64, [2], [-1, 1]))
        graph.node.append(helper.make_node("Reshape", ["plaus_raw", "plaus_shape"], ["plausibility"]))
    graph.output.append(helper.make_tensor_value_info("plausibility", TensorProto.FLOAT, declared))
    entry = model.metadata_props.add()
    entry.key, entry.value = PLAUSIBILITY_CALIBRATION, json.dumps(CALIBRATION)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


@pytest.fixture(scope="module")
def plain(tmp_path_factory: pytest.TempPathFactory) -> Lifter:
    return load_model(build_plain(tmp_path_factory.mktemp("model") / "plain.onnx"))


@pytest.fixture(scope="module")
def plausible(tmp_path_factory: pytest.TempPathFactory) -> Lifter:
    path = build_model(tmp_path_factory.mktemp("model") / "plausible.onnx")
    return load_model(path)


def poses(n: int) -> np.ndarray:
    """(n, 17, 2) px: the conftest person seen from n directions."""
    return np.stack([project(POSE_3D, yaw) for yaw in np.linspace(-60, 60, n)])


def test_lifter_returns_the_models_plausibility(plausible: Lifter, plain: Lifter) -> None:
    points = poses(5)
    visible = np.ones(points.shape[:2], bool)
    prediction = plausible.lift(points, visible)
    assert prediction.plausibility is not None and prediction.plausibility.shape == (5,)
    assert prediction.plausibility.dtype == np.float32
    np.testing.assert_allclose(prediction.plausibility, expected_plausibility(prediction.pose_3d), atol=1e-6)
    assert plausible.has_plausibility and plausible.info.plausibility_calibration == CALIBRATION
    assert len(prediction.slice(1, 3).plausibility) == 2  # type: ignore[arg-type]
    bundled = plain.lift(points, visible)
    assert bundled.plausibility is None and not plain.has_plausibility
    assert plain.info.plausibility_calibration is None
    np.testing.assert_array_equal(bundled.pose_3d, prediction.pose_3d)  # the extra output changes nothing


def test_a_plausibility_output_of_another_shape_is_refused(tmp_path: Path) -> None:
    path = build_model(tmp_path / "wrong.onnx", shape=["N", 1])
    with pytest.raises(ModelLoadError, match=r"expected output plausibility of shape \(N,\), got \['N', 1\]"):
        load_model(path)


def _body(points: np.ndarray) -> dict[str, object]:
    return {"poses": [{"keypoints": p.tolist()} for p in points]}


@pytest.fixture
def app_for(
    engine_factory: Callable[..., LiftBatcher], metrics: Metrics, settings: Settings
) -> Iterator[Callable[[Lifter], TestClient]]:
    clients: list[TestClient] = []

    def build(model: Lifter) -> TestClient:
        engine = engine_factory(model, max_batch=4)  # a 10-pose request runs in three chunks
        client = TestClient(build_app(engine, metrics, settings), base_url="http://localhost")
        clients.append(client.__enter__())
        return client

    yield build
    for client in clients:
        client.__exit__(None, None, None)


def test_http_reply_carries_plausibility_across_chunks(
    app_for: Callable[[Lifter], TestClient], plausible: Lifter, registry: CollectorRegistry
) -> None:
    client = app_for(plausible)
    reply = client.post("/lift", json=_body(poses(10)))
    assert reply.status_code == 200, reply.text
    results = reply.json()["poses"]
    pose_3d = np.array([r["pose_3d"] for r in results])
    got = np.array([r["plausibility"] for r in results])
    np.testing.assert_allclose(got, expected_plausibility(pose_3d), atol=1e-5)
    model = {"model": plausible.info.model_id}
    assert registry.get_sample_value("repnet_pose_plausibility_ratio_count", model) == 10
    assert registry.get_sample_value("repnet_pose_plausibility_ratio_sum", model) == pytest.approx(
        got.sum(), 1e-5
    )
    below_half = registry.get_sample_value("repnet_pose_plausibility_ratio_bucket", {"le": "0.5", **model})
    assert below_half == int((got <= 0.5).sum())
    model = client.get("/v1/model").json()
    assert model["plausibility"] is True and model["plausibility_calibration"] == CALIBRATION


def test_http_plausibility_is_null_without_the_output(
    app_for: Callable[[Lifter], TestClient], plain: Lifter, registry: CollectorRegistry
) -> None:
    client = app_for(plain)
    reply = client.post("/lift", json=_body(poses(6)))
    assert reply.status_code == 200, reply.text
    assert [r["plausibility"] for r in reply.json()["poses"]] == [None] * 6
    assert (
        registry.get_sample_value("repnet_pose_plausibility_ratio_count", {"model": plain.info.model_id})
        is None
    )
    model = client.get("/v1/model").json()
    assert model["plausibility"] is False and model["plausibility_calibration"] is None


@pytest.mark.parametrize("with_output", [True, False])
def test_grpc_lift_and_stream_carry_plausibility(
    engine_factory: Callable[..., LiftBatcher],
    metrics: Metrics,
    settings: Settings,
    plausible: Lifter,
    plain: Lifter,
    with_output: bool,
) -> None:
    model = plausible if with_output else plain
    server = build_grpc_server(
        engine_factory(model), metrics, settings.model_copy(update={"grpc_workers": 4})
    )
    server.start()
    try:
        with grpc.insecure_channel(f"localhost:{server.port}") as channel:
            stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
            points = poses(3)
            request = lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=p.ravel()) for p in points])
            unary = stub.Lift(request).poses
            frames = [lifter_pb2.LiftFrame(frame_id=i, pose=request.poses[i]) for i in range(3)]
            streamed = [r.pose for r in stub.LiftStream(iter(frames))]
        with StreamClient(f"localhost:{server.port}") as client:
            results = client.lift_batch(points) + [f.result for f in client.stream(points)]  # type: ignore[misc]
    finally:
        server.stop(0).wait()
    for pose in [*unary, *streamed]:
        assert pose.HasField("plausibility") is with_output
    if with_output:
        pose_3d = np.array([p.pose_3d for p in unary]).reshape(3, 17, 3)
        expected = expected_plausibility(pose_3d)
        np.testing.assert_allclose([p.plausibility for p in unary], expected, atol=1e-5)
        np.testing.assert_allclose([p.plausibility for p in streamed], expected, atol=1e-5)
        np.testing.assert_allclose([r.plausibility for r in results], [*expected, *expected], atol=1e-5)
    else:
        assert [r.plausibility for r in results] == [None] * 6


def test_cli_output_has_plausibility(tmp_path: Path, plausible: Lifter, plain: Lifter) -> None:
    source = tmp_path / "poses.json"
    source.write_text(json.dumps([POSE_2D.tolist(), poses(2)[1].tolist()]))
    for model, out in ((plausible.path, tmp_path / "with.json"), (plain.path, tmp_path / "without.json")):
        extra = ["--model", str(model)]
        assert main(["lift", str(source), "--local", *extra, "-o", str(out)]) == EXIT_OK
    with_output = json.loads((tmp_path / "with.json").read_text())["poses"]
    pose_3d = np.array([p["pose_3d"] for p in with_output])
    np.testing.assert_allclose([p["plausibility"] for p in with_output], expected_plausibility(pose_3d), 1e-5)
    without = json.loads((tmp_path / "without.json").read_text())["poses"]
    assert [p["plausibility"] for p in without] == [None] * 2
