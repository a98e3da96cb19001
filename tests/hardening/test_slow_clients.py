"""F2-F4: slow clients cannot take the service down.

On main (uvicorn starts its keep-alive timer only after a first answer):
- F2: 130 connections that sent POST /lift headers and one body byte held all 128 in-flight slots,
  and every other /lift got 503 for as long as they stayed;
- F3: a header line that never ends was buffered without limit (RSS 164 -> 356 MB for 4 of them);
- F4: 1000 connections that sent nothing were never closed, and at `ulimit -n 1024` /readyz, /lift
  and gRPC health all failed.
Now a /lift takes its slot once its body has arrived, a body slower than its deadline gets 408, the
header block is capped (431), a connection without a complete request within the header timeout is
closed, and open connections are capped below the open-file limit, the idle longest closed first.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from bench.probe import f3_header_lines
from bench.server import ServiceProcess
from bench.slow_clients import ATTACKS, summary, under_attack
from tests.conftest import POSE_2D

BODY = {"poses": [{"keypoints": POSE_2D.tolist()}]}
TIMEOUT_S = 2.0  # the header and body timeouts of the short-timer services below


def slow_body(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sock.sendall(b"POST /lift HTTP/1.1\r\nhost: 127.0.0.1\r\ncontent-length: 1000\r\n\r\n{")
    return sock


def read_all(sock: socket.socket) -> bytes:
    answer = b""
    try:
        while chunk := sock.recv(65536):
            answer += chunk
    except ConnectionResetError:
        pass
    return answer


@pytest.fixture(scope="module")
def short_timers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    log = tmp_path_factory.mktemp("slow") / "service.log"
    flags = ("--intra-op-threads", "1", "--http-max-in-flight", "8", "--http-header-timeout-s",
             str(TIMEOUT_S), "--http-body-timeout-s", str(TIMEOUT_S))  # fmt: skip
    with ServiceProcess(*flags, log=log) as service:
        yield service


def test_slow_bodies_hold_no_lift_slot_and_get_408(short_timers: ServiceProcess) -> None:
    attackers = [slow_body(short_timers.http_port) for _ in range(20)]  # more than the 8 slots
    try:
        time.sleep(0.5)
        for _ in range(3):
            response = httpx.post(short_timers.url + "/lift", json=BODY, timeout=30)
            assert response.status_code == 200, response.text[:200]
        start = time.monotonic()
        answers = [read_all(sock) for sock in attackers]  # until the server closes each
        assert time.monotonic() - start < TIMEOUT_S + 15
        for answer in answers:
            assert answer.startswith(b"HTTP/1.1 408 "), answer[:200]
            assert b"too slowly" in answer
    finally:
        for sock in attackers:
            sock.close()


def test_a_header_block_past_the_cap_gets_431_and_costs_no_memory(short_timers: ServiceProcess) -> None:
    f3_header_lines(short_timers)  # 4 header lines of up to 32 MiB (the cap is 64 KiB): 431 each


def test_connections_without_a_whole_request_are_closed_after_the_header_timeout(
    short_timers: ServiceProcess,
) -> None:
    pid = short_timers.pid
    baseline = len(os.listdir(f"/proc/{pid}/fd"))
    silent = [socket.create_connection(("127.0.0.1", short_timers.http_port), timeout=30) for _ in range(100)]
    half = [socket.create_connection(("127.0.0.1", short_timers.http_port), timeout=30) for _ in range(20)]
    for sock in half:
        sock.sendall(b"GET /readyz HTTP/1.1\r\nhost: 127.0.0.1\r\nx-half: ab")
    try:
        assert [read_all(s) for s in silent] == [b""] * 100  # closed, with nothing to say
        assert all(read_all(s).startswith(b"HTTP/1.1 408 ") for s in half)
        deadline = time.monotonic() + 10
        while len(os.listdir(f"/proc/{pid}/fd")) > baseline + 5:
            assert time.monotonic() < deadline, (baseline, len(os.listdir(f"/proc/{pid}/fd")))
            time.sleep(0.1)
    finally:
        for sock in silent + half:
            sock.close()


def test_at_ulimit_1024_a_thousand_idle_connections_leave_health_and_lift_answering(
    tmp_path: Path,
) -> None:
    log = tmp_path / "service.log"
    module = "tests.hardening.nofile_service"
    with ServiceProcess("--intra-op-threads", "1", log=log, module=module) as service:
        idle = []
        try:
            for i in range(1200):
                sock = socket.create_connection(("127.0.0.1", service.http_port), timeout=30)
                if i >= 1000:
                    sock.sendall(b"GET /readyz HTTP/1.1\r\nhost: 127.0.0.1\r\nx-half: ab")
                idle.append(sock)
            assert len(os.listdir(f"/proc/{service.pid}/fd")) < 1024
            with grpc.insecure_channel(service.target) as channel:
                health = health_pb2_grpc.HealthStub(channel)
                for _ in range(3):
                    start = time.monotonic()
                    assert httpx.get(service.url + "/readyz", timeout=1.0).status_code == 200
                    reply = health.Check(health_pb2.HealthCheckRequest(), timeout=1.0)
                    assert reply.status == health_pb2.HealthCheckResponse.SERVING
                    assert httpx.post(service.url + "/lift", json=BODY, timeout=5).status_code == 200
                    assert time.monotonic() - start < 5
        finally:
            for sock in idle:
                sock.close()
        assert "Too many open files" not in log.read_text()


@pytest.fixture(scope="module")
def default_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    log = tmp_path_factory.mktemp("attacked") / "service.log"
    with ServiceProcess(log=log) as service:
        yield service


@pytest.mark.parametrize("attack", ATTACKS)
def test_under_each_attack_a_normal_client_and_the_probes_are_served(
    default_service: ServiceProcess, attack: str
) -> None:
    """The issue's target is p99 < 100 ms and probes within 1 s (bench.slow_clients measures it,
    docs/BENCHMARKS.md); on a shared 2-core CI machine the p99 gets a margin."""
    found = summary(under_attack(default_service, attack, duration=4.0))
    assert set(found["lift_statuses"]) == {"200"}, found
    assert found["lift_ms"]["p99"] < 250, found
    assert found["readyz_failed"] == 0 and found["readyz_worst_ms"] < 1000, found
    assert found["health_failed"] == 0 and found["health_worst_ms"] < 1000, found
