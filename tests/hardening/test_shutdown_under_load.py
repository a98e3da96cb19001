"""SIGTERM to `repnet serve` under HTTP, gRPC and stream load: every accepted request is answered."""

from __future__ import annotations

import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import httpx
import numpy as np

from bench.server import ServiceProcess
from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from tests.conftest import POSE_2D

HTTP_CLIENTS = 6
GRPC_CLIENTS = 3
STREAMS = 2
STREAM_FRAMES = 600
POSES_PER_REQUEST = 32  # long enough runs that several requests are in flight at SIGTERM


@dataclass(frozen=True)
class Call:
    transport: str  # "http" or "grpc"
    start: float  # time.monotonic() when the client began the call
    end: float
    outcome: str  # "ok", "wrong_answer", an HTTP status, an httpx error name or a gRPC code name
    refused_at: float | None = None  # HTTP: when the TCP connect failed (the server never accepted it)
    detail: str = ""  # the error message, for the failure report


def poses(seed: int) -> np.ndarray:
    """(POSES_PER_REQUEST, 17, 2) distinct poses: an answer can be checked against its request."""
    shift = np.random.default_rng(seed).uniform(-200, 200, (POSES_PER_REQUEST, 1, 2))
    return POSE_2D + shift


def _right(reprojection: np.ndarray, sent: np.ndarray) -> str:
    return "ok" if np.allclose(reprojection.mean(axis=1), sent.mean(axis=1), atol=0.05) else "wrong_answer"


def http_call(client: httpx.Client, seed: int) -> Call:
    """POST /lift on a new connection; a failed TCP connect is recorded with its time."""
    refused_at: float | None = None

    def trace(event: str, info: dict[str, Any]) -> None:
        nonlocal refused_at
        if event == "connection.connect_tcp.failed":
            refused_at = time.monotonic()

    sent = poses(seed)
    body = {"poses": [{"keypoints": p.tolist()} for p in sent]}
    start = time.monotonic()
    try:
        response = client.post("/lift", json=body, extensions={"trace": trace})
    except httpx.TransportError as err:
        return Call("http", start, time.monotonic(), type(err).__name__, refused_at, str(err))
    end = time.monotonic()
    if response.status_code != 200:
        return Call("http", start, end, str(response.status_code))
    return Call(
        "http", start, end, _right(np.array([p["reprojection"] for p in response.json()["poses"]]), sent)
    )


def grpc_call(stub: lifter_pb2_grpc.PoseLifterStub, seed: int) -> Call:
    sent = poses(seed)
    request = lifter_pb2.LiftRequest(poses=[lifter_pb2.Pose2D(keypoints=p.ravel().tolist()) for p in sent])
    start = time.monotonic()
    try:
        reply = stub.Lift(request, timeout=30)
    except grpc.RpcError as err:
        return Call("grpc", start, time.monotonic(), err.code().name, detail=str(err.details()))
    reprojection = np.array([np.reshape(p.reprojection, (17, 2)) for p in reply.poses])
    return Call("grpc", start, time.monotonic(), _right(reprojection, sent))


def keep_calling(call: Callable[[int], Call], seed: int, stop: threading.Event, calls: list[Call]) -> None:
    """Call until stopped or refused: refusal means the server no longer accepts work."""
    while not stop.is_set():
        calls.append(call(seed))
        seed += 1000
        if calls[-1].outcome != "ok":
            return


def http_client(url: str, seed: int, stop: threading.Event, calls: list[Call]) -> None:
    # No keep-alive: every request opens a new connection, so requests race the listener's close.
    limits = httpx.Limits(max_keepalive_connections=0)
    with httpx.Client(base_url=url, timeout=30, limits=limits) as client:
        keep_calling(lambda s: http_call(client, s), seed, stop, calls)


def stream(target: str, offset: int, answers: list[lifter_pb2.LiftFrameResult], errors: list[str]) -> None:
    def frames() -> Iterator[lifter_pb2.LiftFrame]:
        for i in range(STREAM_FRAMES):
            time.sleep(0.004)  # a paced camera: the stream spans the SIGTERM
            pose = lifter_pb2.Pose2D(keypoints=(POSE_2D + [offset + i * 0.1, 0.0]).ravel().tolist())
            yield lifter_pb2.LiftFrame(frame_id=i, pose=pose)

    with grpc.insecure_channel(target) as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        try:
            answers.extend(stub.LiftStream(frames(), timeout=60))
        except grpc.RpcError as err:
            errors.append(f"{err.code().name}: {err.details()}")


