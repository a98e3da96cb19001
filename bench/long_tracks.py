"""Server memory over a long run of tracks opened and dropped in turn (1,000,000 tracked frames).

    python -m bench.long_tracks [--frames 1000000] [--tracks 100] [--out runs/bench/long_tracks.json]

The server runs as `python -m repnet serve` in a child process. --lanes lanes share --tracks tracks
open at once (one person per LiftFrame by default, the lane's tracks in turn; --people N puts N of
them in each frame) and the --frames tracked frames (one person's frame each). Every track lives
--track-frames frames, then it is dropped and a new track (a new id) takes its place; the first
lives are staggered so that the tracks are dropped one after another, not all at once. A track is
dropped in one of two ways (--drop):

- stream: the lane's stream ends when its tracks' lives end (freeing them), and a new stream
  with new tracks opens;
- idle: the stream goes on and the track just gets no more frames; the server drops it after
  REPNET_TRACK_IDLE_S (--track-idle-s, 1 s here).

`both` (the default) drops them by stream end on the first half of the lanes and by idle expiry
on the rest. The server's resident memory and its track gauges are sampled at the start (ready,
idle), after --warmup frames, every --sample-every frames and at the end (every stream closed: the
gauges must read 0). Growth is reported from the warmed-up sample to the end (target < 5 %) and
from the idle start. Every 1000th answer is checked for its frame id and a temporal pose; frames
never answered count as bad.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc

if __package__ in (None, ""):  # `python bench/long_tracks.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import OPTIONS
from bench.long_tracks_report import markdown, summarize
from bench.server import ServiceProcess, cpu_seconds, rss_bytes
from bench.stats import report
from bench.tracked import (
    FPS,
    Check,
    Crowd,
    Lane,
    expect_people,
    expect_pose,
    moving_clip,
    people_entry,
    pose_parts,
    single_frame,
    track_gauges,
)
from repnet._proto.repnet.v1 import lifter_pb2

log = logging.getLogger("bench.long_tracks")
MB = 2**20
CHECK_EVERY = 1000


@dataclass(frozen=True)
class Rotation:
    """Which tracks a lane's frames carry. The lane holds `slots` tracks at once, `people` of them
    per frame, in turn: frame i carries group i % (slots / people) at frame number
    i // (slots / people). A slot's track lives `life` frames, its first one (slot + 1) / slots of
    that (staggered), then the next track (a new id) takes the slot."""

    lane: int
    slots: int
    people: int
    life: int

    @property
    def groups(self) -> int:
        """Frames it takes to give every slot one frame."""
        return self.slots // self.people

    def first_life(self, slot: int) -> int:
        """Frames of the slot's first track."""
        return max(1, round(self.life * (slot + 1) / self.slots))

    def generation(self, slot: int, frame: int) -> int:
        """Which of the slot's tracks has frame number `frame`."""
        first = self.first_life(slot)
        return 0 if frame < first else 1 + (frame - first) // self.life

    def frame(self, i: int) -> tuple[int, list[int]]:
        """Frame i's frame number and slots."""
        group, number = i % self.groups, i // self.groups
        return number, list(range(group * self.people, (group + 1) * self.people))

    def stream_frames(self, stream: int, rank: int, ranks: int) -> int:
        """Frames of stream number `stream` of a lane dropping its tracks by stream end: every track
        lives `life` frames; the first stream of the lane ranked `rank` of `ranks` such lanes lives
        (rank + 1) / ranks of that (staggered)."""
        life = self.life if stream else max(1, round(self.life * (rank + 1) / ranks))
        return life * self.groups


