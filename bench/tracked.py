"""Tracked LiftStream load: people moving in a loop, their frames as LiftFrame bytes, and a stream
driver that paces or floods frames and checks every answer.

Frames are built from pieces serialised once: protobuf merges concatenated messages, so a frame is
the bytes of its header (frame id, track id, fps) followed by the bytes of a LiftFrame that holds
only the pose (or, for a frame of several people, one `people` entry per person). The load
generator spends its CPU on the wire, not on protobuf.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import grpc
import httpx
import numpy as np

from bench.grpc_load import LIFT_STREAM
from bench.server import cpu_seconds
from bench.stats import Result, Tally, latency_summary, sample_poses
from repnet._proto.repnet.v1 import lifter_pb2

FPS = 30.0  # a camera's frame rate
CYCLE = 60  # frames of one loop of a person's movement (2 s at 30 fps)
# h36m17 joints that swing when walking: knees, feet (legs), elbows, wrists (arms); the right side
# (1-3, 14-16) against the left (4-6, 11-13), arms against legs.
SWING = {2: 0.04, 3: 0.08, 5: -0.04, 6: -0.08, 15: -0.03, 16: -0.06, 12: 0.03, 13: 0.06}


def moving_clip(frames: int = CYCLE, seed: int = 0) -> np.ndarray:
    """(frames, 17, 2) float32 px: one person (a sample pose) walking on the spot and swaying
    sideways, one loop over `frames` (the frame after the last is the first again)."""
    base = sample_poses(1, seed=seed)[0].astype(np.float64)
    height = float(np.ptp(base[:, 1]))
    phase = 2 * np.pi * np.arange(frames) / frames
    clip = np.repeat(base[None], frames, axis=0)
    clip[:, :, 0] += 0.05 * height * np.sin(phase)[:, None]  # the body sways
    for joint, amplitude in SWING.items():  # the limbs swing forwards and back
        clip[:, joint, 0] += amplitude * height * np.sin(2 * phase)
        clip[:, joint, 1] -= 0.2 * abs(amplitude) * height * np.cos(2 * phase)
    return clip.astype(np.float32)


def pose_message(points: np.ndarray) -> lifter_pb2.Pose2D:
    """A Pose2D of (17, 2) px."""
    return lifter_pb2.Pose2D(keypoints=points.ravel().round(2).tolist())


def pose_parts(clip: np.ndarray) -> list[bytes]:
    """Per frame of the clip: a serialised LiftFrame holding only that pose."""
    return [lifter_pb2.LiftFrame(pose=pose_message(p)).SerializeToString() for p in clip]


def single_frame(parts: Sequence[bytes], frame: int, track_id: str = "", fps: float = FPS) -> bytes:
    """Frame number `frame` of one person: tracked with `track_id` at `fps`, or untracked (empty)."""
    if track_id:
        head = lifter_pb2.LiftFrame(frame_id=frame, track_id=track_id, fps=fps)
    else:
        head = lifter_pb2.LiftFrame(frame_id=frame)
    return head.SerializeToString() + parts[frame % len(parts)]


PEOPLE_TAG = bytes([lifter_pb2.LiftFrame.DESCRIPTOR.fields_by_name["people"].number << 3 | 2])


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        low, n = n & 0x7F, n >> 7
        out.append(low | 0x80 if n else low)
        if not n:
            return bytes(out)


def people_entry(track_id: str, pose_part: bytes) -> bytes:
    """One serialised LiftFrame.people entry: `track_id` and a pose given as a serialised
    TrackedPose that holds only the pose."""
    payload = lifter_pb2.TrackedPose(track_id=track_id).SerializeToString() + pose_part
    return PEOPLE_TAG + _varint(len(payload)) + payload


@dataclass
class Crowd:
    """People of multi-person frames (LiftFrame.people): person k moves as clip k, each clip frame
    serialised once (a TrackedPose that holds only the pose)."""

    parts: list[list[bytes]]

    @classmethod
    def of(cls, people: int, seed: int = 0) -> Crowd:
        """`people` different people (clips of CYCLE frames)."""
        return cls.of_clips([moving_clip(CYCLE, seed=seed + k) for k in range(people)])

    @classmethod
    def of_clips(cls, clips: Sequence[np.ndarray]) -> Crowd:
        """People moving as the (frames, 17, 2) clips."""
        return cls(
            [[lifter_pb2.TrackedPose(pose=pose_message(p)).SerializeToString() for p in c] for c in clips]
        )

    def frame(self, frame: int, track_ids: Sequence[str], fps: float = FPS) -> bytes:
        """Frame number `frame` with one tracked person per id (the k-th moves as person k)."""
        head = lifter_pb2.LiftFrame(frame_id=frame, fps=fps).SerializeToString()
        entries = (
            people_entry(t, (parts := self.parts[k % len(self.parts)])[frame % len(parts)])
            for k, t in enumerate(track_ids)
        )
        return head + b"".join(entries)


Check = Callable[[bytes, int], bool]  # (answer, the index of the frame it answers) -> it is right


def expect_pose(temporal: bool, every: int = 1) -> Check:
    """Answer k (every `every`th is parsed) is a pose for frame id k, temporal or not as expected."""

    def check(answer: bytes, k: int) -> bool:
        if k % every:
            return True
        result = lifter_pb2.LiftFrameResult.FromString(answer)
        return (
            result.frame_id == k
            and result.WhichOneof("result") == "pose"
            and result.pose.temporal == temporal
            and len(result.pose.pose_3d) == 51
        )

    return check


def expect_people(count: int, every: int = 1) -> Check:
    """Answer k (every `every`th is parsed) is for frame id k with `count` people, each a temporal pose."""

    def check(answer: bytes, k: int) -> bool:
        if k % every:
            return True
        result = lifter_pb2.LiftFrameResult.FromString(answer)
        return (
            result.frame_id == k
            and len(result.people) == count
            and all(p.WhichOneof("result") == "pose" and p.pose.temporal for p in result.people)
        )

    return check


@dataclass
class Load(Tally):
    """A Tally that also counts the frames sent in the window (a paced client that falls behind
    sends fewer than it offers) and the CPU seconds used within it (`watch`): by the server, this
    client process and the whole machine."""

    sent: int = 0
    cpu: dict[str, float] = field(default_factory=dict)


def _cpu_now(server_pid: int) -> dict[str, float]:
    return {
        "server": cpu_seconds(server_pid),
        "client": time.process_time(),
        "machine": machine_busy_seconds(),
        "wall": time.perf_counter(),
    }


async def watch(server_pid: int, tally: Load) -> None:
    """Fill tally.cpu with the CPU seconds used from tally.start to tally.stop (run beside the load)."""
    await asyncio.sleep(max(0.0, tally.start - time.perf_counter()))
    before = _cpu_now(server_pid)
    await asyncio.sleep(max(0.0, tally.stop - time.perf_counter()))
    after = _cpu_now(server_pid)
    tally.cpu = {k: after[k] - before[k] for k in before}


def result_of(name: str, concurrency: int, frames_per_call: int, tally: Load, **extra: object) -> Result:
    """The Result of one measured window: frames/s and latency, the CPU of the server, the client and
    everything else on the machine (cores, over the window), the frames sent and the load average."""
    cpu, seconds = tally.cpu, tally.stop - tally.start
    wall = cpu.get("wall", seconds) or seconds
    server, client = cpu.get("server", 0.0) / wall, cpu.get("client", 0.0) / wall
    others = cpu.get("machine", 0.0) / wall - server - client
    return Result(
        name=name,
        concurrency=concurrency,
        frames=tally.completed * frames_per_call,
        calls=tally.completed,
        seconds=seconds,
        latency_ms=latency_summary(tally.latencies),
        errors=tally.errors,
        server_cpu=server,
        client_cpu=client,
        extra={"sent": tally.sent, "other_cpu": others, "load_1m": load_average(), **extra},
    )


async def drive(
    call: grpc.aio.StreamStreamCall[bytes, bytes],
    frame_of: Callable[[int], bytes],
    tally: Load,
    check: Check,
    *,
    fps: float = 0.0,
    window: int = 256,
    phase_s: float = 0.0,
) -> None:
    """Send frame_of(0), frame_of(1), ... on one LiftStream until tally.stop: `fps` a second after
    `phase_s` (a camera; 0: as fast as `window` unanswered frames allow), each answer checked.
    Frames never answered (the call failed) count as errors."""
    room = asyncio.Semaphore(window)
    sent: deque[float] = deque()

    async def write() -> None:
        frame, next_at = 0, time.perf_counter() + phase_s
        while True:
            if fps:
                await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
                next_at += 1 / fps
            await room.acquire()
            now = time.perf_counter()
            if now >= tally.stop:
                break
            sent.append(now)
            tally.sent += tally.start <= now
            await call.write(frame_of(frame))
            frame += 1
        await call.done_writing()

    writer = asyncio.create_task(write())
    received = 0
    try:
        async for answer in call:
            tally.record(sent.popleft(), time.perf_counter(), check(answer, received))
            received += 1
            room.release()
        await writer
    except grpc.aio.AioRpcError:
        writer.cancel()
        with contextlib.suppress(asyncio.CancelledError, grpc.aio.AioRpcError):
            await writer
    tally.errors += len(sent)


def machine_busy_seconds() -> float:
    """CPU seconds all processes of the machine have used so far (/proc/stat, every core)."""
    with open("/proc/stat") as f:
        values = [int(v) for v in f.readline().split()[1:]]
    idle = values[3] + values[4]  # idle, iowait
    return (sum(values[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def load_average() -> float:
    """The machine's 1-minute load average."""
    return os.getloadavg()[0]


