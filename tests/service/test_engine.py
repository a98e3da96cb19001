"""Dynamic batching: runs shared across transports, own answers, chunking, overload, drain."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import grpc
import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client import CollectorRegistry

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.core.errors import ModelNotReady, Overloaded
from repnet.core.inputs import ModelInput, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.pipeline import Job, Lifted
from repnet.runtime.window import BUSY_TO_WAIT, batch_window
from repnet.server.app import limits_of
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from tests.conftest import POSE_2D, GatedLifter, GrpcHandle, build_app, build_grpc_server
from tests.service.invalid_inputs import to_proto_pose


@pytest.fixture
def engine(engine_factory: Callable[..., LiftBatcher], gated: GatedLifter) -> LiftBatcher:
    """Shared by `client` and `grpc_handle`: real runs, held back while the gate is closed."""
    return engine_factory(gated, max_batch=64, max_wait_s=0.0, queue_size=8)


def variant(i: int) -> np.ndarray:
    """A distinct valid pose per caller."""
    return POSE_2D * (1 + 0.05 * i) + [7 * i, -3 * i]


def model_input(*poses: np.ndarray) -> ModelInput:
    return prepare_poses([PoseInput(p, np.ones(17, bool)) for p in poses], limits_of(Settings())).check()


def wait_until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + 10
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def queued(registry: CollectorRegistry) -> float:
    return sum(s.value for m in registry.collect() if m.name == "repnet_batch_queue_poses" for s in m.samples)


def test_concurrent_http_and_grpc_requests_share_one_run(
    client: TestClient,
    grpc_handle: GrpcHandle,
    gated: GatedLifter,
    lifter: Lifter,
    registry: CollectorRegistry,
) -> None:
    gated.gate.clear()
    with ThreadPoolExecutor(max_workers=7) as pool:
        first = pool.submit(client.post, "/lift", json={"keypoints": variant(0).tolist()})
        wait_until(gated.entered.is_set, "the first run")  # the worker is busy: the rest queue up
        http = [pool.submit(client.post, "/lift", json={"keypoints": variant(i).tolist()}) for i in (1, 2, 3)]
        rpc = [pool.submit(grpc_handle.stub.Lift, _request(variant(i)), timeout=20) for i in (4, 5, 6)]
        wait_until(lambda: queued(registry) == 6, "six queued poses")
        gated.gate.set()
        answers: list[Any] = [first.result().json()["poses"][0]["pose_3d"]]
        answers += [f.result().json()["poses"][0]["pose_3d"] for f in http]
        answers += [np.reshape(f.result().poses[0].pose_3d, (17, 3)) for f in rpc]
    assert gated.batches == [1, 6]
    model = {"model": lifter.info.model_id}
    assert registry.get_sample_value("repnet_batch_size_poses_bucket", {"le": "4.0", **model}) == 1  # one > 4
    assert registry.get_sample_value("repnet_batch_size_poses_count", model) == 2
    for i, answer in enumerate(answers):  # each caller gets the answer to its own pose
        alone = lifter.lift(model_input(variant(i)).keypoints_2d, np.ones((1, 17), bool)).pose_3d[0]
        np.testing.assert_allclose(answer, alone, rtol=1e-4, atol=1e-2)
    for transport in ("http", "grpc"):
        assert registry.get_sample_value(
            "repnet_batch_queue_wait_seconds_count", {"transport": transport, **model}
        )


def _request(points: np.ndarray) -> Any:
    from repnet._proto.repnet.v1 import lifter_pb2

    return lifter_pb2.LiftRequest(poses=[to_proto_pose({"keypoints": points.tolist()})])


def test_full_queue_answers_503_and_resource_exhausted_at_once(
    client: TestClient,
    grpc_handle: GrpcHandle,
    gated: GatedLifter,
    registry: CollectorRegistry,
) -> None:
    gated.gate.clear()
    with ThreadPoolExecutor(max_workers=2) as pool:
        first = pool.submit(client.post, "/lift", json={"keypoints": variant(0).tolist()})
        wait_until(gated.entered.is_set, "the first run")
        filler = pool.submit(client.post, "/lift", json={"poses": [{"keypoints": variant(1).tolist()}] * 8})
        wait_until(lambda: queued(registry) == 8, "a full queue")
        start = time.monotonic()
        refused = client.post("/lift", json={"keypoints": variant(2).tolist()})
        with pytest.raises(grpc.RpcError) as rpc_error:
            grpc_handle.stub.Lift(_request(variant(3)), timeout=10)
        assert time.monotonic() - start < 5  # refused at once, not after a timeout
        gated.gate.set()
        assert first.result().status_code == 200 and filler.result().status_code == 200
    assert refused.status_code == 503 and "queue is full" in refused.json()["detail"]
    assert refused.headers["retry-after"] == "1"
    assert rpc_error.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "queue is full" in (rpc_error.value.details() or "")
    for transport in ("http", "grpc"):
        labels = {"transport": transport, "method": "Lift", "outcome": "overloaded"}
        assert registry.get_sample_value("repnet_requests_total", labels) == 1
    assert client.post("/lift", json={"keypoints": variant(4).tolist()}).status_code == 200  # recovered


def test_large_request_is_run_in_chunks_and_answered_in_order(
    engine_factory: Callable[..., LiftBatcher],
    gated: GatedLifter,
    lifter: Lifter,
) -> None:
    engine = engine_factory(gated, max_batch=4, queue_size=16)
    inputs = model_input(*(variant(i) for i in range(10)))
    prediction = engine.lift(inputs, "test")
    assert max(gated.batches) == 4 and sum(gated.batches) == 10
    alone = lifter.lift(inputs.keypoints_2d, inputs.visible)
    np.testing.assert_allclose(prediction.pose_3d, alone.pose_3d, rtol=1e-4, atol=1e-2)


def test_another_clients_request_waits_for_one_run_of_a_large_prediction_not_all(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter
) -> None:
    # A temporal request's poses are predicted max_batch at a time, each queued apart: a one-pose
    # request of another client rides along with the next run instead of waiting for all of them.
    engine = engine_factory(gated, max_batch=4, queue_size=64)
    gated.gate.clear()
    large = engine.submit(model_input(*(variant(i) for i in range(12))), "test", source="large")
    wait_until(gated.entered.is_set, "the large prediction's first run")
    small = engine.submit(model_input(variant(20)), "test", source="small")
    done: list[str] = []
    for name, futures in (("large", large), ("small", small)):
        for future in futures:
            future.add_done_callback(lambda _, name=name: done.append(name))
    gated.gate.set()
    wait_until(lambda: len(done) == len(large) + len(small), "every answer")
    assert len(large) == 3 and done[-1] == "large" and done.index("small") < 2
    assert max(gated.batches) <= 5 and sum(gated.batches) == 13  # the small one rode along


def twelve_poses(*invalid: int) -> list[dict[str, Any]]:
    """12 distinct poses; those at `invalid` break a rule of the batch's input rules (3 of 17 joints
    visible, or every joint at one point)."""
    poses: list[dict[str, Any]] = [{"keypoints": variant(i).tolist()} for i in range(12)]
    for k, i in enumerate(invalid):
        keypoints: list[Any] = variant(i).tolist()
        poses[i] = {"keypoints": [p if j < 3 else None for j, p in enumerate(keypoints)]}
        if k % 2:
            poses[i] = {"keypoints": [[10.0, 20.0]] * 17}
    return poses


@pytest.mark.parametrize(
    "body",
    [
        {"poses": twelve_poses()},
        {"poses": twelve_poses(5, 9)},
        {"poses": twelve_poses(5, 9), "invalid_poses": "report"},
        {"poses": twelve_poses(*range(12)), "invalid_poses": "report"},
    ],
    ids=["valid", "refused", "report", "report-none-valid"],
)
def test_a_large_untracked_request_is_answered_in_parts_as_it_would_be_whole(
    engine_factory: Callable[..., LiftBatcher],
    gated: GatedLifter,
    lifter: Lifter,
    metrics: Metrics,
    settings: Settings,
    body: dict[str, Any],
) -> None:
    # More poses than a run holds: queued as parts of max_batch, each answered apart, their join
    # answered as the whole request would be (poses named by their index in the request).
    answers = []
    for engine in (engine_factory(gated, max_batch=4), engine_factory(lifter, max_batch=64)):
        with TestClient(build_app(engine, metrics, settings), base_url="http://localhost") as http:
            reply = http.post("/lift", json=body)
            answers.append((reply.status_code, reply.json()))
    valid = [p == {"keypoints": variant(i).tolist()} for i, p in enumerate(body["poses"])]
    runs = [sum(valid[a : a + 4]) for a in range(0, 12, 4)]
    assert gated.batches == [n for n in runs if n]  # a run per part, of its valid poses
    (status, parts), (whole_status, whole) = answers
    assert status == whole_status
    if status == 422:
        fields = [e["field"] for e in parts["detail"]]
        assert fields == [e["field"] for e in whole["detail"]]
        assert fields == ["poses[5].keypoints", "poses[9].keypoints"]
        return
    assert status == 200, parts
    if "errors" in whole:
        assert parts["errors"] == whole["errors"]
        assert sorted({e["pose"] for e in parts["errors"]}) == [i for i, ok in enumerate(valid) if not ok]
    assert [p is None for p in parts["poses"]] == [p is None for p in whole["poses"]]
    for mine, theirs in zip(parts["poses"], whole["poses"], strict=True):
        if theirs is not None:
            np.testing.assert_allclose(mine["pose_3d"], theirs["pose_3d"], rtol=1e-5, atol=1e-4)
            np.testing.assert_allclose(mine["camera"], theirs["camera"], rtol=1e-5, atol=1e-6)


def test_a_large_grpc_lift_is_answered_in_parts_as_it_would_be_whole(
    engine_factory: Callable[..., LiftBatcher],
    gated: GatedLifter,
    lifter: Lifter,
    metrics: Metrics,
    settings: Settings,
) -> None:
    request = lifter_pb2.LiftRequest(
        poses=[to_proto_pose(p) for p in twelve_poses(5, 9)],
        invalid_poses=lifter_pb2.INVALID_POSES_REPORT,
    )
    answers = []
    for engine in (engine_factory(gated, max_batch=4), engine_factory(lifter, max_batch=64)):
        server = build_grpc_server(engine, metrics, settings)
        server.start()
        try:
            with grpc.insecure_channel(f"localhost:{server.port}") as channel:
                stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
                answers.append(stub.Lift(request, timeout=30))
        finally:
            server.stop(0).wait()
    parts, whole = answers
    assert gated.batches == [4, 3, 3]
    assert [e.pose for e in parts.errors] == [5, 9] and list(parts.errors) == list(whole.errors)
    for mine, theirs in zip(parts.poses, whole.poses, strict=True):
        np.testing.assert_allclose(mine.pose_3d, theirs.pose_3d, rtol=1e-5, atol=1e-4)


def test_another_clients_request_waits_for_one_run_of_a_large_untracked_request_not_all(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter
) -> None:
    # A 12-pose request with max_batch 4 is queued as three parts: a one-pose request of another
    # client that comes during the first run runs next (before: after all three), and the large
    # request is answered once, whole, after its last part.
    engine = engine_factory(gated, max_batch=4, queue_size=64)
    gated.gate.clear()
    done: list[str] = []
    got: list[Any] = []

    def finish(name: str) -> Callable[[Lifted], Any]:
        def answer(lifted: Lifted) -> Lifted:
            done.append(name)
            return lifted

        return answer

    poses = [PoseInput(variant(i), np.ones(17, bool)) for i in range(12)]
    large = threading.Thread(target=lambda: got.append(engine.run(Job(finish("large"), poses), "test")))
    large.start()
    wait_until(gated.entered.is_set, "the large request's first run")
    small = engine.submit(Job(finish("small"), [PoseInput(variant(20), np.ones(17, bool))]), "test")
    gated.gate.set()
    large.join(10)
    assert small[0].result(10).prediction.pose_3d.shape == (1, 17, 3)
    assert done == ["small", "large"]  # the large one's finish ran once, on the join of its parts
    assert gated.batches == [4, 1, 4, 4]  # the small one ran after one of the large one's runs
    whole = got[0]
    assert len(whole.prepared.inputs) == 12 and whole.replies is not None and len(whole.replies) == 12
    alone = engine_factory(gated, max_batch=64).run(Job(lambda lifted: lifted, poses), "test")
    np.testing.assert_allclose(whole.prediction.pose_3d, alone.prediction.pose_3d, rtol=1e-5, atol=1e-4)


def test_close_finishes_queued_work_then_refuses_new(engine: LiftBatcher, gated: GatedLifter) -> None:
    gated.gate.clear()
    futures = engine.submit(model_input(variant(0)), "test")
    wait_until(gated.entered.is_set, "the first run")
    queued_futures = engine.submit(model_input(variant(1), variant(2)), "test")
    closing = threading.Thread(target=engine.close, kwargs={"timeout": 10})
    closing.start()
    wait_until(lambda: not engine.ready, "closing")
    with pytest.raises(ModelNotReady):
        engine.submit(model_input(variant(3)), "test")
    gated.gate.set()
    closing.join(10)
    assert len(futures[0].result(timeout=5)) == 1 and len(queued_futures[0].result(timeout=5)) == 2


def test_queue_overflow_raises_before_queueing(engine: LiftBatcher, gated: GatedLifter) -> None:
    gated.gate.clear()
    engine.submit(model_input(variant(0)), "test")
    wait_until(gated.entered.is_set, "the first run")
    engine.submit(model_input(*(variant(i) for i in range(8))), "test")
    with pytest.raises(Overloaded, match=r"8 of 8 poses waiting, 1 more requested"):
        engine.submit(model_input(variant(9)), "test")


def test_a_waiting_submit_gets_in_once_the_queue_has_room(engine: LiftBatcher, gated: GatedLifter) -> None:
    gated.gate.clear()
    engine.submit(model_input(variant(0)), "test")
    wait_until(gated.entered.is_set, "the first run")
    engine.submit(model_input(*(variant(i) for i in range(8))), "test")
    with ThreadPoolExecutor(1) as pool:
        waiting = pool.submit(engine.submit, model_input(variant(9)), "test", 10.0)
        time.sleep(0.2)
        assert not waiting.done()  # the queue is still full: it waits instead of failing
        gated.gate.set()
        prediction = waiting.result(timeout=10)[0].result(timeout=10)
    alone = model_input(variant(9))
    expected = engine.lifter.lift(alone.keypoints_2d, alone.visible)
    np.testing.assert_allclose(prediction.pose_3d, expected.pose_3d, atol=1e-3)


def test_a_waiting_submit_still_fails_when_no_room_comes(engine: LiftBatcher, gated: GatedLifter) -> None:
    gated.gate.clear()
    engine.submit(model_input(variant(0)), "test")
    wait_until(gated.entered.is_set, "the first run")
    engine.submit(model_input(*(variant(i) for i in range(8))), "test")
    start = time.monotonic()
    with pytest.raises(Overloaded, match=r"8 of 8 poses waiting"):
        engine.submit(model_input(variant(9)), "test", wait_s=0.3)
    assert 0.25 < time.monotonic() - start < 5


def test_an_awaiting_submit_gets_in_once_the_queue_has_room_or_fails_in_time(
    engine: LiftBatcher, gated: GatedLifter
) -> None:
    """submit_async waits like submit, but suspends its coroutine: the loop runs on meanwhile."""
    gated.gate.clear()
    engine.submit(model_input(variant(0)), "test")
    wait_until(gated.entered.is_set, "the first run")
    engine.submit(model_input(*(variant(i) for i in range(8))), "test")

    async def scenario() -> tuple[int, float]:
        ticks = 0

        async def tick() -> None:  # proves the event loop is free while a submit waits
            nonlocal ticks
            while True:
                await asyncio.sleep(0.01)
                ticks += 1

        ticker = asyncio.create_task(tick())
        start = time.monotonic()
        with pytest.raises(Overloaded, match=r"8 of 8 poses waiting"):
            await engine.submit_async(model_input(variant(9)), "test", wait_s=0.3)
        failed_after = time.monotonic() - start
        waiting = asyncio.create_task(engine.submit_async(model_input(variant(9)), "test", wait_s=10.0))
        await asyncio.sleep(0.2)
        assert not waiting.done()  # the queue is still full: it waits instead of failing
        gated.gate.set()
        (future,) = await asyncio.wait_for(waiting, 10)
        await asyncio.wrap_future(future)
        ticker.cancel()
        return ticks, failed_after

    ticks, failed_after = asyncio.run(scenario())
    assert 0.25 < failed_after < 5 and ticks >= 10


class FailingLifter(Lifter):
    def lift(self, keypoints_2d: np.ndarray, visibility: np.ndarray) -> Prediction:
        raise RuntimeError("session failed")


def test_a_failed_run_reaches_every_caller_and_the_worker_goes_on(
    engine_factory: Callable[..., LiftBatcher],
    lifter: Lifter,
) -> None:
    engine = engine_factory(FailingLifter(lifter.session, lifter.path), max_wait_s=0.05)
    futures = engine.submit(model_input(variant(0)), "test") + engine.submit(model_input(variant(1)), "test")
    for future in futures:
        with pytest.raises(RuntimeError, match="session failed"):
            future.result(timeout=10)
    with pytest.raises(RuntimeError):
        engine.lift(model_input(variant(2)), "test")


def test_an_idle_batcher_runs_a_lone_request_without_waiting(
    engine_factory: Callable[..., LiftBatcher], lifter: Lifter
) -> None:
    """max_wait only applies under load: a request to an idle engine does not wait for company."""
    engine = engine_factory(lifter, max_wait_s=5.0)
    engine.lift(model_input(variant(0)), "http")  # warm-up
    start = time.monotonic()
    engine.lift(model_input(variant(1)), "http")
    assert time.monotonic() - start < 2.5


def test_the_batching_window_follows_the_load() -> None:
    assert batch_window(0.004, 0.0) == 0.0 and batch_window(0.004, BUSY_TO_WAIT) == 0.0  # idle: at once
    assert batch_window(0.004, 1.0) == pytest.approx(0.004)  # always busy: the whole window
    middle = (1.0 + BUSY_TO_WAIT) / 2
    assert batch_window(0.004, middle) == pytest.approx(0.002)


def test_a_busy_batcher_lets_a_request_wait_for_company_and_an_idle_one_does_not(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter
) -> None:
    """Requests that arrive within the window of a busy batcher under load join one batch; a request
    that finds nothing queued runs at once."""
    engine = engine_factory(gated, max_batch=64, max_wait_s=1.0, queue_size=64)
    engine.lift(model_input(variant(0)), "http")
    engine.lift(model_input(variant(1)), "http")  # idle: two batches of one
    engine.window.busy = 1.0  # as after runs that took all of its time
    gated.gate.clear()
    gated.entered.clear()
    running = engine.submit(model_input(variant(2)), "http")
    wait_until(gated.entered.is_set, "the run to start")
    first = engine.submit(model_input(variant(3)), "http")  # queued during a run: load
    gated.gate.set()
    running[0].result(timeout=10)
    second = engine.submit(model_input(variant(4)), "http")  # after the run, within the window
    assert len(first[0].result(timeout=10)) == 1 and len(second[0].result(timeout=10)) == 1
    assert gated.batches == [1, 1, 1, 2]
    engine.lift(model_input(variant(5)), "http")  # alone again: at once, busy or not
    assert gated.batches[-1] == 1