class Frames:
    """The LiftFrame bytes of a lane, by rotation (each slot a different person moving)."""

    def __init__(self, rotation: Rotation) -> None:
        self.rotation = rotation
        clips = [moving_clip(seed=rotation.lane * rotation.slots + j) for j in range(rotation.slots)]
        if rotation.people == 1:
            self.single = [pose_parts(c) for c in clips]
        else:
            self.crowd = Crowd.of_clips(clips)

    def idle(self, i: int) -> bytes:
        """Frame i of a lane whose tracks are dropped by idle expiry: a slot's tracks follow each other."""
        number, slots = self.rotation.frame(i)
        ids = [f"l{self.rotation.lane}-j{j}-g{self.rotation.generation(j, number)}" for j in slots]
        return self._build(number, slots, ids)

    def in_stream(self, stream: int) -> Callable[[int], bytes]:
        """Frame i of stream number `stream` of a lane whose tracks end with the stream."""

        def frame(i: int) -> bytes:
            number, slots = self.rotation.frame(i)
            return self._build(number, slots, [f"l{self.rotation.lane}-s{stream}-j{j}" for j in slots])

        return frame

    def _build(self, number: int, slots: list[int], ids: list[str]) -> bytes:
        if self.rotation.people == 1:
            return single_frame(self.single[slots[0]], number, ids[0])
        head = lifter_pb2.LiftFrame(frame_id=number, fps=FPS).SerializeToString()
        parts = self.crowd.parts
        return head + b"".join(
            people_entry(t, parts[j][number % len(parts[j])]) for j, t in zip(slots, ids, strict=True)
        )


def checker(rotation: Rotation) -> Check:
    """Every CHECK_EVERYth answer of a lane: a temporal pose (or one per person) for its frame number."""
    expect = expect_pose(temporal=True) if rotation.people == 1 else expect_people(rotation.people)

    def check(answer: bytes, i: int) -> bool:
        return bool(i % CHECK_EVERY) or expect(answer, rotation.frame(i)[0])

    return check


def tracks_opened(rotation: Rotation, frames: int) -> int:
    """Tracks an idle-drop lane opens over `frames` LiftFrames."""
    last = (frames - 1) // rotation.groups
    return sum(rotation.generation(j, last) + 1 for j in range(rotation.slots)) if frames else 0


async def run_lane(
    channel: grpc.aio.Channel,
    rotation: Rotation,
    drop: str,
    messages: int,
    rank: tuple[int, int],
    args: argparse.Namespace,
    on_answer: Callable[[], None],
) -> dict[str, int]:
    """One lane's LiftFrames: one stream (drop idle) or one stream per life of its tracks (drop stream)."""
    frames, check = Frames(rotation), checker(rotation)
    if drop == "idle":
        lane = Lane(channel, window=args.window)
        bad = await lane.send(messages, frames.idle, check, on_answer)
        await lane.close()
        return {"bad": bad, "tracks": tracks_opened(rotation, messages), "streams": 1}
    bad = stream = 0
    while messages > 0:
        count = min(messages, rotation.stream_frames(stream, *rank))
        lane = Lane(channel, window=args.window)
        bad += await lane.send(count, frames.in_stream(stream), check, on_answer)
        await lane.close()
        messages -= count
        stream += 1
    return {"bad": bad, "tracks": stream * rotation.slots, "streams": stream}


