"""Shared fixtures: the bundled model, a fresh metrics registry, the HTTP app and a live gRPC server."""

from __future__ import annotations

import contextlib
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from prometheus_client import CollectorRegistry

with warnings.catch_warnings():  # starlette's note about httpx2 is not ours to act on
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

from repnet._proto.repnet.v1 import lifter_pb2_grpc
from repnet.core.inputs import Limits, PoseInput
from repnet.core.keypoints import prepare_poses
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter, Prediction
from repnet.runtime.loading import BUNDLED_MODEL, BUNDLED_OFFLINE
from repnet.runtime.replies import Replies, build_replies
from repnet.server.app import build_app, build_grpc_server, limits_of
from repnet.server.config import Settings
from repnet.server.grpc.server import Health
from repnet.server.metrics import Metrics

# A person in mid-stride, template frame (mm; x right in the image, y down, z away from the
# camera, facing it), Human3.6M 17-joint order; the pelvis at the origin.
POSE_3D = np.array(
    [[0, 0, 0], [-130, 5, 10], [-150, 430, -60], [-145, 860, 20], [130, -5, -10], [135, 445, 70],
     [150, 880, 150], [5, -235, 15], [10, -490, 20], [15, -590, -40], [20, -710, 0], [150, -440, 30],
     [215, -190, 80], [250, 40, 20], [-135, -435, 10], [-210, -180, -50], [-240, 50, -30]],
    dtype=np.float64,
)  # fmt: skip
FOCAL_PX = 1145.0
CENTRE_PX = np.array([512.0, 515.0])


def project(pose_3d: np.ndarray, yaw_deg: float = 25.0, distance_mm: float = 4500.0) -> np.ndarray:
    """(17, 3) template-frame pose turned by `yaw_deg` about the vertical and seen by a pinhole
    camera `distance_mm` away -> (17, 2) pixels."""
    a = np.deg2rad(yaw_deg)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    camera = pose_3d @ turn.T + [0, 0, distance_mm]  # (17, 3)
    return np.asarray(FOCAL_PX * camera[:, :2] / camera[:, 2:] + CENTRE_PX)


POSE_2D = project(POSE_3D)  # (17, 2) px


def expected_reprojection(
    camera: np.ndarray, pose_3d: np.ndarray, points: np.ndarray, visible: np.ndarray
) -> np.ndarray:
    """K X (2x3 @ 17x3) mapped into pixels by the input normalisation, written out independently:
    centre K X and the input on their visible joints, scale by the input's std, add its mean."""
    kx = pose_3d @ camera.T  # (17, 2)
    vis_points = points[visible]
    mean = vis_points.mean(axis=0)
    std = np.sqrt(((vis_points - mean) ** 2).sum() / (2 * len(vis_points)))
    return np.asarray((kx - kx[visible].mean(axis=0)) * std + mean)


def load_model(path: Path) -> Lifter:
    """The model at `path` with the service's session settings, on one thread."""
    return Lifter.load(path, Settings(intra_op_threads=1))


def reply_of(lifter: Lifter, points: np.ndarray) -> Replies:
    """The replies to (N, 17, 2) h36m17 poses, every joint present, as a request would get them."""
    poses = [PoseInput(p.astype(np.float64), np.ones(len(p), bool)) for p in points]
    inputs = prepare_poses(poses, limits_of(Settings())).check()
    return build_replies(inputs, lifter.lift(inputs.keypoints_2d, inputs.visible)).check()


@pytest.fixture(scope="session")
def lifter() -> Lifter:
    """The bundled model, or the one REPNET_MODEL_PATH names (to test another export)."""
    return load_model(Path(os.environ.get("REPNET_MODEL_PATH", BUNDLED_MODEL)))


@pytest.fixture
def trained(lifter: Lifter) -> Lifter:
    """The lifter, or a skip while the bundled model is the untrained placeholder."""
    if lifter.info.model_id.startswith("untrained"):
        pytest.skip(f"bundled model {lifter.info.model_id!r} is untrained")
    return lifter


@pytest.fixture
def settings() -> Settings:
    """The servers' settings in tests: small requests, and a gRPC server on a free localhost port."""
    return Settings(
        host="localhost", grpc_port=0, grpc_workers=8, max_request_poses=16, max_body_bytes=64 * 1024
    )


@pytest.fixture
def limits(settings: Settings) -> Limits:
    return limits_of(settings)


@pytest.fixture
def registry() -> CollectorRegistry:
    return CollectorRegistry()


@pytest.fixture
def metrics(registry: CollectorRegistry, lifter: Lifter) -> Metrics:
    metrics = Metrics(registry)
    metrics.set_model(lifter.info.model_id, lifter.info.skeleton)
    return metrics


