"""Slow-client attacks (issue F2-F4) against the service, and what a normal client sees meanwhile.

    python -m bench.slow_clients                      # each attack for 15 s, default settings
    python -m bench.slow_clients --attack f2 --duration 5 --json out.json

The attacker runs in a process of its own and keeps its connections up, opening a new one
whenever the server closes one:
- f2: 130 connections send POST /lift headers with Content-Length 1000 and one body byte, then nothing;
- f3: 4 connections each send a header line that never ends (32 MiB at most per connection);
- f4: 1000 connections that send nothing and 200 that send half a header line.
Meanwhile one normal client sends POST /lift (one pose) on a keep-alive connection every 20 ms, a
prober asks GET /readyz on a fresh connection and gRPC health every 0.25 s, and the server's open
file descriptors and resident memory are sampled. Prints the normal client's statuses and p50/p99,
the probes' worst latencies, and the server's fds and RSS; it measures, it asserts nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import multiprocessing
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

if __package__ in (None, ""):  # `python bench/slow_clients.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.http_load import Connection, lift_request
from bench.overload import PROBE_EVERY_S, _probe_once
from bench.server import ServiceProcess, open_fds, rss_bytes
from bench.stats import latency_summary, machine, sample_poses, write_json

ATTACKS = ("f2", "f3", "f4")
NORMAL_EVERY_S = 0.02
HEADER_CHUNK = 64 * 1024
HEADER_LINE_MAX = 32 * 1024 * 1024


async def _hold(host: str, port: int, first: bytes, trickle: bytes, stop: float) -> None:
    """One attacker connection: send `first`, then `trickle` (if any) until the server closes it or
    refuses more; then a new connection, until `stop`."""
    while time.monotonic() < stop:
        try:
            reader, writer = await asyncio.open_connection(host, port)
        except OSError:
            await asyncio.sleep(0.1)
            continue
        try:
            writer.write(first)
            await writer.drain()
            sent = len(first)
            while time.monotonic() < stop and not reader.at_eof():
                if trickle and sent < HEADER_LINE_MAX:
                    writer.write(trickle)
                    await asyncio.wait_for(writer.drain(), 1.0)
                    sent += len(trickle)
                else:
                    await asyncio.sleep(0.2)
                with_data = await _read_some(reader)
                if with_data is None:
                    break
        except (OSError, asyncio.TimeoutError):
            pass
        finally:
            writer.close()


async def _read_some(reader: asyncio.StreamReader) -> bytes | None:
    """What the server sent within 10 ms (b"" if nothing); None once it closed."""
    try:
        data = await asyncio.wait_for(reader.read(4096), 0.01)
    except asyncio.TimeoutError:
        return b""
    return data or None


def attacker(attack: str, host: str, port: int, duration: float) -> None:
    """Run one attack for `duration` seconds (in a process of its own)."""
    stop = time.monotonic() + duration
    head = f"POST /lift HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n".encode()
    if attack == "f2":
        plan = [(head + b"Content-Length: 1000\r\n\r\n{", b"")] * 130
    elif attack == "f3":
        plan = [(b"GET /readyz HTTP/1.1\r\nX-Long: ", b"a" * HEADER_CHUNK)] * 4
    else:
        plan = [(b"", b"")] * 1000 + [(b"GET /readyz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Half: ab", b"")] * 200

    async def run() -> None:
        await asyncio.gather(*(_hold(host, port, first, trickle, stop) for first, trickle in plan))

    asyncio.run(run())


@dataclass
class Seen:
    """What the normal client, the probes and the server's counters showed during one attack."""

    statuses: collections.Counter[str] = field(default_factory=collections.Counter)
    lift_s: list[float] = field(default_factory=list)
    readyz_s: list[float | None] = field(default_factory=list)
    health_s: list[float | None] = field(default_factory=list)
    fds: list[int] = field(default_factory=list)
    rss_mb: list[float] = field(default_factory=list)


async def _normal_client(host: str, port: int, stop: float, seen: Seen) -> None:
    request = lift_request(host, port, sample_poses(1))
    connection: Connection | None = None
    while time.monotonic() < stop:
        start = time.perf_counter()
        try:
            if connection is None:
                connection = await asyncio.wait_for(Connection.open(host, port), 5)
            reply = await asyncio.wait_for(connection.send(request), 5)
            seen.statuses[str(reply.status)] += 1
            if reply.status == 200:
                seen.lift_s.append(time.perf_counter() - start)
        except (OSError, asyncio.TimeoutError, asyncio.IncompleteReadError) as err:
            seen.statuses[type(err).__name__] += 1
            if connection is not None:
                connection.close()
            connection = None
        await asyncio.sleep(max(0.0, NORMAL_EVERY_S - (time.perf_counter() - start)))
    if connection is not None:
        connection.close()


