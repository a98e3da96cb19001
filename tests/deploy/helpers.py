"""Helpers shared by the deploy tests: a known pose, free ports, a handle on a running service."""

from __future__ import annotations

import socket
import subprocess
from dataclasses import dataclass

# A standing person facing the camera, Human3.6M 17-joint order, pixels (x right, y down).
STANDING_POSE = [
    [500, 500], [470, 500], [475, 600], [478, 700], [530, 500], [525, 600], [522, 700], [500, 440],
    [500, 380], [500, 360], [500, 330], [540, 385], [560, 440], [570, 495], [460, 385], [440, 440],
    [430, 495],
]  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class RunningService:
    http_url: str
    grpc_address: str
    process: subprocess.Popen[bytes]
