"""A long LiftStream (1,000,000 frames by default) with the server's resident memory sampled along the way.

    python -m bench.long_stream [--frames 1000000] [--streams 1] [--out runs/bench/long_stream.json]

The server runs as `python -m repnet serve` in a child process. Memory is read from /proc at start
(ready, idle), after a warm-up of --warmup frames (onnxruntime and gRPC buffers allocated), every
--sample-every frames, and at the end; growth is reported against the warmed-up figure (target
< 5 %) and against the idle start.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from pathlib import Path
from typing import Any

import grpc

if __package__ in (None, ""):  # `python bench/long_stream.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import LIFT_STREAM, OPTIONS, STREAM_WINDOW, stream_frames
from bench.server import ServiceProcess, cpu_seconds, rss_bytes
from bench.stats import machine, report
from repnet._proto.repnet.v1 import lifter_pb2

log = logging.getLogger("bench.long_stream")
GROWTH_LIMIT = 0.05
MB = 2**20


async def stream(
    channel: grpc.aio.Channel, count: int, frames: list[bytes], on_answer: Any, window: int = STREAM_WINDOW
) -> int:
    """Send `count` frames on one LiftStream (at most `window` unanswered); returns the bad answers."""
    call: grpc.aio.StreamStreamCall[bytes, bytes] = channel.stream_stream(LIFT_STREAM)()
    room = asyncio.Semaphore(window)

    async def write() -> None:
        for i in range(count):
            await room.acquire()
            await call.write(frames[i % len(frames)])
        await call.done_writing()

    writer = asyncio.create_task(write())
    bad = received = 0
    async for answer in call:
        room.release()
        if received % 1000 == 0:  # spot check: in order, and a pose
            result = lifter_pb2.LiftFrameResult.FromString(answer)
            bad += result.WhichOneof("result") != "pose" or result.frame_id != received % len(frames)
        received += 1
        on_answer()
    await writer
    return bad + count - received


async def run_streams(service: ServiceProcess, args: argparse.Namespace) -> dict[str, Any]:
    """Run the streams for the configured time, sampling the server's memory as they go."""
    samples: list[dict[str, float]] = []
    done = 0
    started = time.perf_counter()
    cpu0 = cpu_seconds(service.pid)

    def sample() -> None:
        elapsed = time.perf_counter() - started
        samples.append({"frames": done, "seconds": round(elapsed, 2), "rss_mb": rss_bytes(service.pid) / MB})
        log.info(
            "%d frames, %.0f frames/s, server RSS %.1f MB",
            done,
            done / max(elapsed, 1e-9),
            samples[-1]["rss_mb"],
        )

    def on_answer() -> None:
        nonlocal done
        done += 1
        if done % args.sample_every == 0 or done == args.warmup:
            sample()

    sample()  # idle, ready
    per_stream = args.frames // args.streams
    async with grpc.aio.insecure_channel(service.target, options=OPTIONS) as channel:
        bad = await asyncio.gather(
            *(stream(channel, per_stream, stream_frames(seed=k), on_answer) for k in range(args.streams))
        )
    seconds = time.perf_counter() - started
    if samples[-1]["frames"] != done:
        sample()
    return {
        "samples": samples,
        "bad_answers": sum(bad),
        "frames": done,
        "seconds": seconds,
        "server_cpu": (cpu_seconds(service.pid) - cpu0) / seconds,
    }


def summarize(run: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """Memory growth after the warm-up, throughput and the answers that were wrong."""
    samples = run["samples"]
    idle = samples[0]["rss_mb"]
    warm = next(s["rss_mb"] for s in samples if s["frames"] >= args.warmup)
    end = samples[-1]["rss_mb"]
    return {
        "command": " ".join(["python -m bench.long_stream", *sys.argv[1:]]),
        "machine": machine(),
        "frames": run["frames"],
        "streams": args.streams,
        "seconds": round(run["seconds"], 1),
        "frames_per_s": run["frames"] / run["seconds"],
        "server_cpu": run["server_cpu"],
        "bad_answers": run["bad_answers"],
        "rss_mb": {
            "idle_start": idle,
            "after_warmup": warm,
            "end": end,
            "peak": max(s["rss_mb"] for s in samples),
        },
        "growth_after_warmup": (end - warm) / warm,
        "growth_from_idle": (end - idle) / idle,
        "samples": samples,
    }


def markdown(result: dict[str, Any]) -> str:
    """The result as markdown, against the growth limit."""
    rss = result["rss_mb"]
    ok = result["growth_after_warmup"] < GROWTH_LIMIT and result["bad_answers"] == 0
    return (
        f"`{result['command']}`: {result['frames']:,} frames on {result['streams']} stream(s) in "
        f"{result['seconds']:,.0f} s ({result['frames_per_s']:,.0f} frames/s, server CPU "
        f"{result['server_cpu']:.2f} cores), {result['bad_answers']} bad answers.\n\n"
        f"| server RSS | MB |\n|---|---:|\n| idle at start | {rss['idle_start']:.1f} |\n"
        f"| after warm-up | {rss['after_warmup']:.1f} |\n| peak | {rss['peak']:.1f} |\n"
        f"| end | {rss['end']:.1f} |\n\n"
        f"Growth after warm-up {100 * result['growth_after_warmup']:+.2f} % "
        f"(from idle {100 * result['growth_from_idle']:+.2f} %): "
        f"{'met' if ok else 'MISSED'} (target < {100 * GROWTH_LIMIT:.0f} %, no bad answers)."
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.long_stream`."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.long_stream",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--frames", type=int, default=1_000_000)
    parser.add_argument("--streams", type=int, default=1, help="concurrent streams sharing the frames")
    parser.add_argument("--warmup", type=int, default=20_000, help="frames before the baseline memory sample")
    parser.add_argument("--sample-every", type=int, default=50_000)
    parser.add_argument(
        "--service-flag", action="append", default=[], help="extra flag for `python -m repnet serve`"
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/long_stream.json"))
    args = parser.parse_args(argv)
    if not 0 < args.warmup < args.frames or args.streams < 1:
        parser.error("need 0 < --warmup < --frames and --streams >= 1")
    return args


def main(argv: list[str] | None = None) -> int:
    """Run against a fresh service, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    with ServiceProcess(*args.service_flag) as service:
        result = summarize(asyncio.run(run_streams(service, args)), args)
    return report(result, args.out, markdown)


if __name__ == "__main__":
    sys.exit(main())
