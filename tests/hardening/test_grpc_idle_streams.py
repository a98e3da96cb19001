"""Idle streams cannot lock out gRPC: streams and Lift calls have limits of their own, refusals
are counted, health always answers, and an idle stream is closed after its timeout."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.runtime.lifter import Lifter
from repnet.server.app import Service
from repnet.server.auth import client_identity
from repnet.server.config import Settings
from tests.conftest import POSE_2D, GatedLifter
from tests.hardening.conftest import running

MAX_STREAMS = 4
MAX_UNARY = 4
IDLE_S = 4.0
POSE = lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist())


@pytest.fixture
def limited(lifter: Lifter) -> Iterator[tuple[Service, GatedLifter]]:
    gated = GatedLifter(lifter)
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1,
                        grpc_workers=MAX_UNARY, grpc_max_streams=MAX_STREAMS,
                        grpc_max_streams_per_client=MAX_STREAMS, stream_idle_timeout_s=IDLE_S,
                        shutdown_grace_s=2)  # fmt: skip
    try:
        with running(settings, gated) as service:
            yield service, gated
    finally:
        gated.gate.set()


def one_frame_then_quiet(quiet: threading.Event) -> Iterator[lifter_pb2.LiftFrame]:
    """What an idle client sends: one frame, then nothing (without closing its side)."""
    yield lifter_pb2.LiftFrame(frame_id=1, pose=POSE)
    quiet.wait(60)


def check_health(channel: grpc.Channel) -> None:
    stub = health_pb2_grpc.HealthStub(channel)  # type: ignore[no-untyped-call]
    reply = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=2)
    assert reply.status == health_pb2.HealthCheckResponse.SERVING


def expect_refused(call: Callable[[], object]) -> None:
    with pytest.raises(grpc.RpcError) as refused:
        call()
    assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, refused.value.details()


def test_idle_streams_do_not_lock_out_lift_or_health(limited: tuple[Service, GatedLifter]) -> None:
    service, gated = limited
    quiet = threading.Event()
    with grpc.insecure_channel(f"127.0.0.1:{service.grpc_server.port}") as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        try:
            streams = [stub.LiftStream(one_frame_then_quiet(quiet), timeout=60) for _ in range(MAX_STREAMS)]
            for stream in streams:
                assert next(stream).WhichOneof("result") == "pose"
            opened = time.monotonic()
            start = time.perf_counter()
            for _ in range(2):
                expect_refused(lambda: next(stub.LiftStream(one_frame_then_quiet(quiet), timeout=30)))
            assert time.perf_counter() - start < 3.0  # refused at once
            check_health(channel)
            assert len(stub.Lift(lifter_pb2.LiftRequest(poses=[POSE]), timeout=10).poses) == 1

            # Lift calls have their own limit, and health still answers when it is reached.
            gated.gate.clear()
            with ThreadPoolExecutor(MAX_UNARY) as pool:
                held = [
                    pool.submit(stub.Lift, lifter_pb2.LiftRequest(poses=[POSE]), timeout=30)
                    for _ in range(MAX_UNARY)
                ]
                deadline = time.monotonic() + 10
                value = service.metrics.registry.get_sample_value
                while value("repnet_in_flight_requests", {"transport": "grpc"}) < MAX_UNARY:
                    assert time.monotonic() < deadline, "the held Lift calls never arrived"
                    time.sleep(0.02)
                expect_refused(lambda: stub.Lift(lifter_pb2.LiftRequest(poses=[POSE]), timeout=10))
                check_health(channel)
                gated.gate.set()
                assert all(len(f.result(timeout=30).poses) == 1 for f in held)

            # The idle streams are closed after IDLE_S, with a status that says why.
            for stream in streams:
                with pytest.raises(grpc.RpcError) as closed:
                    next(stream)
                assert closed.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
                assert "idle" in closed.value.details()
            assert time.monotonic() - opened < IDLE_S + 10
            (result,) = stub.LiftStream(iter([lifter_pb2.LiftFrame(frame_id=2, pose=POSE)]), timeout=10)
            assert result.WhichOneof("result") == "pose"
        finally:
            quiet.set()
    value = service.metrics.registry.get_sample_value
    refused = {"transport": "grpc", "outcome": "overloaded"}
    assert value("repnet_requests_total", {**refused, "method": "LiftStream"}) == 2
    assert value("repnet_requests_total", {**refused, "method": "Lift"}) == 1
    assert value("repnet_idle_streams_closed_total") == MAX_STREAMS


def first_result_code(stub: lifter_pb2_grpc.PoseLifterStub, frame_id: int) -> grpc.StatusCode:
    """The status of a one-frame stream: OK once its frame is lifted, else why it was refused."""
    try:
        stream = stub.LiftStream(iter([lifter_pb2.LiftFrame(frame_id=frame_id, pose=POSE)]), timeout=30)
        return grpc.StatusCode.OK if next(stream).WhichOneof("result") == "pose" else grpc.StatusCode.UNKNOWN
    except grpc.RpcError as err:
        return err.code()  # type: ignore[no-any-return]


def test_one_client_holds_half_the_streams_and_gets_a_slot_back_when_one_ends(lifter: Lifter) -> None:
    """Issue 30: one client could hold all 64 stream slots (and with them every track). A client is
    its address here (no API keys): the default per-client limit is half of grpc_max_streams."""
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1, grpc_max_streams=8,
                        shutdown_grace_s=1)  # fmt: skip
    quiet = threading.Event()
    with (
        running(settings, lifter) as service,
        grpc.insecure_channel(f"127.0.0.1:{service.grpc_server.port}") as a,
    ):
        stub = lifter_pb2_grpc.PoseLifterStub(a)  # type: ignore[no-untyped-call]
        try:
            held = [stub.LiftStream(one_frame_then_quiet(quiet), timeout=60) for _ in range(4)]
            assert all(next(s).WhichOneof("result") == "pose" for s in held)
            with pytest.raises(grpc.RpcError) as refused:  # a fifth from the same address
                next(stub.LiftStream(one_frame_then_quiet(quiet), timeout=30))
            assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "this client has too many open streams (limit 4)" in refused.value.details()
            held[0].cancel()  # a stream that ends gives its slot back
            deadline = time.monotonic() + 10
            while (code := first_result_code(stub, 2)) == grpc.StatusCode.RESOURCE_EXHAUSTED:
                assert time.monotonic() < deadline, "the ended stream's slot was never given back"
                time.sleep(0.1)
            assert code == grpc.StatusCode.OK
        finally:
            quiet.set()


def test_a_client_is_its_key_or_its_address_without_the_port() -> None:
    assert client_identity(None, "ipv4:10.0.0.7:51234") == client_identity(None, "ipv4:10.0.0.7:40000")
    assert client_identity(None, "ipv6:[::1]:5000") == "ipv6:[::1]"
    one, two = (
        client_identity("Bearer k1", "ipv4:10.0.0.7:1"),
        client_identity("bearer k2", "ipv4:10.0.0.7:1"),
    )
    assert one != two and one.startswith("key:") and "k1" not in one  # the key itself is kept nowhere
    assert client_identity("Bearer k1", "ipv4:10.9.9.9:2") == one  # a key is one client wherever it is
