"""Memory per open track: server RSS with 0, 100 and 1000 open tracks, and what one Track holds.

    python -m bench.track_memory [--tracks 100,1000] [--streams 16] [--out runs/bench/track_memory.json]

The server runs as `python -m repnet serve` in a child process, with tracks and streams that do not
expire during the run. Tracked poses travel in LiftFrames of at most --people tracks each (a
stream's tracks in turn for each frame number), at most --window frames in flight per stream, so
that the poses in flight (whose windows the server holds until their run) are about as many
whatever the track count. First --streams warm-up streams of --people tracks each run as many
frames and close (the allocator and the temporal model's arenas reach their working size); then
--streams streams open and send untracked frames: the server's RSS then is the figure for 0
tracks. Then tracks are opened, spread over the streams, until each count of --tracks is open;
each track gets --frames-per-track frames, by default as many as its ring holds, so that its
state is written through. After each count the server's RSS and its gauges (repnet_open_tracks,
repnet_track_state_bytes) are read. Last, the streams close: the gauges must come back to 0.
Memory per track: the RSS added per track between two counts.

Also reported: Track.nbytes (the bytes of state the server counts per track) and the bytes one
Track, filled, takes in this process as tracemalloc counts them (its arrays and Python objects).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import time
import tracemalloc
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Any

import grpc
import numpy as np

if __package__ in (None, ""):  # `python bench/track_memory.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import OPTIONS
from bench.server import ServiceProcess, rss_bytes
from bench.stats import machine, report
from bench.tracked import (
    FPS,
    Crowd,
    Lane,
    expect_people,
    expect_pose,
    load_average,
    moving_clip,
    pose_parts,
    single_frame,
    track_gauges,
)
from repnet.runtime.temporal import TemporalLifter
from repnet.runtime.tracks import Observation, Track, track_bytes, track_capacity
from repnet.server.app import parse_settings

log = logging.getLogger("bench.track_memory")
MB = 2**20
SETTLE_S = 0.5  # after a phase, before memory is read


def python_track_bytes(capacity: int, fps: float = 30.0, count: int = 200) -> float:
    """Bytes one Track of `capacity` frames takes once filled, as tracemalloc counts them (the mean
    of `count` tracks, each pushed `capacity` frames)."""
    seen = Observation(np.zeros((17, 3), np.float32), np.zeros((17, 2), np.float32), np.ones(17, np.float32))
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracks = [Track(capacity, fps) for _ in range(count)]
        for track in tracks:
            for frame in range(capacity):
                track.push(frame, seen)
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return (after - before) / count


def spread(tracks: int, streams: int) -> list[list[str]]:
    """Track ids t0..t{tracks-1}, dealt over `streams` streams in turn."""
    return [[f"t{k}" for k in range(s, tracks, streams)] for s in range(streams)]


async def feed(lane: Lane, crowd: Crowd, ids: list[str], first: int, frames: int, people: int) -> int:
    """Frames number first .. first + frames - 1 of the tracks `ids` on one stream, in LiftFrames of
    at most `people` of them (a frame number's tracks in turn, so that as many poses are in flight
    whatever the track count); returns the bad answers."""
    if not ids:
        return 0
    groups = [ids[a : a + people] for a in range(0, len(ids), people)]
    checks = [expect_people(len(g)) for g in groups]

    def frame_of(i: int) -> bytes:
        return crowd.frame(first + i // len(groups), groups[i % len(groups)])

    def check(answer: bytes, i: int) -> bool:
        return checks[i % len(groups)](answer, first + i // len(groups))

    return await lane.send(frames * len(groups), frame_of, check)


async def measure(service: ServiceProcess, args: argparse.Namespace, capacity: int) -> dict[str, Any]:
    """The phases: warm-up, 0 tracks, each track count, streams closed; RSS and gauges after each."""
    frames = args.frames_per_track or capacity
    crowd = Crowd.of(args.people)
    phases: list[dict[str, Any]] = []
    bad = 0

    async def sample(name: str, tracks: int) -> None:
        await asyncio.sleep(SETTLE_S)
        gauges = await track_gauges(service.url)
        phases.append({"phase": name, "tracks": tracks, "rss_mb": rss_bytes(service.pid) / MB, **gauges})
        log.info("%s: %d tracks, RSS %.1f MB, gauges %s", name, tracks, phases[-1]["rss_mb"], gauges)

    async with grpc.aio.insecure_channel(service.target, options=OPTIONS) as channel:
        await sample("idle", 0)
        # warm-up: as many poses in flight as later, on streams that then close
        warm = [Lane(channel, window=args.window) for _ in range(args.streams)]
        ids = [[f"w{s}-{k}" for k in range(args.people)] for s in range(args.streams)]
        bad += sum(
            await asyncio.gather(
                *(feed(w, crowd, i, 0, frames, args.people) for w, i in zip(warm, ids, strict=True))
            )
        )
        for lane in warm:
            await lane.close()
        lanes = [Lane(channel, window=args.window) for _ in range(args.streams)]
        parts = pose_parts(moving_clip())
        untracked, check = args.untracked_frames, expect_pose(temporal=False)
        await asyncio.gather(*(lane.send(untracked, partial(single_frame, parts), check) for lane in lanes))
        await sample("0 tracks, streams open", 0)
        first = 0  # frame numbers go on from phase to phase
        for count in sorted(args.tracks):
            owned = spread(count, args.streams)
            started = time.perf_counter()
            fed = await asyncio.gather(
                *(feed(lane, crowd, owned[s], first, frames, args.people) for s, lane in enumerate(lanes))
            )
            bad += sum(fed)
            first += frames
            log.info("%d tracks fed %d frames each in %.1f s", count, frames, time.perf_counter() - started)
            await sample(f"{count} tracks", count)
        for lane in lanes:
            await lane.close()
        await sample("streams closed", 0)
    return {"phases": phases, "bad_answers": bad, "frames_per_track": frames, "people_per_frame": args.people}


def per_track(phases: list[dict[str, Any]]) -> list[dict[str, float]]:
    """RSS added per track between consecutive track counts (from the 0-track phase with the
    streams open), and the gauges' bytes per track."""
    counted = [p for p in phases if p["phase"] == "0 tracks, streams open" or p["phase"].endswith(" tracks")]
    out = []
    for before, after in zip(counted, counted[1:], strict=False):
        added = after["tracks"] - before["tracks"]
        out.append(
            {
                "from": before["tracks"],
                "to": after["tracks"],
                "rss_kb_per_track": (after["rss_mb"] - before["rss_mb"]) * 1024 / added,
                "gauge_kb_per_track": after.get("track_state_bytes", 0.0) / 1024 / max(after["tracks"], 1),
            }
        )
    return out