class GatedLifter(Lifter):
    """The real lifter, except that a run waits while the gate is closed (deterministic batching)."""

    def __init__(self, inner: Lifter) -> None:
        super().__init__(inner.session, inner.path)
        self.gate = threading.Event()
        self.gate.set()
        self.entered = threading.Event()  # set when a run reached the gate
        self.batches: list[int] = []

    def lift(self, keypoints_2d: np.ndarray, visibility: np.ndarray) -> Prediction:
        self.entered.set()
        self.gate.wait(timeout=30)
        self.batches.append(int(keypoints_2d.shape[0]))
        return super().lift(keypoints_2d, visibility)


@pytest.fixture
def gated(lifter: Lifter) -> Iterator[GatedLifter]:
    gated = GatedLifter(lifter)
    yield gated
    gated.gate.set()


@pytest.fixture
def engine_factory(metrics: Metrics) -> Iterator[Callable[..., LiftBatcher]]:
    """Build Engines on the shared metrics; all are closed at teardown."""
    engines: list[LiftBatcher] = []

    def build(
        lifter: Lifter, max_batch: int = 64, max_wait_s: float = 0.001, queue_size: int = 64
    ) -> LiftBatcher:
        engine = LiftBatcher(
            lifter, metrics, max_batch=max_batch, max_wait_s=max_wait_s, queue_size=queue_size
        )
        engines.append(engine)
        return engine

    yield build
    for engine in engines:
        engine.close(timeout=10)


@pytest.fixture
def engine(engine_factory: Callable[..., LiftBatcher], lifter: Lifter) -> LiftBatcher:
    return engine_factory(lifter)


@pytest.fixture
def client(engine: LiftBatcher, metrics: Metrics, settings: Settings) -> Iterator[TestClient]:
    with TestClient(
        build_app(engine, metrics, settings), base_url="http://localhost"
    ) as client:  # a loopback Host
        yield client


@dataclass
class GrpcHandle:
    stub: lifter_pb2_grpc.PoseLifterStub
    channel: grpc.Channel
    health: Health
    port: int


@pytest.fixture
def grpc_handle(engine: LiftBatcher, metrics: Metrics, settings: Settings) -> Iterator[GrpcHandle]:
    """A real gRPC server on a free localhost port, sharing `engine` with `client`."""
    server = build_grpc_server(engine, metrics, settings)
    server.start()
    channel = grpc.insecure_channel(f"localhost:{server.port}")
    try:
        yield GrpcHandle(lifter_pb2_grpc.PoseLifterStub(channel), channel, server.health, server.port)  # type: ignore[no-untyped-call]
    finally:
        channel.close()
        server.stop(0).wait()


@pytest.fixture
def stub(grpc_handle: GrpcHandle) -> lifter_pb2_grpc.PoseLifterStub:
    return grpc_handle.stub


@dataclass(frozen=True)
class LiveService:
    http_url: str
    grpc_target: str


@contextlib.contextmanager
def running_service(settings: Settings, lifter: Lifter) -> Iterator[LiveService]:
    """`python -m repnet serve` in-process with `settings`: uvicorn and gRPC on their ports (0: free ones)."""
    from repnet.server.app import build_service

    service = build_service(settings, lifter)
    thread = threading.Thread(target=service.run, name="live-service", daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not service.http.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the live service did not start")
        time.sleep(0.02)
    port = service.http.servers[0].sockets[0].getsockname()[1]
    try:
        yield LiveService(f"http://{settings.host}:{port}", f"{settings.host}:{service.grpc_server.port}")
    finally:
        service.begin_shutdown()
        thread.join(timeout=15)


def live_settings(**changes: Any) -> Settings:
    """The settings of a live test service: localhost, free ports, one onnxruntime thread."""
    return Settings(
        host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1, shutdown_grace_s=1, **changes
    )


@pytest.fixture(scope="module")
def live_service(lifter: Lifter) -> Iterator[LiveService]:
    """`python -m repnet serve` in-process: uvicorn and gRPC on free localhost ports (for clients)."""
    with running_service(live_settings(), lifter) as service:
        yield service


# A temporal request of the small service holds this many poses: a longer clip is cut (repnet.client.chunks).
SMALL_TEMPORAL_POSES = 120


@pytest.fixture(scope="module")
def small_service(lifter: Lifter) -> Iterator[LiveService]:
    """A live service whose temporal requests hold SMALL_TEMPORAL_POSES poses."""
    with running_service(live_settings(max_temporal_poses=SMALL_TEMPORAL_POSES), lifter) as service:
        yield service


# The temporal modes the bundled models give: offline once its model is in service/models/.
TEMPORAL_MODES = [
    "causal",
    pytest.param(
        "offline",
        marks=pytest.mark.skipif(not BUNDLED_OFFLINE.is_file(), reason=f"no {BUNDLED_OFFLINE.name}"),
    ),
]
