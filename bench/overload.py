"""HTTP overload: far more closed-loop clients than the server can serve, and the probes meanwhile.

    python -m bench.overload                        # 1024 clients for 20 s, one pose each
    python -m bench.overload --concurrency 16 --duration 2 --poses 64 --json out.json

Each client opens its connection during the first `--ramp` seconds (the issue's second probe
opened 512 over one second), then sends POST /lift again as soon as the last answer came, 503s
included (a client that honoured Retry-After would press less). A prober opens a fresh connection
every 0.25 s for GET /readyz with the Kubernetes probe's 2 s timeout. Prints the status mix, the
p50/p99 of the 200s and of the 503s, and the /readyz latencies; it measures, it asserts nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import resource
import socket
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.http_load import Connection, lift_request
from bench.server import ServiceProcess
from bench.stats import latency_summary, machine, sample_poses, write_json

PROBE_EVERY_S = 0.25
PROBE_TIMEOUT_S = 2.0  # deploy/k8s: timeoutSeconds of the readiness probe
REQUEST_TIMEOUT_S = 10.0  # a request unanswered this long counts as "timeout" and its client reconnects


@dataclass
class Outcomes:
    """What the clients and the prober saw during the measured window."""

    statuses: collections.Counter[str] = field(default_factory=collections.Counter)
    seconds: dict[str, list[float]] = field(default_factory=lambda: collections.defaultdict(list))
    connects: list[float] = field(default_factory=list)  # seconds to establish each connection
    probes: list[float | None] = field(default_factory=list)  # /readyz seconds; None: no 200 in time

    def record(self, status: str, seconds: float) -> None:
        """Count one answer with its status and latency."""
        self.statuses[status] += 1
        self.seconds[status].append(seconds)


async def _open(host: str, port: int) -> tuple[Connection, float]:
    start = time.perf_counter()
    connection = await asyncio.wait_for(Connection.open(host, port), REQUEST_TIMEOUT_S)
    return connection, time.perf_counter() - start


async def _client(
    host: str, port: int, requests: list[bytes], k: int, delay: float, stop: float, out: Outcomes
) -> None:
    """One closed-loop client: (re)connect, send, record, until `stop`."""
    await asyncio.sleep(delay)
    connection: Connection | None = None
    i = k
    while time.perf_counter() < stop:
        sent = time.perf_counter()
        try:
            if connection is None:
                connection, seconds = await _open(host, port)
                out.connects.append(seconds)
                sent = time.perf_counter()
            reply = await asyncio.wait_for(connection.send(requests[i % len(requests)]), REQUEST_TIMEOUT_S)
            status = str(reply.status)
        except (asyncio.TimeoutError, TimeoutError):
            status = "timeout"
        except (OSError, asyncio.IncompleteReadError, ValueError, StopIteration) as err:
            status = type(err).__name__
        if not status.isdigit() and connection is not None:  # the connection's state is unknown
            connection.close()
            connection = None
        out.record(status, time.perf_counter() - sent)
        if status == "ConnectionRefusedError":
            await asyncio.sleep(0.1)
        i += 1
    if connection is not None:
        connection.close()


def _probe_once(host: str, port: int) -> float | None:
    """Seconds for GET /readyz on a fresh connection to answer 200; None if it did not in time."""
    start = time.perf_counter()
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as sock:
            sock.sendall(f"GET /readyz HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n\r\n".encode())
            sock.settimeout(max(PROBE_TIMEOUT_S - (time.perf_counter() - start), 0.001))
            head = sock.recv(64)
    except OSError:  # refused, reset or timed out
        return None
    return time.perf_counter() - start if b" 200 " in head else None


def probe_readiness(host: str, port: int, duration: float) -> list[float | None]:
    """The kubelet's view, from a process of its own so that the load generator's busy event loop
    does not delay it: one /readyz every PROBE_EVERY_S for `duration` seconds."""
    probes = []
    stop = time.perf_counter() + duration
    while time.perf_counter() < stop:
        probes.append(_probe_once(host, port))
        time.sleep(PROBE_EVERY_S)
    return probes


async def overload(
    host: str, port: int, concurrency: int, duration: float, poses: int, ramp: float
) -> tuple[Outcomes, float]:
    """`concurrency` closed-loop clients for `duration` seconds, with a health probe every 0.25 s."""
    requests = [lift_request(host, port, sample_poses(poses, seed=s)) for s in range(64)]
    out = Outcomes()
    with ProcessPoolExecutor(1) as prober:
        probes = prober.submit(probe_readiness, host, port, duration)
        start = time.perf_counter()
        stop = start + duration
        clients = [
            _client(host, port, requests, k, ramp * k / concurrency, stop, out) for k in range(concurrency)
        ]
        await asyncio.gather(*clients)
        wall = time.perf_counter() - start
        out.probes = probes.result()
    return out, wall


def summary(out: Outcomes, wall: float) -> dict[str, Any]:
    """Counts, rates and latency quantiles of the answers and the probes."""
    answered = sum(out.statuses.values())
    probes_ok = [p for p in out.probes if p is not None]
    return {
        "requests": answered,
        "requests_per_s": answered / wall,
        "statuses": dict(out.statuses.most_common()),
        "latency_ms": {status: latency_summary(s) for status, s in out.seconds.items()},
        "connect_ms": latency_summary(out.connects),
        "readyz": {
            "probes": len(out.probes),
            "failed": len(out.probes) - len(probes_ok),
            "ms": {**latency_summary(probes_ok), "max": max(probes_ok, default=0.0) * 1e3},
        },
    }


def report(found: dict[str, Any]) -> str:
    """The summary as text."""
    lines = [f"{found['requests']} answers in the window ({found['requests_per_s']:,.0f}/s)", "status mix:"]
    for status, count in found["statuses"].items():
        lat = found["latency_ms"].get(status, {})
        lines.append(
            f"  {status:>24}: {count:8d} ({count / max(found['requests'], 1):6.1%})"
            f"  p50 {lat.get('p50', 0):8.1f} ms  p99 {lat.get('p99', 0):8.1f} ms"
        )
    ready = found["readyz"]
    lines.append(
        f"/readyz on a fresh connection: {ready['probes']} probes, {ready['failed']} without a 200 "
        f"within {PROBE_TIMEOUT_S:g} s; p50 {ready['ms'].get('p50', 0):.1f} ms, p99 "
        f"{ready['ms'].get('p99', 0):.1f} ms, max {ready['ms']['max']:.1f} ms"
    )
    connect = found["connect_ms"]
    lines.append(f"connect: p50 {connect.get('p50', 0):.1f} ms, p99 {connect.get('p99', 0):.1f} ms")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Overload a fresh service and print what it answered; the exit status."""
    parser = argparse.ArgumentParser(prog="python -m bench.overload", description=__doc__.split("\n")[0])
    parser.add_argument("--concurrency", type=int, default=1024, help="closed-loop clients (default 1024)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds of load (default 20)")
    parser.add_argument("--poses", type=int, default=1, help="poses per request (default 1)")
    parser.add_argument("--ramp", type=float, default=1.0, help="seconds over which clients connect")
    parser.add_argument(
        "--url", help="a running server (default: start python -m repnet serve on free ports)"
    )
    parser.add_argument("--service-flag", action="append", default=[], help="flag for the started server")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args(argv)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    with contextlib.suppress(ValueError, OSError):  # each client holds a socket
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, 4 * args.concurrency + 256)), hard))
    with contextlib.ExitStack() as stack:
        if args.url:
            host, _, port = args.url.removeprefix("http://").rstrip("/").partition(":")
            server_flags: list[str] = []
        else:
            flags = [f for flag in args.service_flag for f in flag.split(maxsplit=1)]
            service = stack.enter_context(ServiceProcess(*flags))
            host, port, server_flags = "127.0.0.1", str(service.http_port), flags
        out, wall = asyncio.run(
            overload(host, int(port), args.concurrency, args.duration, args.poses, args.ramp)
        )
    found = summary(out, wall)
    print(
        f"HTTP overload: {args.concurrency} clients, {args.poses} pose(s) per request, "
        f"{args.duration:g} s, connected over {args.ramp:g} s"
    )
    print(report(found))
    if args.json:
        write_json(
            args.json, {"machine": machine(), "args": vars(args), "server_flags": server_flags, **found}
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
