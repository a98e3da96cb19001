"""The memory attacks of issue 30 (reliability round 3) against a fresh service each: what one client's
requests cost the server, measured as its peak resident memory over what it held before.

    python -m bench.memory_attacks                          # every attack
    python -m bench.memory_attacks --attack gap-bomb --json runs/bench/memory.json

- gap-bomb: POST /lift, temporal offline at 240 fps, 300 poses of one track 121 frames apart (each
  gap bridged: a clip spanning 36,180 frames) in an 85 KB body;
- widest-offline / widest-causal: the largest temporal request the defaults allow, 6,000 poses of
  one track at 240 fps, 120 frames apart (every gap bridged);
- consecutive-offline: 6,000 consecutive frames at 240 fps;
- silent-streams: 4 LiftStreams that send 1,024-person frames as fast as the server reads them and
  never read a reply, for --duration s;
- temporal-bodies: 8 clients each sending the widest causal request (6,000 poses, every gap
  bridged) back to back for --duration s: the parsing and the bridged work of big bodies;
- frame-overflow: a tracked pose with `frame` 2^63 (the status);
- widest-untracked: 2 clients each sending the largest untracked request (1,024 poses, no track)
  to POST /lift back to back for --duration s;
- widest-unary: the same through gRPC Lift (2 clients, 1,024 poses a call).

Each prints the server's resident memory before, its peak (VmHWM), the peak's growth, the status
and the server CPU seconds the attack cost, and what a bystander saw meanwhile (issue 30's targets:
a one-pose `POST /lift` every 20 ms on its own keep-alive connection, p99 ≤ 100 ms; `/readyz` on a
fresh connection every 0.25 s, each ≤ 0.5 s). It measures; it asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import httpx

if __package__ in (None, ""):  # `python bench/memory_attacks.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.bystander import JSON, Bystander, bystanders_line
from bench.server import ServiceProcess, cpu_seconds, process_tree, rss_bytes
from bench.stats import machine, sample_poses, write_json
from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc

MB = 1024 * 1024
STREAMS = 4
BODY_CLIENTS = 8
UNTRACKED_CLIENTS = 2
WIDEST_POSES = 1024  # the defaults' largest untracked request (Limits.max_request_poses)
POSES = sample_poses(64)


def peak_rss_bytes(pid: int) -> int:
    """The highest resident memory process `pid` and each of its workers have had, summed (VmHWM,
    Linux /proc)."""
    total = 0
    for member in process_tree(pid):
        with open(f"/proc/{member}/status") as f:
            total += next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
    return total


def temporal_body(frames: list[int], mode: str, fps: float = 240.0) -> bytes:
    """A POST /lift body of one track's poses at `frames`."""
    poses = [
        {"keypoints": POSES[k % len(POSES)].round(1).tolist(), "track_id": "a", "frame": f}
        for k, f in enumerate(frames)
    ]
    return json.dumps({"temporal": mode, "fps": fps, "poses": poses}, separators=(",", ":")).encode()


def post(service: ServiceProcess, body: bytes) -> str:
    """POST /lift; the status and the first words of an error."""
    response = httpx.post(
        service.url + "/lift", content=body, headers={"content-type": "application/json"}, timeout=300
    )
    if response.status_code == 200:
        return "200"
    return f"{response.status_code} {response.text[:160]}"


def gap_bomb(service: ServiceProcess, _: float) -> str:
    """300 poses 121 frames apart at 240 fps, offline."""
    body = temporal_body(list(range(0, 300 * 121, 121)), "offline")
    return f"{post(service, body)} ({len(body) / 1024:.0f} KB body)"


def widest(mode: str) -> Callable[[ServiceProcess, float], str]:
    """6,000 poses 120 frames apart at 240 fps (the defaults' largest temporal request)."""

    def attack(service: ServiceProcess, _: float) -> str:
        body = temporal_body(list(range(0, 6000 * 120, 120)), mode)
        return f"{post(service, body)} ({len(body) / 1024:.0f} KB body)"

    return attack