GAUGES = {"repnet_open_tracks": "open_tracks", "repnet_track_state_bytes": "track_state_bytes"}


def parse_gauges(text: str) -> dict[str, float]:
    """The track gauges (open tracks, bytes of track state) from a Prometheus text page."""
    found = {}
    for line in text.splitlines():
        name, _, value = line.partition(" ")
        if name in GAUGES:
            found[GAUGES[name]] = float(value)
    return found


async def track_gauges(url: str) -> dict[str, float]:
    """The server's track gauges, from GET /metrics."""
    async with httpx.AsyncClient(timeout=10) as client:
        return parse_gauges((await client.get(f"{url}/metrics")).text)


class Lane:
    """One LiftStream driven by count rather than time: send(frames) writes them (at most `window`
    unanswered) while reading their answers; the stream stays open between sends."""

    def __init__(self, channel: grpc.aio.Channel, window: int = 8, timeout: float = 3600.0) -> None:
        self.call: grpc.aio.StreamStreamCall[bytes, bytes] = channel.stream_stream(LIFT_STREAM)(
            timeout=timeout
        )
        self.window = window

    async def send(
        self,
        count: int,
        frame_of: Callable[[int], bytes],
        check: Check,
        on_answer: Callable[[], None] | None = None,
    ) -> int:
        """Send frame_of(0) .. frame_of(count - 1) and read their answers, each checked as
        check(answer, i); returns the bad ones, frames never answered included."""
        room = asyncio.Semaphore(self.window)

        async def write() -> None:
            for i in range(count):
                await room.acquire()
                await self.call.write(frame_of(i))

        writer = asyncio.create_task(write())
        bad = answered = 0
        try:
            while answered < count:
                answer = await self.call.read()
                if answer is grpc.aio.EOF:
                    break
                bad += not check(answer, answered)
                answered += 1
                room.release()
                if on_answer is not None:
                    on_answer()
        except grpc.aio.AioRpcError:
            pass
        if answered == count:
            await writer
        else:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, grpc.aio.AioRpcError):
                await writer
        return bad + count - answered

    async def close(self) -> None:
        """Half-close and wait for the end of the call."""
        await self.call.done_writing()
        while await self.call.read() is not grpc.aio.EOF:
            pass
