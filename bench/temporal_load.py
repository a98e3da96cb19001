"""Capacity and cost of causal temporal lifting on gRPC LiftStream, and the temporal model's roof.

    python -m bench.temporal_load [--cameras 8,16,32,48,64] [--duration 10] [--out PATH.json]

1. The roof: raw onnxruntime runs of the causal temporal model (the service's session settings) on
   windows of K slots for 30 fps (temporal.Contract.slots), built from a tracked person's
   single-frame answers, at each batch size; the single-frame model's session.run at the same
   sizes; and both per tracked pose (a tracked pose costs one run of each).
2. Saturated streams: S LiftStreams of one tracked person each (track_id, fps 30, a moving pose,
   frame ids increasing), 256 frames in flight each; then the same streams untracked.
3. Cameras: N LiftStreams paced at 30 frames/s each, one tracked person per frame, their send times
   spread evenly over a frame period; then the same N streams untracked. N is searched: the
   --cameras counts in turn until one is not held, then halved down to --refine cameras between the
   last held and the first not. Held: p99 <= --p99-ms per frame, no errors, and >= 98 % of the
   offered frames sent and answered within the window, less one frame a camera at its edges.
4. People per frame: one stream in lock-step (one frame in flight) of 1-person frames (`pose`),
   1-person frames (`people`) and --people-person frames (`people`): per-frame latency and server
   CPU, and their ratio (target: a 16-person frame <= 3x a 1-person frame).
5. One worker: the saturated tracked streams again, on a second service with --workers 1 (the
   service's workers against one: target >= 1.6x on 2 cores).
6. The transport's floor: bench.echo (Python grpc.aio answering each frame with a fixed reply)
   under the same clients: 8 streams of 256 in flight, one in lock-step, 8 paced cameras.

The targets are issue 35's (bench.temporal_report); each line says met or MISSED.
The service runs as `python -m repnet serve` in a child process with the same flags as the roof's
session; the load generator is this process, on the same machine. Each load's CPU (server, this
client, everything else on the machine) is measured over its window, with the load average.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import httpx

if __package__ in (None, ""):  # `python bench/temporal_load.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.echo import measure_floor
from bench.server import ServiceProcess, rss_bytes
from bench.stats import Result, machine, write_json
from bench.temporal_clients import camera, crowd_frames, run_id, run_streams
from bench.temporal_report import (
    EDGE_FRAMES,
    HELD_FRACTION,
    P99_TARGET_MS,
    PEOPLE_KINDS,
    Report,
)
from bench.temporal_roof import ROOF_BATCHES, temporal_roof
from bench.tracked import (
    FPS,
    load_average,
    result_of,
)
from repnet.server.app import parse_settings

log = logging.getLogger("bench.temporal_load")

DEFAULT_MAX_STREAMS = 64  # REPNET_GRPC_MAX_STREAMS' default


def measure_cameras(service: ServiceProcess, count: int, tracked: bool, args: argparse.Namespace) -> Result:
    """`count` cameras at 30 fps, one person each, tracked or not."""
    rid = run_id()
    sources = [camera(k, tracked, rid) for k in range(count)]
    tally = asyncio.run(
        run_streams(
            service.target,
            service.pid,
            sources,
            fps=FPS,
            window=256,
            warmup=args.warmup,
            duration=args.duration,
            spread=args.phase == "spread",
        )
    )
    name = f"{count} cameras at {FPS:g} fps, " + ("tracked" if tracked else "untracked")
    result = result_of(name, count, 1, tally, offered=count * FPS * args.duration, tracked=tracked)
    result.extra["held"] = held(result, args.p99_ms)
    return result


def held(result: Result, p99_ms: float) -> bool:
    """The cameras were served: p99 within the target, no errors, the offered frames sent and answered.

    Each camera may be EDGE_FRAMES short at the window's edges beyond HELD_FRACTION: where its phase
    puts its first and last frame, and the frame in flight when the window closes. In a long window
    that is noise (32 cameras for 8 s: 32 of 7,680 frames); in a short one it alone would decide (2
    cameras for 0.6 s: one missing frame of 36 is 97 %)."""
    need = HELD_FRACTION * result.extra["offered"] - EDGE_FRAMES * result.concurrency
    return (
        result.errors == 0
        and result.latency_ms.get("p99", float("inf")) <= p99_ms
        and result.extra["sent"] >= need
        and result.calls >= need
    )


def search(counts: list[int], is_held: Callable[[int], bool], refine: int) -> tuple[int, list[int]]:
    """The most cameras held: `counts` ascending until one is not held, then the gap between the
    last held and the first not halved down to `refine` cameras (0: no halving). Returns it (0 when
    none is held) and the counts in the order they were measured."""
    tried: list[int] = []
    best, failed = 0, None
    for n in sorted(counts):
        tried.append(n)
        if not is_held(n):
            failed = n
            break
        best = n
    while failed is not None and refine and failed - best > refine:
        n = (best + failed) // 2
        tried.append(n)
        if is_held(n):
            best = n
        else:
            failed = n
    return best, tried


def measure_saturated(
    service: ServiceProcess, streams: int, tracked: bool, args: argparse.Namespace
) -> Result:
    """`streams` streams of one person each, 256 frames in flight: throughput."""
    rid = run_id()
    sources = [camera(k, tracked, rid) for k in range(streams)]
    tally = asyncio.run(
        run_streams(
            service.target,
            service.pid,
            sources,
            fps=0,
            window=256,
            warmup=args.warmup,
            duration=args.duration,
        )
    )
    name = f"LiftStream x{streams}, 256 in flight, " + ("tracked" if tracked else "untracked")
    return result_of(name, streams, 1, tally, tracked=tracked)


def measure_people(service: ServiceProcess, kind: str, args: argparse.Namespace) -> Result:
    """One stream in lock-step (one frame in flight) of one kind of frame (see PEOPLE_KINDS)."""
    rid = run_id()
    if kind == "pose":
        source = camera(0, True, rid)
    elif kind == "untracked":
        source = camera(0, False, rid)
    else:
        source = crowd_frames(int(kind), rid)
    tally = asyncio.run(
        run_streams(
            service.target,
            service.pid,
            [source],
            fps=0,
            window=1,
            warmup=args.warmup,
            duration=args.people_duration,
        )
    )
    result = result_of(PEOPLE_KINDS.get(kind, f"{kind} people (people)"), 1, 1, tally, people=source.people)
    cpu = tally.cpu.get("server", 0.0)
    result.extra["server_cpu_ms_per_frame"] = 1e3 * cpu / max(result.calls, 1)
    return result


# --- the report -----------------------------------------------------------------------------


# --- the run --------------------------------------------------------------------------------


def service_flags(args: argparse.Namespace) -> list[str]:
    """The service's flags: --service-flag values, and room for the cameras when more than the
    default stream limit are asked for (unless a --grpc-max-streams is given)."""
    flags = list(args.service_flag)
    most = max([*args.cameras, args.streams])
    if most > DEFAULT_MAX_STREAMS and not any(f.startswith("--grpc-max-streams") for f in flags):
        flags.append(f"--grpc-max-streams={most}")
    return flags


def run(args: argparse.Namespace) -> Report:
    """The roof, the loads against a fresh service, the roof again."""
    flags = service_flags(args)
    settings = parse_settings(flags)
    started, load_start = time.perf_counter(), load_average()
    log.info("roof (load average %.2f)", load_start)
    roof, contract = temporal_roof(settings, args.batches, args.roof_duration)
    report = Report(
        when=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        command=" ".join(["python -m bench.temporal_load", *sys.argv[1:]]),
        machine=machine(),
        models={"single": settings.model_path.name, "causal": settings.causal_model_path.name},
        contract={**contract.__dict__, "slots_30fps": contract.slots(FPS)},
        service_flags=flags or ["(defaults)"],
        roof=roof,
        people_count=args.people,
        p99_ms=args.p99_ms,
    )
    with ServiceProcess(*flags) as service:
        rss_start = rss_bytes(service.pid)
        ready = httpx.get(f"{service.url}/readyz", timeout=10).json()
        report.models["single_id"] = str(ready.get("model_id"))
        measure_loads(service, args, report)
        report.server_rss_mb = {"start": rss_start / 2**20, "end": rss_bytes(service.pid) / 2**20}
    if args.streams and args.one_worker:
        with ServiceProcess(*flags, "--workers", "1") as one:
            log.info("saturated: %d streams, tracked, one worker", args.streams)
            result = measure_saturated(one, args.streams, True, args)
            result.name += ", --workers 1"
            report.one_worker.append(result)
    if args.floor:
        log.info("the transport's floor (bench.echo)")
        report.floor = measure_floor(args.warmup, args.people_duration)
    log.info("roof again, after the loads")
    report.roof_end, _ = temporal_roof(settings, args.batches, args.roof_duration)
    report.load_average = {"start": load_start, "end": load_average()}
    report.wall_s = time.perf_counter() - started
    return report


def measure_loads(service: ServiceProcess, args: argparse.Namespace, report: Report) -> None:
    """The saturated streams, the camera search and the people per frame, into the report."""
    if args.streams:
        for tracked in (True, False):
            log.info("saturated: %d streams, tracked=%s", args.streams, tracked)
            report.saturated.append(measure_saturated(service, args.streams, tracked, args))

    def is_held(count: int) -> bool:
        log.info("cameras: %d, tracked", count)
        result = measure_cameras(service, count, True, args)
        report.cameras.append(result)
        log.info("  p99 %.1f ms, %s", result.latency_ms.get("p99", float("nan")), result.extra["held"])
        if args.untracked:
            log.info("cameras: %d, untracked", count)
            report.cameras.append(measure_cameras(service, count, False, args))
        return bool(result.extra["held"])

    if args.cameras:
        report.most_cameras, report.searched = search(args.cameras, is_held, args.refine)
    for kind in ("untracked", "pose", "1", str(args.people)) if args.people else ():
        log.info("people per frame: %s", kind)
        report.people.append(measure_people(service, kind, args))


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.temporal_load`."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.temporal_load",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--cameras",
        type=_ints,
        default=[8, 16, 32, 48, 64, 80, 96],
        help="camera counts to try, ascending (empty: skip the search)",
    )
    parser.add_argument("--refine", type=int, default=4, help="halve the gap after the search down to this")
    parser.add_argument("--p99-ms", type=float, default=P99_TARGET_MS, help="held: p99 per frame <= this")
    parser.add_argument(
        "--phase",
        choices=("spread", "sync"),
        default="spread",
        help="cameras send spread evenly over a frame period, or all at once",
    )
    parser.add_argument(
        "--no-untracked",
        dest="untracked",
        action="store_false",
        help="skip the untracked run beside each camera count",
    )
    parser.add_argument("--streams", type=int, default=8, help="saturated streams (0: skip)")
    parser.add_argument(
        "--no-one-worker",
        dest="one_worker",
        action="store_false",
        help="skip the saturated tracked streams on a second service with --workers 1",
    )
    parser.add_argument(
        "--no-floor", dest="floor", action="store_false", help="skip the transport's floor (bench.echo)"
    )
    parser.add_argument("--people", type=int, default=16, help="people of the many-person frame (0: skip)")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds measured per load")
    parser.add_argument("--people-duration", type=float, default=5.0, help="seconds per people load")
    parser.add_argument("--warmup", type=float, default=2.0, help="seconds before each measured window")
    parser.add_argument("--batches", type=lambda t: tuple(_ints(t)), default=ROOF_BATCHES)
    parser.add_argument("--roof-duration", type=float, default=1.5, help="seconds per roof batch size")
    parser.add_argument(
        "--service-flag",
        action="append",
        default=[],
        help="extra flag for `python -m repnet serve` (and the roof's sessions)",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/temporal_load.json"))
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    report = run(args)
    write_json(args.out, report)
    print(report.markdown())
    log.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
