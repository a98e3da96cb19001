"""The clients of bench.temporal_load: a paced camera (one person, tracked or not), a crowd's frames, and
the streams that send them for a while against the service."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass

import grpc

from bench.grpc_load import LIFT_STREAM, OWN_CONNECTION
from bench.tracked import (
    Check,
    Crowd,
    Load,
    drive,
    expect_people,
    expect_pose,
    moving_clip,
    pose_parts,
    single_frame,
    watch,
)

_RUNS = itertools.count(1)  # loads started in this process


@dataclass(frozen=True)
class Source:
    """What one stream sends: frame_of(n), how answers are checked, the people per frame."""

    frame_of: Callable[[int], bytes]
    check: Check
    people: int = 1


def camera(index: int, tracked: bool, run_id: str) -> Source:
    """One camera's frames: a person (moving as person `index`) tracked at 30 fps, or untracked."""
    parts = pose_parts(moving_clip(seed=index))
    track_id = f"cam{index}-{run_id}" if tracked else ""
    return Source(lambda n: single_frame(parts, n, track_id), expect_pose(temporal=tracked))


def crowd_frames(people: int, run_id: str) -> Source:
    """Frames of `people` tracked people (LiftFrame.people) at 30 fps."""
    crowd = Crowd.of(people)
    ids = [f"p{k}-{run_id}" for k in range(people)]
    return Source(lambda n: crowd.frame(n, ids), expect_people(people), people)


async def run_streams(
    target: str,
    server_pid: int,
    sources: list[Source],
    *,
    fps: float,
    window: int,
    warmup: float,
    duration: float,
    spread: bool = True,
) -> Load:
    """One LiftStream per source, paced at `fps` (0: flooding, `window` frames in flight), measured
    for `duration` seconds after `warmup`; paced streams' send times are spread evenly over one
    frame period (`spread`) or all at once."""
    channels = [grpc.aio.insecure_channel(target, options=OWN_CONNECTION) for _ in sources]  # a camera each
    try:
        start = time.perf_counter() + warmup
        tally = Load(start, start + duration)
        calls = [c.stream_stream(LIFT_STREAM)(timeout=warmup + duration + 60) for c in channels]
        step = 1 / (fps * len(sources)) if fps and spread else 0.0
        await asyncio.gather(
            watch(server_pid, tally),
            *(
                drive(call, s.frame_of, tally, s.check, fps=fps, window=window, phase_s=k * step)
                for k, (call, s) in enumerate(zip(calls, sources, strict=True))
            ),
        )
    finally:
        for channel in channels:
            await channel.close()
    return tally


def run_id() -> str:
    """A new suffix for track ids: every load starts its tracks afresh."""
    return f"r{next(_RUNS)}"