def consecutive_offline(service: ServiceProcess, _: float) -> str:
    """6,000 consecutive frames at 240 fps, offline."""
    body = temporal_body(list(range(6000)), "offline")
    return f"{post(service, body)} ({len(body) / 1024:.0f} KB body)"


def crowded_frames(people: int) -> Iterator[lifter_pb2.LiftFrame]:
    """Frames of `people` tracked people without end."""
    persons = [
        lifter_pb2.TrackedPose(
            track_id=f"p{k}", pose=lifter_pb2.Pose2D(keypoints=POSES[k % len(POSES)].ravel().tolist())
        )
        for k in range(people)
    ]
    frame = 0
    while True:
        yield lifter_pb2.LiftFrame(frame_id=frame, people=persons, fps=30.0)
        frame += 1


def silent_streams(service: ServiceProcess, duration_s: float) -> str:
    """4 LiftStreams of 1,024-person frames that never read a reply."""
    stop = threading.Event()
    calls = []
    channels = [grpc.insecure_channel(service.target) for _ in range(STREAMS)]
    for channel in channels:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]

        def frames() -> Iterator[lifter_pb2.LiftFrame]:
            for frame in crowded_frames(1024):
                if stop.is_set():
                    return
                yield frame

        calls.append(stub.LiftStream(frames()))  # never read
    time.sleep(duration_s)
    stop.set()
    for call in calls:
        call.cancel()
    for channel in channels:
        channel.close()
    return f"4 streams for {duration_s:g} s"


def _send_bodies(url: str, body: bytes, stop: float, out: Any) -> None:
    """One attacking client: `body` to POST /lift back to back until `stop` (monotonic), ignoring
    Retry-After; each status goes to `out`."""
    with httpx.Client(timeout=300) as http:
        while time.monotonic() < stop:
            out.put(str(http.post(url + "/lift", content=body, headers=JSON).status_code))


def temporal_bodies(service: ServiceProcess, duration_s: float) -> str:
    """BODY_CLIENTS clients sending 6,000-pose causal requests with every gap bridged, back to back."""
    body = temporal_body(list(range(0, 6000 * 120, 120)), "causal")
    stop = time.monotonic() + duration_s  # CLOCK_MONOTONIC is one clock for the whole machine
    statuses = _clients(_send_bodies, (service.url, body, stop), BODY_CLIENTS)
    kb = len(body) / 1024
    return f"{_counts(statuses)} ({kb:.0f} KB bodies, {BODY_CLIENTS} clients for {duration_s:g} s)"


def _clients(target: Callable[..., None], args: tuple[Any, ...], count: int) -> list[str]:
    """`count` attacking client processes (their own, so that they do not slow the bystander's
    measuring) running target(*args, out); the statuses they put in `out`."""
    context = multiprocessing.get_context("fork")
    out = context.Queue()
    clients = [context.Process(target=target, args=(*args, out)) for _ in range(count)]
    for client in clients:
        client.start()
    statuses: list[str] = []
    while any(c.is_alive() for c in clients) or not out.empty():
        try:
            statuses.append(out.get(timeout=0.1))
        except queue.Empty:
            continue
    for client in clients:
        client.join()
    return statuses


def _counts(statuses: list[str]) -> str:
    return ", ".join(f"{statuses.count(s)} x {s}" for s in sorted(set(statuses)))


def untracked_bodies(service: ServiceProcess, duration_s: float) -> str:
    """UNTRACKED_CLIENTS clients sending 1,024-pose untracked requests back to back."""
    poses = [{"keypoints": POSES[k % len(POSES)].round(1).tolist()} for k in range(WIDEST_POSES)]
    body = json.dumps({"poses": poses}, separators=(",", ":")).encode()
    stop = time.monotonic() + duration_s  # CLOCK_MONOTONIC is one clock for the whole machine
    statuses = _clients(_send_bodies, (service.url, body, stop), UNTRACKED_CLIENTS)
    kb = len(body) / 1024
    return f"{_counts(statuses)} ({kb:.0f} KB bodies, {UNTRACKED_CLIENTS} clients for {duration_s:g} s)"


