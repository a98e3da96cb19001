"""The transport's floor: a `grpc.aio` server whose LiftStream answers every message with one fixed reply.

    python -m bench.echo --grpc-port 50051 --http-port 8000   (bench.temporal_load starts it)

No parsing, no model, no service code on the path: each ~200-byte LiftFrame is taken as bytes and
answered with the same serialized LiftFrameResult, with every field of a tracked reply and its size
(721 bytes). What this server spends per message is what Python gRPC itself costs on the machine, the
floor under any service written on it.

The HTTP port is the same for HTTP: uvicorn with httptools, as the service runs it, in front of a bare
ASGI app that reads a `POST /lift` body whole and answers it with one fixed JSON reply of a pose
(every field the service fills, its size), no parsing and no framework. `GET /readyz` answers 200, so
that bench.server.ServiceProcess waits for it as for the service. Other flags are ignored.

measure_floor drives it with bench.temporal_load's own clients (the same frames, each answer parsed):
8 streams of 256 in flight, one stream in lock-step, and 8 cameras paced at 30 fps.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import grpc
import uvicorn

if __package__ in (None, ""):  # `python bench/echo.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.grpc_load import LIFT_STREAM
from bench.server import ServiceProcess
from bench.stats import Result
from bench.temporal_clients import Source, camera, run_id, run_streams
from bench.tracked import FPS, result_of
from repnet._proto.repnet.v1 import lifter_pb2

SERVICE, METHOD = LIFT_STREAM.strip("/").split("/")


def fixed_reply() -> bytes:
    """A tracked person's LiftFrameResult with every field the service fills (721 bytes, as a real one)."""
    ramp = [float(v) * 0.731 - 17.3 for v in range(51)]
    pose = lifter_pb2.PoseResult(
        pose_3d=ramp,
        pose_3d_camera=[-v for v in ramp],
        camera=[0.82, 0.01, -0.03, 0.02, 0.81, 0.04],
        scale=0.003081123111769557,
        rotation=[0.99, 0.01, 0.02, -0.01, 0.98, 0.1, -0.02, -0.1, 0.98],
        reprojection=ramp[:34],
        reprojection_error_px=8.838696479797363,
        visible=[True] * 17,
        imputed=[False] * 17,
        derived=[False] * 17,
        plausibility=0.8191808462142944,
        temporal=True,
        track_id="cam0-r1",
    )
    return lifter_pb2.LiftFrameResult(frame_id=4, model_id="repnet-h36m-v7", pose=pose).SerializeToString()


async def serve(host: str, grpc_port: int, http_port: int) -> None:
    """Serve the echo LiftStream and /readyz until killed."""
    reply = fixed_reply()

    async def lift_stream(
        requests: AsyncIterator[bytes], context: grpc.aio.ServicerContext
    ) -> AsyncIterator[bytes]:
        async for _ in requests:
            yield reply

    server = grpc.aio.server()
    handler = grpc.method_handlers_generic_handler(
        SERVICE,
        {METHOD: grpc.stream_stream_rpc_method_handler(lift_stream)},  # bytes in, bytes out
    )
    server.add_generic_rpc_handlers((handler,))
    server.add_insecure_port(f"{host}:{grpc_port}")
    await server.start()

    config = uvicorn.Config(http_echo(), host=host, port=http_port, http="httptools", lifespan="off")
    config.log_level = "warning"
    http = uvicorn.Server(config)
    await asyncio.gather(server.wait_for_termination(), http.serve())


def fixed_json_reply() -> bytes:
    """A POST /lift answer of one pose with every field the service fills, as JSON (fixed numbers)."""
    ramp = [round(float(v) * 0.731 - 17.3, 4) for v in range(51)]
    pose = {
        "pose_3d": [ramp[i : i + 3] for i in range(0, 51, 3)],
        "pose_3d_camera": [[-v for v in ramp[i : i + 3]] for i in range(0, 51, 3)],
        "camera": [[0.82, 0.01, -0.03], [0.02, 0.81, 0.04]],
        "scale": 0.003081123111769557,
        "rotation": [[0.99, 0.01, 0.02], [-0.01, 0.98, 0.1], [-0.02, -0.1, 0.98]],
        "reprojection": [ramp[i : i + 2] for i in range(0, 34, 2)],
        "reprojection_error_px": 8.838696479797363,
        "visible": [True] * 17,
        "imputed": [False] * 17,
        "derived": [False] * 17,
        "plausibility": 0.8191808462142944,
        "temporal": False,
    }
    return json.dumps({"model_id": "repnet-h36m-v7", "poses": [pose]}, separators=(",", ":")).encode()


def http_echo() -> Callable[..., Awaitable[None]]:
    """The bare ASGI app: POST /lift read whole and answered with fixed_json_reply, GET /readyz 200."""
    reply = fixed_json_reply()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(reply)).encode())]

    async def app(scope: dict[str, Any], receive: Callable[..., Any], send: Callable[..., Any]) -> None:
        if scope["type"] != "http":
            return
        more = True
        while more:  # the body, read and dropped
            message = await receive()
            more = message.get("more_body", False)
        if scope["method"] == "POST" and scope["path"] == "/lift":
            status, body, head = 200, reply, headers
        elif scope["path"] == "/readyz":
            status, body, head = 200, b"ok", [(b"content-length", b"2")]
        else:
            status, body, head = 404, b"", [(b"content-length", b"0")]
        await send({"type": "http.response.start", "status": status, "headers": head})
        await send({"type": "http.response.body", "body": body})

    return app


def echoed(answer: bytes, k: int) -> bool:
    """An echo's answer, parsed as the service's are: a pose."""
    return lifter_pb2.LiftFrameResult.FromString(answer).WhichOneof("result") == "pose"


FLOOR_LOADS = {  # name: (streams, frames/s each (0: as fast as the window allows), frames in flight)
    "8 streams, 256 in flight": (8, 0.0, 256),
    "1 stream, 1 frame in flight": (1, 0.0, 1),
    f"8 cameras at {FPS:g} fps": (8, FPS, 256),
}


def measure_floor(warmup: float, duration: float) -> list[Result]:
    """The echo server's cost per message under each of FLOOR_LOADS (a fresh echo server)."""
    results = []
    with ServiceProcess(module="bench.echo") as echo:
        for name, (streams, fps, window) in FLOOR_LOADS.items():
            rid = run_id()
            sources = [Source(camera(k, True, rid).frame_of, echoed) for k in range(streams)]
            tally = asyncio.run(
                run_streams(
                    echo.target, echo.pid, sources, fps=fps, window=window, warmup=warmup, duration=duration
                )
            )
            result = result_of(f"(echo floor) {name}", streams, 1, tally, tracked=True)
            result.extra["server_cpu_ms_per_frame"] = (
                1e3 * tally.cpu.get("server", 0.0) / max(result.calls, 1)
            )
            results.append(result)
    return results


def main(argv: list[str] | None = None) -> int:
    """Parse the service's address flags (others ignored) and serve."""
    parser = argparse.ArgumentParser(prog="python -m bench.echo", description=__doc__)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--grpc-port", type=int, required=True)
    parser.add_argument("--http-port", type=int, required=True)
    args, _ = parser.parse_known_args(argv)
    asyncio.run(serve(args.host, args.grpc_port, args.http_port))
    return 0


if __name__ == "__main__":
    sys.exit(main())