def _health_once(stub: health_pb2_grpc.HealthStub) -> float | None:
    start = time.perf_counter()
    try:
        reply = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=2.0)
    except grpc.RpcError:
        return None
    return time.perf_counter() - start if reply.status == health_pb2.HealthCheckResponse.SERVING else None


def _probe(service: ServiceProcess, stop: float, seen: Seen) -> None:
    with grpc.insecure_channel(service.target) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while time.monotonic() < stop:
            seen.readyz_s.append(_probe_once("127.0.0.1", service.http_port))
            seen.health_s.append(_health_once(stub))
            seen.fds.append(open_fds(service.pid))
            seen.rss_mb.append(rss_bytes(service.pid) / 2**20)
            time.sleep(PROBE_EVERY_S)


def under_attack(service: ServiceProcess, attack: str, duration: float, warmup: float = 1.0) -> Seen:
    """Run `attack` for warmup + duration seconds and measure the last `duration` of them."""
    context = multiprocessing.get_context("spawn")  # no copy of this process's threads or loops
    process = context.Process(
        target=attacker, args=(attack, "127.0.0.1", service.http_port, warmup + duration), daemon=True
    )
    process.start()
    time.sleep(warmup)
    seen = Seen()
    stop = time.monotonic() + duration
    prober = threading.Thread(target=_probe, args=(service, stop, seen), daemon=True)
    prober.start()
    asyncio.run(_normal_client("127.0.0.1", service.http_port, stop, seen))
    prober.join(timeout=10)
    process.join(timeout=15)
    if process.is_alive():
        process.kill()
    return seen


def summary(seen: Seen) -> dict[str, Any]:
    """The figures of one attack."""

    def worst(values: list[float | None]) -> float | None:
        if not values or None in values:
            return None
        return round(max(v for v in values if v is not None) * 1e3, 1)

    return {
        "lift_statuses": dict(seen.statuses),
        "lift_ms": latency_summary(seen.lift_s),
        "readyz_worst_ms": worst(seen.readyz_s),
        "readyz_failed": sum(v is None for v in seen.readyz_s),
        "health_worst_ms": worst(seen.health_s),
        "health_failed": sum(v is None for v in seen.health_s),
        "server_fds_max": max(seen.fds, default=0),
        "server_rss_mb_max": round(max(seen.rss_mb, default=0.0), 1),
    }


def report(rows: dict[str, dict[str, Any]]) -> str:
    """A markdown table: one row per attack."""
    lines = [
        "| attack | normal /lift statuses | p50 ms | p99 ms | worst /readyz ms (failed) | worst gRPC health "
        "ms (failed) | server fds max | RSS MB max |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        ms = r["lift_ms"]
        lines.append(
            f"| {name} | {r['lift_statuses']} | {ms.get('p50', float('nan')):.1f} | "
            f"{ms.get('p99', float('nan')):.1f} | {r['readyz_worst_ms']} ({r['readyz_failed']}) | "
            f"{r['health_worst_ms']} ({r['health_failed']}) | {r['server_fds_max']} | "
            f"{r['server_rss_mb_max']} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Measure each attack against a fresh `python -m repnet serve` with the given flags."""
    parser = argparse.ArgumentParser(prog="python -m bench.slow_clients", description=__doc__.split("\n")[0])
    parser.add_argument("--attack", choices=[*ATTACKS, "all"], default="all")
    parser.add_argument("--duration", type=float, default=15.0, help="seconds measured per attack")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("flags", nargs="*", help="flags for python -m repnet serve (after --)")
    args = parser.parse_args(argv)
    rows = {}
    for attack in ATTACKS if args.attack == "all" else (args.attack,):
        with ServiceProcess(*args.flags) as service:
            rows[attack] = summary(under_attack(service, attack, args.duration))
        print(f"{attack}: {rows[attack]}", flush=True)
    print(report(rows))
    if args.json:
        write_json(args.json, {"machine": machine(), "flags": args.flags, "attacks": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