def lane_plan(args: argparse.Namespace) -> list[tuple[Rotation, str, tuple[int, int]]]:
    """Each lane's rotation, how it drops tracks, and its rank among the lanes that drop them so."""
    drops = [args.drop] * args.lanes
    if args.drop == "both":
        half = max(1, args.lanes // 2)
        drops = ["stream"] * half + ["idle"] * (args.lanes - half)
    plan = []
    for lane, drop in enumerate(drops):
        rank = (drops[:lane].count(drop), drops.count(drop))
        plan.append((Rotation(lane, args.tracks // args.lanes, args.people, args.track_frames), drop, rank))
    return plan


async def run_all(service: ServiceProcess, args: argparse.Namespace) -> dict[str, Any]:
    """All lanes at once, the server's memory and gauges sampled as they go."""
    samples: list[dict[str, float]] = []
    done = 0
    started = time.perf_counter()
    cpu0 = cpu_seconds(service.pid)

    async def sample() -> None:
        at, rss = done, rss_bytes(service.pid) / MB
        gauges = await track_gauges(service.url)
        samples.append(
            {"frames": at, "seconds": round(time.perf_counter() - started, 2), "rss_mb": rss, **gauges}
        )
        elapsed = max(time.perf_counter() - started, 1e-9)
        log.info("%d frames, %.0f frames/s, server RSS %.1f MB, %s", at, at / max(elapsed, 1e-9), rss, gauges)

    def on_answer() -> None:
        nonlocal done
        done += args.people

    async def sampler(finished: asyncio.Event) -> None:
        marks = sorted({args.warmup, *range(args.sample_every, args.frames, args.sample_every)})
        while marks and not finished.is_set():
            if done >= marks[0]:
                while marks and done >= marks[0]:
                    marks.pop(0)
                await sample()
            await asyncio.sleep(0.05)

    await sample()  # ready, idle
    plan = lane_plan(args)
    messages = args.frames // args.people // args.lanes
    finished = asyncio.Event()
    watcher = asyncio.create_task(sampler(finished))
    async with grpc.aio.insecure_channel(service.target, options=OPTIONS) as channel:
        lanes = await asyncio.gather(
            *(run_lane(channel, rot, drop, messages, rank, args, on_answer) for rot, drop, rank in plan)
        )
    finished.set()
    await watcher
    seconds = time.perf_counter() - started
    server_cpu = (cpu_seconds(service.pid) - cpu0) / seconds
    await asyncio.sleep(0.5)  # the last streams' ends are handled
    await sample()  # every stream closed
    return {
        "samples": samples,
        "bad_answers": sum(lane["bad"] for lane in lanes),
        "tracks_opened": sum(lane["tracks"] for lane in lanes),
        "streams_opened": sum(lane["streams"] for lane in lanes),
        "lanes": [{"drop": drop, **lane} for (_, drop, _), lane in zip(plan, lanes, strict=True)],
        "frames": done,
        "seconds": seconds,
        "server_cpu": server_cpu,
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.long_tracks`."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.long_tracks",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--frames", type=int, default=1_000_000, help="tracked frames (people) in all")
    parser.add_argument("--tracks", type=int, default=100, help="tracks open at a time")
    parser.add_argument("--lanes", type=int, default=4, help="lanes (each its own stream at a time)")
    parser.add_argument("--people", type=int, default=1, help="people per LiftFrame")
    parser.add_argument("--track-frames", type=int, default=300, help="frames of one track's life")
    parser.add_argument("--drop", choices=("stream", "idle", "both"), default="both")
    parser.add_argument("--track-idle-s", type=float, default=1.0, help="the server's REPNET_TRACK_IDLE_S")
    parser.add_argument("--warmup", type=int, default=100_000, help="frames before the baseline sample")
    parser.add_argument("--sample-every", type=int, default=50_000)
    parser.add_argument("--window", type=int, default=256, help="LiftFrames in flight per lane")
    parser.add_argument("--service-flag", action="append", default=[], help="extra flag for the service")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/long_tracks.json"))
    args = parser.parse_args(argv)
    if args.lanes < 1 or args.tracks % args.lanes or (args.tracks // args.lanes) % args.people:
        parser.error("--tracks must split evenly over --lanes, and each lane's tracks over --people")
    if args.tracks // args.lanes > 64 or not 0 < args.warmup < args.frames:
        parser.error("at most 64 tracks per lane (REPNET_STREAM_MAX_TRACKS), and 0 < --warmup < --frames")
    return args


def main(argv: list[str] | None = None) -> int:
    """Run against a fresh service, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    flags = ["--track-idle-s", str(args.track_idle_s), *args.service_flag]
    with ServiceProcess(*flags) as service:
        result = summarize(asyncio.run(run_all(service, args)), args)
    return report(result, args.out, markdown)


if __name__ == "__main__":
    sys.exit(main())