def markdown(result: dict[str, Any]) -> str:
    """The result as markdown."""
    lines = [
        f"`{result['command']}` on {result['machine']['cpus']} CPUs ({result['machine']['cpu']}), "
        f"{result['when']}; {result['streams']} streams, {result['frames_per_track']} frames per track "
        f"(a track's ring holds {result['capacity']}); load average {result['load_average']['start']:.2f} "
        f"at the start, {result['load_average']['end']:.2f} at the end; {result['bad_answers']} bad answers.",
        "",
        "| phase | open tracks (gauge) | track state (gauge) MB | server RSS MB |",
        "|---|---:|---:|---:|",
    ]
    for p in result["phases"]:
        lines.append(
            f"| {p['phase']} | {p.get('open_tracks', 0):.0f} | {p.get('track_state_bytes', 0) / MB:.2f} "
            f"| {p['rss_mb']:.1f} |"
        )
    lines += ["", "| tracks | RSS added per track, KB | gauge per track, KB |", "|---|---:|---:|"]
    for r in result["per_track"]:
        lines.append(
            f"| {r['from']} → {r['to']} | {r['rss_kb_per_track']:.1f} | {r['gauge_kb_per_track']:.1f} |"
        )
    closed = result["phases"][-1]
    freed = closed.get("open_tracks") == 0 and closed.get("track_state_bytes") == 0
    lines += [
        "",
        f"Track.nbytes {result['track_nbytes'] / 1024:.1f} KB (ring of {result['capacity']} frames); one "
        f"filled Track in Python (tracemalloc) {result['python_track_bytes'] / 1024:.1f} KB. Streams "
        f"closed: gauges {'back to 0' if freed else 'NOT back to 0'}.",
    ]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of `python -m bench.track_memory`."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.track_memory",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--tracks", type=lambda t: [int(v) for v in t.split(",")], default=[100, 1000])
    parser.add_argument("--streams", type=int, default=16, help="streams the tracks are spread over")
    parser.add_argument("--frames-per-track", type=int, default=0, help="0: a track's ring capacity")
    parser.add_argument("--people", type=int, default=8, help="most tracks (people) per LiftFrame")
    parser.add_argument("--untracked-frames", type=int, default=32, help="per stream, before 0 tracks")
    parser.add_argument("--window", type=int, default=4, help="frames in flight per stream")
    parser.add_argument("--service-flag", action="append", default=[], help="extra flag for the service")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/track_memory.json"))
    args = parser.parse_args(argv)
    if args.streams < 1 or max(args.tracks) > 63 * args.streams:
        parser.error("need --streams >= 1 and at most 63 tracks per stream (REPNET_STREAM_MAX_TRACKS 64)")
    return args


def main(argv: list[str] | None = None) -> int:
    """Run against a fresh service, print the markdown and write the JSON; the exit status."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    flags = ["--track-idle-s", "3600", "--stream-idle-timeout-s", "3600", *args.service_flag]
    contract = TemporalLifter.load(parse_settings(flags).causal_model_path).contract
    capacity = track_capacity(contract, FPS)
    load_start = load_average()
    with ServiceProcess(*flags) as service:
        measured = asyncio.run(measure(service, args, capacity))
    result = {
        "command": " ".join(["python -m bench.track_memory", *sys.argv[1:]]),
        "when": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "streams": args.streams,
        "capacity": capacity,
        "track_nbytes": track_bytes(capacity),
        "python_track_bytes": python_track_bytes(capacity),
        "load_average": {"start": load_start, "end": load_average()},
        **measured,
        "per_track": per_track(measured["phases"]),
    }
    return report(result, args.out, markdown)


if __name__ == "__main__":
    sys.exit(main())
