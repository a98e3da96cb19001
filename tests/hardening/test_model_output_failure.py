"""Non-finite model output at serving time: a clean 500 / INTERNAL with a stable message (no
exception class), counted, and the other requests of the same run still answered."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any

import grpc
import httpx
import numpy as np
import pytest

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.runtime.lifter import Lifter
from repnet.server.app import Service
from repnet.server.config import Settings
from tests.conftest import POSE_2D
from tests.hardening.conftest import http_url, running

# The message both transports give; the probe saw a leaked numpy.linalg.LinAlgError.
MESSAGE = "the model produced non-finite output for this input; this is a server fault"
POISON_X = 7777.0  # a pelvis x coordinate that makes the broken session answer NaN


class NaNSession:
    """The real onnxruntime session, except that poses whose pelvis is at POISON_X get NaN."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def run(self, names: list[str], feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        outputs = self.inner.run(names, feeds)
        poisoned = feeds["keypoints_2d"][:, 0, 0] == POISON_X  # (N,)
        outputs[1][poisoned] = np.nan  # camera
        return list(outputs)


@pytest.fixture
def broken(lifter: Lifter) -> Iterator[Service]:
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1, max_wait_ms=20,
                        shutdown_grace_s=2)  # fmt: skip
    with running(settings, Lifter(NaNSession(lifter.session), lifter.path)) as service:
        yield service


def poisoned_pose() -> np.ndarray:
    pose = POSE_2D.copy()
    pose[0, 0] = POISON_X
    return pose


async def lift_together(url: str) -> list[httpx.Response]:
    """A poisoned and a healthy request at once, so that they can share a run."""
    async with httpx.AsyncClient(base_url=url, timeout=30) as client:
        bodies = [{"keypoints": poisoned_pose().tolist()}, {"keypoints": POSE_2D.tolist()}] * 4
        return list(await asyncio.gather(*(client.post("/lift", json=b) for b in bodies)))


def test_non_finite_output_is_a_clean_counted_server_error(broken: Service) -> None:
    url = http_url(broken)
    answers = asyncio.run(lift_together(url))
    assert [r.status_code for r in answers] == [500, 200] * 4, [r.text[:200] for r in answers]
    for bad, good in zip(answers[::2], answers[1::2], strict=True):
        assert bad.json() == {"detail": MESSAGE}
        assert len(good.json()["poses"][0]["pose_3d"]) == 17

    with grpc.insecure_channel(f"127.0.0.1:{broken.grpc_server.port}") as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        pose = lifter_pb2.Pose2D(keypoints=poisoned_pose().ravel().tolist())
        with pytest.raises(grpc.RpcError) as failed:
            stub.Lift(lifter_pb2.LiftRequest(poses=[pose]), timeout=30)
        assert failed.value.code() == grpc.StatusCode.INTERNAL
        assert failed.value.details() == MESSAGE
        healthy = lifter_pb2.Pose2D(keypoints=POSE_2D.ravel().tolist())
        frames = [lifter_pb2.LiftFrame(frame_id=i, pose=p) for i, p in enumerate([pose, healthy, pose])]
        results = list(stub.LiftStream(iter(frames), timeout=30))
        assert [r.WhichOneof("result") for r in results] == ["error", "pose", "error"]
        assert results[0].error.code == grpc.StatusCode.INTERNAL.value[0]
        assert results[0].error.message == MESSAGE

    value = broken.metrics.registry.get_sample_value
    assert value("repnet_model_output_errors_total") >= 4 + 1 + 2  # poses, however they were batched
    assert value("repnet_requests_total", {"transport": "http", "method": "Lift", "outcome": "error"}) == 4
    assert value("repnet_requests_total", {"transport": "grpc", "method": "Lift", "outcome": "error"}) == 1
    assert httpx.get(f"{url}/readyz", timeout=5).status_code == 200
