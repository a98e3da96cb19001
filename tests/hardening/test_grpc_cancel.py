"""F6: a cancelled or expired gRPC call drops all of its queued chunks and counts as "cancelled".

On main, 40 x Lift(1024 poses) with a 20 ms deadline computed 8,704 poses for no useful answer:
awaiting the chunks one by one cancelled only the first one's future, the others stayed queued
(and took room: 12-16 of the calls got RESOURCE_EXHAUSTED), and the cancels counted as "error".
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from bench.probe import expire_lifts
from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.inputs import ModelInput
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.server.config import Settings
from repnet.server.metrics import Metrics
from tests.conftest import POSE_2D, GatedLifter
from tests.hardening.conftest import running
from tests.service.test_engine import model_input as model_input_of


def model_input(n: int) -> ModelInput:
    return model_input_of(*[POSE_2D] * n)


def test_a_cancelled_lift_takes_every_queued_chunk_out_of_the_queue(
    engine_factory: Callable[..., LiftBatcher], gated: GatedLifter
) -> None:
    engine = engine_factory(gated, max_batch=8, queue_size=64)
    gated.gate.clear()  # the first run blocks: everything after it stays queued
    blocker = engine.submit(model_input(1), "grpc")
    assert gated.entered.wait(10)

    async def cancel_a_lift() -> None:
        task = asyncio.create_task(engine.lift_async(model_input(40), "grpc"))  # 5 chunks of 8
        await asyncio.sleep(0.05)
        assert engine._queue.rows == 40
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(cancel_a_lift())
    assert engine._queue.rows == 0 and not engine._queue  # all five chunks, not only the first
    gated.gate.set()
    blocker[0].result(timeout=10)
    engine.lift(model_input(2), "grpc")  # the engine goes on
    assert gated.batches == [1, 2]  # none of the cancelled poses was computed


class SlowLifter(Lifter):
    """The real lifter, 200 ms slower per run, counting the poses it computes."""

    def __init__(self, inner: Lifter) -> None:
        super().__init__(inner.session, inner.path)
        self.poses = 0
        self.lock = threading.Lock()

    def lift(self, keypoints_2d: np.ndarray, visibility: np.ndarray):  # type: ignore[no-untyped-def]
        time.sleep(0.2)
        with self.lock:
            self.poses += int(keypoints_2d.shape[0])
        return super().lift(keypoints_2d, visibility)


@pytest.fixture
def slow_service(lifter: Lifter) -> Iterator[tuple[str, Metrics, SlowLifter]]:
    slow = SlowLifter(lifter)
    # Room for all 40 calls (Lift calls in progress, queued poses): the calls end by their deadline,
    # never by a limit (on a fast machine every handler starts and queues its poses within 250 ms).
    # The calls share one channel, one client of the fair queue: its share (a quarter) holds them all.
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1, shutdown_grace_s=1,
                        max_batch=256, queue_size=4 * 65536, grpc_workers=64)  # fmt: skip
    with running(settings, slow) as service:
        yield f"127.0.0.1:{service.grpc_server.port}", service.metrics, slow


def test_lifts_past_their_deadline_are_dropped_and_counted_as_cancelled(
    slow_service: tuple[str, Metrics, SlowLifter],
) -> None:
    target, metrics, slow = slow_service
    calls, poses = 40, 1024
    request = lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist())] * poses)
    # 250 ms: long enough for the handlers to start even on a loaded machine (the probe uses the
    # attack's 20 ms), short beside the 40 x 4 runs of 200 ms the calls would need.
    codes = expire_lifts(target, request, calls, 0.25)
    time.sleep(2.0)  # what is still queued would run now, and the handlers have ended

    def counted(outcome: str) -> float:
        labels = {"transport": "grpc", "method": "Lift", "outcome": outcome}
        return metrics.registry.get_sample_value("repnet_requests_total", labels) or 0.0

    assert "RESOURCE_EXHAUSTED" not in codes, codes
    # Calls whose deadline passed before their handler started are ended by grpc itself, uncounted.
    assert counted("error") == 0 and counted("overloaded") == 0, codes
    assert counted("cancelled") >= 1 and counted("cancelled") + counted("ok") <= calls, codes
    # Only runs that had started when their calls expired were computed: at most a few runs of the
    # calls' short lives, not the 40 x 1024 poses sent (main: 8,704).
    assert slow.poses <= 6 * 256, slow.poses