def not_accepted(call: Call, sigterm_at: float) -> bool:
    """Refused without being taken, which the server may do only once SIGTERM was sent: an HTTP
    connection refused (the listener was closed), or a gRPC call ended UNAVAILABLE (the server
    had gone away) or CANCELLED (gRPC core cancels calls that reach it once its shutdown began,
    before any handler sees them). That no handler took a refused gRPC call is checked against the
    server's own count of answered requests."""
    if call.transport == "http":
        return call.refused_at is not None and call.refused_at > sigterm_at
    return call.outcome in ("UNAVAILABLE", "CANCELLED") and call.end > sigterm_at


def answered_by_server(log: str) -> dict[tuple[str, str, str], int]:
    """(transport, method, outcome) -> count, from the service's last such log line (with workers,
    the supervisor's, which adds up every worker's)."""
    lines = re.findall(r"stopped; requests answered: (.*)", log)
    assert lines, log[-4000:]
    return {(t, m, o): int(n) for t, m, o, n in re.findall(r"(\w+) (\w+) (\w+)=(\d+)", lines[-1])}


def test_sigterm_under_load_answers_every_accepted_request_and_exits_0(tmp_path: Path) -> None:
    """Every HTTP request whose connection the server accepted gets 200 with its own poses (a refused
    connection after SIGTERM is no loss: the server never took the request), every gRPC call a
    handler took gets OK, open streams answer every frame, and the exit status is 0."""
    log = tmp_path / "service.log"
    flags = ("--intra-op-threads", "1", "--shutdown-grace-s", "30", "--log-level", "info")
    service = ServiceProcess(*flags, log=log).start()
    stop = threading.Event()
    calls: list[list[Call]] = [[] for _ in range(HTTP_CLIENTS + GRPC_CLIENTS)]
    streamed: list[list[lifter_pb2.LiftFrameResult]] = [[] for _ in range(STREAMS)]
    stream_errors: list[str] = []
    channel = grpc.insecure_channel(service.target)
    stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
    workers = [
        threading.Thread(target=http_client, args=(service.url, 100 * i, stop, calls[i]))
        for i in range(HTTP_CLIENTS)
    ] + [
        threading.Thread(
            target=keep_calling, args=(lambda seed: grpc_call(stub, seed), 100 * i, stop, calls[i])
        )
        for i in range(HTTP_CLIENTS, HTTP_CLIENTS + GRPC_CLIENTS)
    ] + [
        threading.Thread(target=stream, args=(service.target, 50 * i, streamed[i], stream_errors))
        for i in range(STREAMS)
    ]  # fmt: skip
    try:
        for worker in workers:
            worker.start()
        time.sleep(1.0)
        sigterm_at = time.monotonic()
        status = service.terminate(timeout=60)
        stop.set()
        for worker in workers:
            worker.join(timeout=60)
    finally:
        stop.set()
        channel.close()
        service.kill()
    assert status == 0, log.read_text()[-4000:]
    assert not any(worker.is_alive() for worker in workers), "a client hung after the server exited"
    everything = [c for per_client in calls for c in per_client]
    # Each call was answered right, or refused after SIGTERM without the server taking it. A call
    # whose connection was accepted and then dropped, answered wrongly, or refused before SIGTERM fails.
    lost = [
        (c.transport, c.outcome, round(c.start - sigterm_at, 3), round(c.end - sigterm_at, 3), c.detail)
        for c in everything
        if c.outcome != "ok" and not not_accepted(c, sigterm_at)
    ]
    assert not lost, f"(transport, outcome, start, end relative to SIGTERM, detail): {lost}"
    drained = [c for c in everything if c.start < sigterm_at < c.end and c.outcome == "ok"]
    assert {c.transport for c in drained} == {"http", "grpc"}, "no request was in flight at SIGTERM"
    # Every request a handler took was answered right and reached its client: the server counted
    # (outcome "ok") exactly the calls the clients got answered, and nothing else.
    got = Counter(c.transport for c in everything if c.outcome == "ok")
    expected = {("http", "Lift", "ok"): got["http"], ("grpc", "Lift", "ok"): got["grpc"],
                ("grpc", "LiftStream", "ok"): STREAMS * STREAM_FRAMES}  # fmt: skip
    assert answered_by_server(log.read_text()) == expected
    assert not stream_errors
    for i, answers in enumerate(streamed):  # open streams were drained: every frame answered in order
        assert [a.frame_id for a in answers] == list(range(STREAM_FRAMES))
        assert all(a.HasField("pose") for a in answers)
        reprojection = np.array([np.reshape(a.pose.reprojection, (17, 2)) for a in answers])
        expected = np.array([POSE_2D.mean(axis=0) + [50 * i + k * 0.1, 0.0] for k in range(STREAM_FRAMES)])
        np.testing.assert_allclose(reprojection.mean(axis=1), expected, atol=0.05)
    assert "shutting down" in log.read_text() and "stopped" in log.read_text()
