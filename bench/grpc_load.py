"""gRPC load with grpc.aio: unary Lift in closed loops, LiftStream with a bounded number of frames in flight.

Requests are serialised once up front and sent as bytes, and answers are parsed only for spot
checks (stream answers come in frame order, the contract the fuzz test checks), so the load
generator spends its CPU on the wire, not on protobuf.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque

import grpc
import numpy as np

from bench.stats import Result, Tally, measured, sample_poses
from repnet._proto.repnet.v1 import lifter_pb2

LIFT = "/repnet.v1.PoseLifter/Lift"
LIFT_STREAM = "/repnet.v1.PoseLifter/LiftStream"
OPTIONS = [("grpc.max_receive_message_length", 64 << 20), ("grpc.max_send_message_length", 64 << 20)]
# A channel of its own connection: streams from different clients (cameras) come on different
# connections, which the kernel spreads over the service's workers (SO_REUSEPORT).
OWN_CONNECTION = [*OPTIONS, ("grpc.use_local_subchannel_pool", 1)]
STREAM_WINDOW = 256  # frames one stream keeps in flight when saturating (the server's default window)


def _pose(points: np.ndarray) -> lifter_pb2.Pose2D:
    return lifter_pb2.Pose2D(keypoints=points.ravel().round(2).tolist())


def lift_requests(poses_per_request: int, distinct: int = 64) -> list[bytes]:
    """`distinct` serialised LiftRequests of `poses_per_request` sample poses each."""
    requests = []
    for seed in range(distinct):
        poses = [_pose(p) for p in sample_poses(poses_per_request, seed=seed)]
        requests.append(lifter_pb2.LiftRequest(poses=poses).SerializeToString())
    return requests


def stream_frames(count: int = 512, seed: int = 0) -> list[bytes]:
    """`count` serialised LiftFrames of sample poses."""
    poses = sample_poses(count, seed=seed)
    return [lifter_pb2.LiftFrame(frame_id=i, pose=_pose(p)).SerializeToString() for i, p in enumerate(poses)]


async def _unary(
    target: str, requests: list[bytes], concurrency: int, warmup: float, duration: float
) -> Tally:
    async with grpc.aio.insecure_channel(target, options=OPTIONS) as channel:
        call: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes] = channel.unary_unary(LIFT)  # bytes in and out
        reply = lifter_pb2.LiftResponse.FromString(await call(requests[0], timeout=30))
        if len(reply.poses[0].pose_3d) != 51:
            raise RuntimeError(f"unexpected Lift answer: {reply}")
        tally = Tally(time.perf_counter() + warmup, time.perf_counter() + warmup + duration)

        async def client(k: int) -> None:
            i = k
            while (sent := time.perf_counter()) < tally.stop:
                try:
                    await call(requests[i % len(requests)], timeout=30)
                    ok = True
                except grpc.aio.AioRpcError:
                    ok = False
                tally.record(sent, time.perf_counter(), ok)
                i += concurrency

        await asyncio.gather(*(client(k) for k in range(concurrency)))
    return tally


def measure_unary(
    target: str, server_pid: int, poses_per_request: int, concurrency: int, duration: float = 3.0
) -> Result:
    """Closed-loop unary Lift calls from `concurrency` clients for `duration` seconds."""
    requests = lift_requests(poses_per_request)
    name = f"gRPC Lift, {poses_per_request} pose" + ("s" if poses_per_request > 1 else "")
    return measured(
        name,
        concurrency,
        poses_per_request,
        server_pid,
        lambda: asyncio.run(_unary(target, requests, concurrency, 0.5, duration)),
    )


async def _one_stream(
    call: grpc.aio.StreamStreamCall[bytes, bytes], frames: list[bytes], window: int, tally: Tally, fps: float
) -> None:
    """Send frames until tally.stop with at most `window` unanswered, `fps` a second (0: as fast as
    the window allows); answers come in frame order."""
    room = asyncio.Semaphore(window)
    sent: deque[float] = deque()

    async def write() -> None:
        i = 0
        next_at = time.perf_counter()
        while time.perf_counter() < tally.stop:
            if fps:  # a camera: one frame every 1/fps seconds
                next_at += 1 / fps
                await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
            await room.acquire()
            sent.append(time.perf_counter())
            await call.write(frames[i % len(frames)])
            i += 1
        await call.done_writing()

    writer = asyncio.create_task(write())
    received = 0
    async for answer in call:
        received += 1
        ok = True
        if received % 97 == 1:  # spot check: a pose for the frame sent
            result = lifter_pb2.LiftFrameResult.FromString(answer)
            ok = result.WhichOneof("result") == "pose" and result.frame_id == (received - 1) % len(frames)
        tally.record(sent.popleft(), time.perf_counter(), ok)
        room.release()
    await writer
    tally.errors += len(sent)  # frames never answered


async def _streams(target: str, count: int, window: int, fps: float, warmup: float, duration: float) -> Tally:
    """`count` streams, each on a connection of its own (as `count` clients would open them)."""
    channels = [grpc.aio.insecure_channel(target, options=OWN_CONNECTION) for _ in range(count)]
    try:
        tally = Tally(time.perf_counter() + warmup, time.perf_counter() + warmup + duration)
        calls = [c.stream_stream(LIFT_STREAM)(timeout=warmup + duration + 60) for c in channels]
        await asyncio.gather(
            *(_one_stream(c, stream_frames(seed=k), window, tally, fps) for k, c in enumerate(calls))
        )
    finally:
        for channel in channels:
            await channel.close()
    return tally


def measure_stream(
    target: str,
    server_pid: int,
    streams: int,
    window: int = STREAM_WINDOW,
    duration: float = 3.0,
    fps: float = 0,
) -> Result:
    """`streams` concurrent LiftStreams, each with at most `window` frames unanswered (1: lock-step)
    and, if `fps`, sending at that rate like a camera."""
    if fps:
        name = f"gRPC LiftStream, {fps:g} frames/s each"
    else:
        name = "gRPC LiftStream, 1 frame in flight" if window == 1 else f"gRPC LiftStream, {window} in flight"
    return measured(
        name,
        streams,
        1,
        server_pid,
        lambda: asyncio.run(_streams(target, streams, window, fps, 0.5, duration)),
    )
