"""HTTP load: closed-loop clients on keep-alive connections, written on raw asyncio streams.

A minimal HTTP/1.1 client keeps the load generator's own CPU cost per request low (httpx costs
several times more), which matters when client and server share two cores.
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass

import numpy as np

from bench.stats import Result, Tally, measured, sample_poses


@dataclass(frozen=True)
class Reply:
    """One HTTP answer: its status and body."""

    status: int
    body: bytes


def lift_request(host: str, port: int, poses: np.ndarray) -> bytes:
    """The bytes of one POST /lift with `poses` (n, 17, 2), ready to send again and again."""
    body = json.dumps({"poses": [{"keypoints": p.round(2).tolist()} for p in poses]}).encode()
    head = (
        f"POST /lift HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode()
    return head + body


class Connection:
    """One keep-alive HTTP/1.1 connection."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, host: str, port: int) -> Connection:
        """A keep-alive connection to host:port."""
        reader, writer = await asyncio.open_connection(host, port, limit=1 << 24)
        return cls(reader, writer)

    async def send(self, request: bytes) -> Reply:
        """Send one request and read its answer (Content-Length bodies only)."""
        self.writer.write(request)
        head = await self.reader.readuntil(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split(" ", 2)[1])
        length = next(
            int(v) for k, _, v in (line.partition(":") for line in lines[1:]) if k.lower() == "content-length"
        )
        return Reply(status, await self.reader.readexactly(length))

    def close(self) -> None:
        """Close the connection."""
        self.writer.close()


async def _closed_loop(
    host: str, port: int, requests: list[bytes], concurrency: int, warmup: float, duration: float
) -> Tally:
    """Each of `concurrency` clients sends its next request when the last is answered."""
    connections = [await Connection.open(host, port) for _ in range(concurrency)]
    first = await connections[0].send(requests[0])
    if first.status != 200 or len(json.loads(first.body)["poses"][0]["pose_3d"]) != 17:
        raise RuntimeError(f"the service answered {first.status}: {first.body[:300]!r}")
    tally = Tally(time.perf_counter() + warmup, time.perf_counter() + warmup + duration)

    async def client(k: int) -> None:
        i = k
        while (sent := time.perf_counter()) < tally.stop:
            reply = await connections[k].send(requests[i % len(requests)])
            tally.record(sent, time.perf_counter(), reply.status == 200)
            i += concurrency

    await asyncio.gather(*(client(k) for k in range(concurrency)))
    for c in connections:
        c.close()
    return tally


def measure_http(
    host: str,
    port: int,
    server_pid: int,
    poses_per_request: int,
    concurrency: int,
    duration: float = 3.0,
    warmup: float = 0.5,
    distinct: int = 64,
) -> Result:
    """Closed-loop POST /lift load: throughput of calls done in the window, latency of calls sent in it."""
    requests = [lift_request(host, port, sample_poses(poses_per_request, seed=s)) for s in range(distinct)]
    name = "HTTP /lift, 1 pose" if poses_per_request == 1 else f"HTTP /lift, {poses_per_request} poses"
    return measured(
        name,
        concurrency,
        poses_per_request,
        server_pid,
        lambda: asyncio.run(_closed_loop(host, port, requests, concurrency, warmup, duration)),
    )
