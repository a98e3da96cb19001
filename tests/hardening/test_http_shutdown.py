"""The HTTP server's shutdown answers connections it had not yet accepted, or not yet read a request from."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from repnet.runtime.lifter import Lifter
from repnet.server.app import Service, build_service
from repnet.server.config import Settings
from repnet.server.http.server import FIRST_REQUEST_WAIT_S
from tests.conftest import POSE_2D


@pytest.fixture
def service(lifter: Lifter) -> Iterator[Service]:
    """Both servers built, neither started: the test drives the HTTP server's event loop itself."""
    service = build_service(Settings(host="127.0.0.1", http_port=0, grpc_port=0, shutdown_grace_s=5), lifter)
    yield service
    service.engine.close(5)


def lift_request(shift: float) -> bytes:
    body = json.dumps({"poses": [{"keypoints": (POSE_2D + shift).tolist()}]}).encode()
    head = (
        "POST /lift HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}"
    )
    return head.encode() + b"\r\n\r\n" + body


def read_answer(client: socket.socket) -> tuple[int, bytes]:
    """(status, body) of the one answer on `client`, read until the server closes the connection."""
    data = b"".join(iter(lambda: client.recv(1 << 16), b""))
    head, _, body = data.partition(b"\r\n\r\n")
    return (int(head.split()[1]) if head else 0), body


async def shut_down_with_clients_waiting(
    service: Service,
) -> tuple[list[socket.socket], socket.socket, float]:
    """Start the HTTP server, open connections it cannot accept yet, then shut it down.

    Returns the clients that sent a request, a client that never sends one, and the shutdown's seconds.
    """
    server = service.http
    server.config.load()  # what uvicorn's serve() does before startup()
    server.lifespan = server.config.lifespan_class(server.config)
    await server.startup()
    port = server.servers[0].sockets[0].getsockname()[1]
    # The event loop runs this coroutine, so it accepts none of these connections: they wait in the
    # kernel's listen backlog (established, their requests sent) when the shutdown begins.
    clients = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(4)]
    for i, client in enumerate(clients[:3]):
        client.sendall(lift_request(10.0 * i))
    # The fourth sends its request only once the shutdown has begun.
    threading.Timer(0.3, clients[3].sendall, args=(lift_request(30.0),)).start()
    silent = socket.create_connection(("127.0.0.1", port), timeout=10)  # never sends a request
    start = time.monotonic()
    await server.shutdown()
    return clients, silent, time.monotonic() - start


def test_connections_waiting_when_shutdown_begins_are_answered(service: Service) -> None:
    clients, silent, seconds = asyncio.run(shut_down_with_clients_waiting(service))
    for i, client in enumerate(clients):
        with client:
            status, body = read_answer(client)
        assert status == 200, (i, status, body[:300])
        reprojection = np.array(json.loads(body)["poses"][0]["reprojection"])
        np.testing.assert_allclose(reprojection.mean(axis=0), POSE_2D.mean(axis=0) + 10.0 * i, atol=0.05)
    with silent:  # closed unanswered once the wait for its first request ran out
        assert read_answer(silent) == (0, b"")
    assert FIRST_REQUEST_WAIT_S <= seconds < FIRST_REQUEST_WAIT_S + 3, seconds