def _send_unary(target: str, stop: float, out: Any) -> None:
    """One attacking client: gRPC Lift calls of WIDEST_POSES poses back to back until `stop`."""
    poses = [lifter_pb2.Pose2D(keypoints=POSES[k % len(POSES)].ravel().tolist()) for k in range(WIDEST_POSES)]
    request = lifter_pb2.LiftRequest(poses=poses)
    with grpc.insecure_channel(target) as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        while time.monotonic() < stop:
            try:
                stub.Lift(request, timeout=300)
                out.put("OK")
            except grpc.RpcError as err:
                out.put(err.code().name)


def unary_calls(service: ServiceProcess, duration_s: float) -> str:
    """UNTRACKED_CLIENTS gRPC clients sending 1,024-pose Lift calls back to back."""
    stop = time.monotonic() + duration_s
    statuses = _clients(_send_unary, (service.target, stop), UNTRACKED_CLIENTS)
    calls = f"{WIDEST_POSES}-pose Lift calls"
    return f"{_counts(statuses)} ({calls}, {UNTRACKED_CLIENTS} clients for {duration_s:g} s)"


def frame_overflow(service: ServiceProcess, _: float) -> str:
    """A tracked pose with frame 2^63."""
    return post(service, temporal_body([2**63], "causal", fps=30.0))


ATTACKS: dict[str, Callable[[ServiceProcess, float], str]] = {
    "gap-bomb": gap_bomb,
    "widest-offline": widest("offline"),
    "widest-causal": widest("causal"),
    "consecutive-offline": consecutive_offline,
    "silent-streams": silent_streams,
    "temporal-bodies": temporal_bodies,
    "frame-overflow": frame_overflow,
    "widest-untracked": untracked_bodies,
    "widest-unary": unary_calls,
}


def measure(name: str, duration_s: float, flags: list[str]) -> dict[str, Any]:
    """One attack on a fresh service: its memory before and at its peak, its CPU, what it answered."""
    with ServiceProcess("--intra-op-threads", "1", *flags) as service:
        time.sleep(0.5)
        before, cpu = rss_bytes(service.pid), cpu_seconds(service.pid)
        started = time.monotonic()
        with Bystander(service) as bystander:
            try:
                seen = ATTACKS[name](service, duration_s)
            except (httpx.HTTPError, grpc.RpcError, OSError) as err:
                seen = f"{type(err).__name__}: {err}"[:200]
        alive = service.process is not None and service.process.poll() is None
        peak = peak_rss_bytes(service.pid) if alive else 0
        return {
            "attack": name,
            "seen": seen if alive else f"{seen}; the server died",
            "rss_before_mb": before / MB,
            "peak_mb": peak / MB,
            "growth_mb": (peak - before) / MB,
            "wall_s": time.monotonic() - started,
            "server_cpu_s": cpu_seconds(service.pid) - cpu if alive else float("nan"),
            "bystander": bystander.summary(),
        }


def main(argv: list[str] | None = None) -> int:
    """Run the chosen attacks, each against a fresh service, and print what each cost."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.memory_attacks", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--attack", choices=sorted(ATTACKS), action="append", help="one attack (repeatable)")
    parser.add_argument("--duration", type=float, default=25.0, help="seconds of the stream attack")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("flags", nargs="*", help="flags for python -m repnet serve (after --)")
    args = parser.parse_args(argv)
    results = []
    for name in args.attack or list(ATTACKS):
        result = measure(name, args.duration, args.flags)
        results.append(result)
        print(
            f"{name:20} before {result['rss_before_mb']:6.0f} MB  peak {result['peak_mb']:6.0f} MB  "
            f"growth {result['growth_mb']:+6.0f} MB  server CPU {result['server_cpu_s']:5.1f} s  "
            f"wall {result['wall_s']:5.1f} s  {result['seen']}",
            flush=True,
        )
        print(f"{'':20} bystander: {bystanders_line(result['bystander'])}", flush=True)
    if args.json:
        write_json(args.json, {"machine": machine(), "flags": args.flags, "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
