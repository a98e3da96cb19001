"""bench.ceiling's model-free lifter and how bench.run reports the ceiling beside the targets."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench import echo
from bench.ceiling import ConstantLifter
from bench.roof import RoofRow
from bench.run import CEILING, FLOOR, Report
from bench.server import ServiceProcess
from bench.stats import Result, sample_poses
from repnet.runtime.lifter import Lifter
from tests.conftest import reply_of


def test_constant_lifter_answers_every_pose_with_one_real_prediction(lifter: Lifter) -> None:
    constant = ConstantLifter(lifter)
    poses = sample_poses(5, seed=3)
    prediction = constant.lift(poses, np.ones(poses.shape[:2], bool))
    assert len(prediction) == 5 and prediction.pose_3d.shape == (5, 17, 3)
    np.testing.assert_array_equal(prediction.camera[4], constant.answer.camera[0])
    assert not prediction.failed.any()
    assert np.isfinite(reply_of(constant, poses).columns["reprojection"]).all()  # the reply can be built


def result(name: str, concurrency: int, frames: int, p50: float = 1.0) -> Result:
    return Result(name, concurrency, frames, frames, 1.0, {"p50": p50, "p99": 2 * p50})


def test_targets_name_the_ceiling_beside_the_service() -> None:
    roof = [RoofRow("session.run", 1, 100, 0.2, {}), RoofRow("session.run", 256, 40, 1.0, {})]
    stream = "gRPC LiftStream, 256 in flight"
    report = Report(
        when="", command="", machine={}, model="m.onnx", model_id="m", service_flags=[], intra_op_threads=0,
        roof=roof,
        results=[
            result("HTTP /lift, 1 pose", 1, 100, p50=4.0),
            result(stream, 1, 2_000),
            result(CEILING + stream, 1, 5_000),
            result(CEILING + "HTTP /lift, 1 pose", 1, 500, p50=1.5),
            result(FLOOR + "HTTP /lift, 1 pose", 1, 900, p50=0.6),
        ],
        server_rss_mb={"start": 1.0, "end": 1.0},
    )  # fmt: skip
    assert report.roof_best == 10_240 and report.roof_batch1_ms == 2.0
    http, x1 = report.targets
    assert http.startswith("MISSED: HTTP single pose c1 p50 4.00 ms")
    assert "roof's batch-1 call: 2.00 ms" in http and "without the model p50 1.50 ms" in http
    assert http.endswith("the HTTP floor (uvicorn, no app code) p50 0.60 ms")
    assert x1.startswith("MISSED: LiftStream x1 at 0.20 of the roof (target >= 0.7)")
    assert x1.endswith("without the model the same load reaches 0.49")


def test_the_roof_is_the_better_of_the_passes_before_and_after_the_loads() -> None:
    report = Report(
        when="", command="", machine={"cpus": 2, "cpu": "x"}, model="m.onnx", model_id="m",
        service_flags=[], intra_op_threads=0,
        roof=[RoofRow("session.run", 1, 100, 0.3, {}), RoofRow("session.run", 256, 20, 1.0, {})],
        roof_end=[RoofRow("session.run", 1, 100, 0.2, {}), RoofRow("session.run", 256, 40, 1.0, {})],
        results=[], server_rss_mb={"start": 1.0, "end": 1.0},
    )  # fmt: skip
    assert report.roof_best == 10_240 and report.roof_batch1_ms == 2.0
    assert "Roof after them" in report.markdown()


def test_the_http_floor_answers_a_lift_as_the_bench_client_reads_it_and_readyz() -> None:
    app = echo.http_echo()

    def call(method: str, path: str, chunks: list[bytes]) -> tuple[int, bytes]:
        incoming = [
            {"type": "http.request", "body": c, "more_body": i < len(chunks) - 1}
            for i, c in enumerate(chunks)
        ]
        sent: list[dict[str, Any]] = []

        async def receive() -> dict[str, Any]:
            return incoming.pop(0)

        async def send(message: dict[str, Any]) -> None:
            sent.append(message)

        asyncio.run(app({"type": "http", "method": method, "path": path}, receive, send))
        assert not incoming  # the whole body was read
        return sent[0]["status"], sent[1]["body"]

    status, body = call("POST", "/lift", [b'{"poses": [', b"]}"])
    pose = json.loads(body)["poses"][0]
    assert status == 200 and len(pose["pose_3d"]) == 17 and len(pose["reprojection"]) == 17
    assert call("GET", "/readyz", [b""]) == (200, b"ok")
    assert call("GET", "/other", [b""])[0] == 404


def test_the_ceiling_runs_the_services_workers_and_answers_from_the_stored_prediction() -> None:
    """bench.ceiling's supervisor starts its workers as `python -m bench.ceiling` (not the service),
    so its figures compare with a service of as many workers."""
    with ServiceProcess("--workers", "2", module="bench.ceiling") as service:
        workers = [
            Path(f"/proc/{p}/cmdline").read_bytes().split(b"\0")
            for p in map(int, Path(f"/proc/{service.pid}/task/{service.pid}/children").read_text().split())
        ]
        assert len(workers) == 2 and all(cmd[1:3] == [b"-m", b"bench.ceiling"] for cmd in workers)
        poses = sample_poses(2, seed=1).tolist()
        first = httpx.post(
            f"{service.url}/lift", json={"poses": [{"keypoints": poses[0]}]}, timeout=10
        ).json()
        second = httpx.post(
            f"{service.url}/lift", json={"poses": [{"keypoints": poses[1]}]}, timeout=10
        ).json()
    assert first["poses"][0]["camera"] == second["poses"][0]["camera"]  # one stored answer, any input
