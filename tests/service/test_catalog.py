"""Several models in one service: REPNET_MODEL_DIR, a request's `model`, GET /v1/models, metrics per
model, batches of one model each, temporal lifting over its base model only, start-up refusals."""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import grpc
import httpx
import numpy as np
import onnx
import pytest
from prometheus_client import CollectorRegistry

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.cli.main import EXIT_REJECTED
from repnet.cli.main import main as repnet
from repnet.client.http import AsyncLiftClient, LiftClient
from repnet.client.stream import StreamClient
from repnet.core.errors import InvalidKeypoints, ModelLoadError, Overloaded
from repnet.core.inputs import PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_MODEL
from repnet.server.app import build_service, limits_of, main
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from repnet.server.startup import load_dir_lifters
from tests.conftest import POSE_2D, LiveService, live_settings, running_service
from tests.service.invalid_inputs import to_proto_pose

ALT = "repnet-alt-test"


def copy_model(source: Path, target: Path, **metadata: str) -> Path:
    """`source` written to `target` with its ONNX metadata entries updated by `metadata`."""
    model = onnx.load(str(source))
    entries = {p.key: p.value for p in model.metadata_props} | metadata
    del model.metadata_props[:]
    for key, value in entries.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(target))
    return target


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled model under another model_id, a byte-for-byte copy of the bundled one (served
    once) and a temporal model (not served by name)."""
    folder = tmp_path_factory.mktemp("models")
    copy_model(BUNDLED_MODEL, folder / "alt.onnx", model_id=ALT)
    shutil.copy(BUNDLED_MODEL, folder / "same-as-default.onnx")
    shutil.copy(BUNDLED_CAUSAL, folder / "causal.onnx")
    return folder


@pytest.fixture(scope="module")
def served(model_dir: Path, lifter: Lifter) -> Iterator[LiveService]:
    with running_service(live_settings(model_dir=model_dir), lifter) as live:
        yield live


@pytest.fixture(scope="module")
def stub(served: LiveService) -> Iterator[lifter_pb2_grpc.PoseLifterStub]:
    with grpc.insecure_channel(served.grpc_target) as channel:
        yield lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]


def post(served: LiveService, body: dict[str, Any]) -> httpx.Response:
    return httpx.post(f"{served.http_url}/lift", json=body, timeout=20)


def test_http_request_is_lifted_by_the_model_it_names(served: LiveService, lifter: Lifter) -> None:
    default = post(served, {"keypoints": POSE_2D.tolist()})
    alt = post(served, {"keypoints": POSE_2D.tolist(), "model": ALT})
    batch = post(served, {"poses": [{"keypoints": POSE_2D.tolist()}], "model": lifter.info.model_id})
    assert default.status_code == alt.status_code == batch.status_code == 200, alt.text
    assert default.json()["model_id"] == batch.json()["model_id"] == lifter.info.model_id
    assert alt.json()["model_id"] == ALT
    # the same weights under another name: the same answer
    np.testing.assert_allclose(
        alt.json()["poses"][0]["pose_3d"], default.json()["poses"][0]["pose_3d"], atol=1e-3
    )


def test_http_unknown_model_is_a_field_error_listing_the_known_ones(
    served: LiveService, lifter: Lifter
) -> None:
    reply = post(served, {"keypoints": POSE_2D.tolist(), "model": "nope"})
    assert reply.status_code == 422
    (item,) = reply.json()["detail"]
    assert item["field"] == "model" and item["code"] == "unknown_model"
    assert (
        "'nope'" in item["reason"]
        and ALT in item["reason"]
        and f"{lifter.info.model_id} (default)" in item["reason"]
    )
    described = httpx.get(f"{served.http_url}/v1/model", params={"model": "nope"}, timeout=20)
    assert described.status_code == 422 and described.json()["detail"][0]["field"] == "model"


def test_models_lists_each_model_with_its_lineage(served: LiveService, lifter: Lifter) -> None:
    listed = httpx.get(f"{served.http_url}/v1/models", timeout=20).json()
    assert listed["default"] == lifter.info.model_id
    by_id = {m["model_id"]: m for m in listed["models"]}
    assert list(by_id) == [lifter.info.model_id, ALT]  # the copy is served once, the temporal one not by name
    assert by_id[lifter.info.model_id]["default"] and not by_id[ALT]["default"]
    assert by_id[lifter.info.model_id]["temporal"] and not by_id[ALT]["temporal"]
    assert by_id[ALT]["metadata"]["model_id"] == ALT and len(by_id[ALT]["sha256"]) == 64
    assert by_id[ALT]["sha256"] != by_id[lifter.info.model_id]["sha256"]
    assert all("/root/" not in value for m in listed["models"] for value in m["metadata"].values())
    alt = httpx.get(f"{served.http_url}/v1/model", params={"model": ALT}, timeout=20).json()
    default = httpx.get(f"{served.http_url}/v1/model", timeout=20).json()
    assert alt["model_id"] == ALT and alt["temporal"] == []  # temporal lifting never runs over it
    assert default["model_id"] == lifter.info.model_id and default["temporal"]


def test_temporal_request_with_another_model_is_refused(served: LiveService, lifter: Lifter) -> None:
    poses = [{"keypoints": POSE_2D.tolist(), "track_id": "a", "frame": i} for i in range(3)]
    body = {"poses": poses, "temporal": "causal", "fps": 25.0}
    refused = post(served, body | {"model": ALT})
    assert refused.status_code == 422
    (item,) = refused.json()["detail"]
    assert (
        item["field"] == "model"
        and item["code"] == "model_not_temporal"
        and lifter.info.model_id in item["reason"]
    )
    assert post(served, body | {"model": lifter.info.model_id}).status_code == 200


def test_grpc_lift_picks_the_named_model(stub: lifter_pb2_grpc.PoseLifterStub, lifter: Lifter) -> None:
    pose = to_proto_pose({"keypoints": POSE_2D.tolist()})
    assert stub.Lift(lifter_pb2.LiftRequest(poses=[pose], model=ALT), timeout=20).model_id == ALT
    assert stub.Lift(lifter_pb2.LiftRequest(poses=[pose]), timeout=20).model_id == lifter.info.model_id
    with pytest.raises(grpc.RpcError) as raised:
        stub.Lift(lifter_pb2.LiftRequest(poses=[pose], model="nope"), timeout=20)
    assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert raised.value.details().startswith("model: unknown model 'nope'") and ALT in raised.value.details()


def test_grpc_stream_frames_pick_their_model(stub: lifter_pb2_grpc.PoseLifterStub, lifter: Lifter) -> None:
    pose = to_proto_pose({"keypoints": POSE_2D.tolist()})
    frames = [
        lifter_pb2.LiftFrame(frame_id=0, pose=pose, model=ALT),
        lifter_pb2.LiftFrame(frame_id=1, pose=pose),
        lifter_pb2.LiftFrame(frame_id=2, pose=pose, model="nope"),
        lifter_pb2.LiftFrame(frame_id=3, pose=pose, model=ALT, track_id="t", fps=25.0),  # tracked: base only
        lifter_pb2.LiftFrame(frame_id=4, pose=pose, model=ALT),
        lifter_pb2.LiftFrame(frame_id=5, pose=pose, model=lifter.info.model_id, track_id="t", fps=25.0),
    ]
    results = list(stub.LiftStream(iter(frames), timeout=30))
    assert [r.frame_id for r in results] == [0, 1, 2, 3, 4, 5]
    assert [r.model_id for r in results] == [
        ALT,
        lifter.info.model_id,
        lifter.info.model_id,
        ALT,
        ALT,
        lifter.info.model_id,
    ]
    assert [r.HasField("pose") for r in results] == [True, True, False, False, True, True]
    unknown, untracked = results[2].error, results[3].error
    assert unknown.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
    assert [(v.field, v.code) for v in unknown.violations] == [("model", "unknown_model")]
    assert ALT in unknown.violations[0].reason
    assert [(v.field, v.code) for v in untracked.violations] == [("model", "model_not_temporal")]


def test_metrics_are_labelled_with_the_loaded_models_only(served: LiveService, lifter: Lifter) -> None:
    post(served, {"keypoints": POSE_2D.tolist(), "model": ALT})
    post(served, {"keypoints": POSE_2D.tolist(), "model": "nope"})
    text = httpx.get(f"{served.http_url}/metrics", timeout=20).text
    assert f'repnet_lifted_poses_total{{model="{ALT}",transport="http"}}' in text
    assert f'repnet_inference_seconds_count{{model="{ALT}"}}' in text
    assert f'repnet_batch_size_poses_count{{model="{lifter.info.model_id}"}}' in text
    assert f'repnet_model_info{{default="false",model_id="{ALT}"' in text
    assert f'repnet_model_info{{default="true",model_id="{lifter.info.model_id}"' in text
    assert 'model="nope"' not in text


class RecordingLifter(Lifter):
    """The real model, recording the first x of every pose of every run, held while the gate is closed."""

    def __init__(self, inner: Lifter, model_id: str) -> None:
        super().__init__(inner.session, inner.path)
        self.info = replace(inner.info, model_id=model_id)
        self.gate = threading.Event()
        self.entered = threading.Event()  # a run reached the gate
        self.runs: list[list[float]] = []

    def lift(self, keypoints_2d: np.ndarray, visibility: np.ndarray) -> Prediction:
        self.entered.set()
        self.gate.wait(timeout=30)
        self.runs.append(keypoints_2d[:, 0, 0].round(1).tolist())
        return super().lift(keypoints_2d, visibility)


def test_batches_never_mix_models(lifter: Lifter, registry: CollectorRegistry) -> None:
    metrics = Metrics(registry)
    lifters = {name: RecordingLifter(lifter, name) for name in ("a", "b")}
    engines = {
        n: LiftBatcher(m, metrics, max_batch=64, max_wait_s=0.01, queue_size=64) for n, m in lifters.items()
    }
    models = Catalog(engines)
    limits = limits_of(Settings())
    try:
        futures = []
        for i in range(12):  # interleaved: a, b, a, b, ... each pose marked by its first x
            name = "ab"[i % 2]
            pose = POSE_2D + [1000.0 * (i + 1), 0.0]
            inputs = prepare_poses([PoseInput(pose, np.ones(17, bool))], limits).check()
            futures += models.pick(name).submit(inputs, "test")
        for recorder in lifters.values():
            recorder.gate.set()
        for future in futures:
            future.result(timeout=30)
    finally:
        models.close(10)
    for name, recorder in lifters.items():
        own = {round(POSE_2D[0, 0] + 1000.0 * (i + 1), 1) for i in range(12) if "ab"[i % 2] == name}
        seen = [x for run in recorder.runs for x in run]
        assert sorted(seen) == sorted(own)  # every run of model a held a's poses only
        assert (
            registry.get_sample_value("repnet_lifted_poses_total", {"model": name, "transport": "test"}) == 6
        )
    with pytest.raises(InvalidKeypoints) as raised:
        models.pick("c")
    assert (
        raised.value.violations[0].field == "model" and "a (default), b" in raised.value.violations[0].reason
    )


def test_queue_of_one_model_full_leaves_the_other_served(lifter: Lifter, registry: CollectorRegistry) -> None:
    metrics = Metrics(registry)
    held = RecordingLifter(lifter, "busy")
    engines = {
        "busy": LiftBatcher(held, metrics, max_batch=1, max_wait_s=0.0, queue_size=2),
        "free": LiftBatcher(lifter, metrics, max_batch=1, max_wait_s=0.0, queue_size=2),
    }
    models = Catalog(engines)
    one = prepare_poses([PoseInput(POSE_2D, np.ones(17, bool))], limits_of(Settings())).check()
    try:
        models.pick("busy").submit(one, "test")
        assert held.entered.wait(10)  # its run holds the worker; two more fill its queue of 2
        models.pick("busy").submit(one, "test")
        models.pick("busy").submit(one, "test")
        with pytest.raises(Overloaded, match="queue is full"):
            models.pick("busy").submit(one, "test")
        assert len(models.pick("free").lift(one, "test")) == 1  # the other model is not held up
    finally:
        held.gate.set()
        models.close(10)


def test_broken_file_in_the_model_dir_stops_the_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "broken.onnx").write_bytes(b"not an onnx model\nsecond line")
    with pytest.raises(ModelLoadError, match="broken.onnx"):
        build_service(live_settings(model_dir=tmp_path))
    caplog.set_level(logging.ERROR)
    assert main(["--model-dir", str(tmp_path), "--http-port", "0", "--grpc-port", "0"]) == 1
    (line,) = [r.getMessage() for r in caplog.records if "cannot start" in r.getMessage()]
    assert "broken.onnx" in line and "\n" not in line


def test_two_files_with_one_model_id_stop_the_start(tmp_path: Path, lifter: Lifter) -> None:
    copy_model(BUNDLED_MODEL, tmp_path / "one.onnx", model_id=ALT)
    copy_model(BUNDLED_MODEL, tmp_path / "two.onnx", model_id=ALT, note="another file")
    with pytest.raises(ModelLoadError, match="two.onnx has model_id 'repnet-alt-test', as .*one.onnx"):
        load_dir_lifters(Settings(model_dir=tmp_path), lifter)


def test_a_model_that_fails_its_check_stops_the_start(tmp_path: Path, lifter: Lifter) -> None:
    copy_model(BUNDLED_MODEL, tmp_path / "wrong-joints.onnx", model_id="x", joint_names='["a", "b"]')
    with pytest.raises(ModelLoadError, match="wrong-joints.onnx"):
        load_dir_lifters(Settings(model_dir=tmp_path), lifter)
    with pytest.raises(ModelLoadError, match="not a directory"):
        load_dir_lifters(Settings(model_dir=tmp_path / "missing"), lifter)


def test_clients_and_cli_name_a_model(
    served: LiveService, lifter: Lifter, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with LiftClient(served.http_url, model=ALT) as client:
        assert client.lift(POSE_2D).model_id == ALT
        assert client.model()["model_id"] == ALT
    with LiftClient(served.http_url) as client:
        assert client.lift(POSE_2D).model_id == lifter.info.model_id

    async def lift_async() -> str:
        async with AsyncLiftClient(served.http_url, model=ALT) as client:
            return (await client.lift(POSE_2D)).model_id

    assert asyncio.run(lift_async()) == ALT
    with StreamClient(served.grpc_target, model=ALT, timeout=20) as stream:
        assert stream.lift_batch(POSE_2D[None])[0].model_id == ALT
        assert [r.result.model_id for r in stream.stream([POSE_2D, POSE_2D]) if r.result] == [ALT, ALT]
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps({"keypoints": POSE_2D.tolist()}))
    assert repnet(["lift", str(poses), "--url", served.http_url, "--model", ALT]) == 0
    assert json.loads(capsys.readouterr().out)["model_id"] == ALT
    assert repnet(["lift", str(poses), "--url", served.http_url, "--model", "nope"]) == EXIT_REJECTED
    assert "unknown model 'nope'" in capsys.readouterr().err
