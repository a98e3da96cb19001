"""`python -m repnet serve`: settings from env and flags, start-up failures, shutdown that drains."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import httpx
import pytest
from grpc_health.v1 import health_pb2
from pydantic import ValidationError

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.runtime.lifter import Lifter
from repnet.runtime.loading import BUNDLED_MODEL
from repnet.server.app import build_service, main, parse_settings
from repnet.server.config import Settings
from tests.conftest import POSE_2D, GatedLifter
from tests.service.invalid_inputs import good, to_proto_pose

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def test_flags_override_environment_which_overrides_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("REPNET_MAX_BATCH", "32")
    monkeypatch.setenv("REPNET_HTTP_PORT", "9000")
    settings = parse_settings(["--http-port", "9100", "--max-wait-ms", "0.5", "--log-level", "debug"])
    assert (settings.http_port, settings.max_batch, settings.max_wait_ms) == (9100, 32, 0.5)
    assert settings.log_level == "debug" and settings.grpc_port == 50051


def test_settings_refuse_a_queue_smaller_than_the_largest_request() -> None:
    with pytest.raises(ValidationError, match="queue_size"):
        Settings(queue_size=10, max_request_poses=20)


def test_invalid_flag_value_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--max-batch", "0"]) == 2
    assert "max_batch" in capsys.readouterr().err


def test_missing_model_fails_at_start(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert main(["--model-path", str(tmp_path / "absent.onnx"), "--http-port", "0", "--grpc-port", "0"]) == 1
    assert f"cannot start: model file not found: {tmp_path / 'absent.onnx'}" in caplog.text


def run_service(*flags: str, log: Path) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "REPNET_INTRA_OP_THREADS": "1"}
    with log.open("wb") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "repnet", "serve", *flags],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )


def test_corrupt_model_fails_at_start_with_a_clear_message(tmp_path: Path) -> None:
    corrupt = tmp_path / "model.onnx"
    corrupt.write_bytes(BUNDLED_MODEL.read_bytes()[:2000])
    process = run_service(
        "--model-path", str(corrupt), "--http-port", "0", "--grpc-port", "0", log=tmp_path / "log"
    )
    assert process.wait(timeout=60) == 1
    assert f"cannot start: cannot load model {corrupt}" in (tmp_path / "log").read_text()


def test_sigterm_drains_an_open_stream_then_exits_0(tmp_path: Path) -> None:
    http_port, grpc_port = free_port(), free_port()
    log = tmp_path / "log"
    process = run_service(
        "--host",
        "127.0.0.1",
        "--http-port",
        str(http_port),
        "--grpc-port",
        str(grpc_port),
        "--shutdown-grace-s",
        "20",
        log=log,
    )
    try:
        wait_until(lambda: _ready(f"http://127.0.0.1:{http_port}/readyz", process), "readiness", timeout=60)
        release = threading.Event()

        def frames() -> Iterator[lifter_pb2.LiftFrame]:
            yield lifter_pb2.LiftFrame(frame_id=1, pose=to_proto_pose(good()))
            release.wait(30)  # the stream stays in flight across SIGTERM
            yield lifter_pb2.LiftFrame(frame_id=2, pose=to_proto_pose(good(keypoints=(POSE_2D + 9).tolist())))

        with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as channel:
            results = lifter_pb2_grpc.PoseLifterStub(channel).LiftStream(frames(), timeout=60)  # type: ignore[no-untyped-call]
            assert next(results).frame_id == 1
            process.send_signal(signal.SIGTERM)
            wait_until(lambda: "shutting down" in log.read_text(), "the shutdown to begin")
            url = f"http://127.0.0.1:{http_port}/readyz"
            wait_until(lambda: not _ready(url, process), "HTTP to stop accepting")  # the stream still open
            release.set()
            last = next(results)
            assert last.frame_id == 2 and last.HasField("pose")
            assert list(results) == []
        assert process.wait(timeout=30) == 0
        assert "stopped" in log.read_text()
    finally:
        if process.poll() is None:
            process.kill()


def _ready(url: str, process: subprocess.Popen[bytes]) -> bool:
    """/readyz answers 200; False while it refuses connections or answers 503."""
    if process.poll() is not None:
        raise AssertionError(f"the service exited with {process.returncode}")
    try:
        return httpx.get(url, timeout=1).status_code == 200
    except httpx.TransportError:
        return False


def test_shutdown_reports_not_serving_and_finishes_in_flight_requests(gated: GatedLifter) -> None:
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, shutdown_grace_s=10)
    service = build_service(settings, gated)
    gated.entered.clear()  # the temporal models' start-up check ran the model: wait for the request's run
    exit_status: list[int] = []
    runner = threading.Thread(target=lambda: exit_status.append(service.run()))
    runner.start()
    wait_until(lambda: service.http.started, "the HTTP server")
    port = service.http.servers[0].sockets[0].getsockname()[1]
    gated.gate.clear()
    answers: list[int] = []
    request = threading.Thread(
        target=lambda: answers.append(
            httpx.post(
                f"http://127.0.0.1:{port}/lift", json={"keypoints": POSE_2D.tolist()}, timeout=30
            ).status_code
        )
    )
    request.start()
    wait_until(gated.entered.is_set, "the request to reach the model")

    service.begin_shutdown()
    assert not service.grpc_server.health.serving and not service.engine.ready
    with grpc.insecure_channel(f"127.0.0.1:{service.grpc_server.port}") as channel:
        stub = lifter_pb2_grpc.PoseLifterStub(channel)  # type: ignore[no-untyped-call]
        with pytest.raises(grpc.RpcError):
            stub.Lift(lifter_pb2.LiftRequest(poses=[to_proto_pose(good())]), timeout=5)  # no new calls
    gated.gate.set()
    request.join(30)
    runner.join(30)
    assert answers == [200] and exit_status == [0]


def test_health_flips_on_the_wire_during_the_shutdown_delay(lifter: Lifter) -> None:
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, shutdown_delay_s=30, shutdown_grace_s=5)
    service = build_service(settings, lifter)
    runner = threading.Thread(target=service.run)
    runner.start()
    try:
        wait_until(lambda: service.http.started, "the HTTP server")
        url = f"http://127.0.0.1:{service.http.servers[0].sockets[0].getsockname()[1]}/readyz"
        with grpc.insecure_channel(f"127.0.0.1:{service.grpc_server.port}") as channel:
            check = channel.unary_unary(
                "/grpc.health.v1.Health/Check",
                request_serializer=health_pb2.HealthCheckRequest.SerializeToString,
                response_deserializer=health_pb2.HealthCheckResponse.FromString,
            )
            assert httpx.get(url).status_code == 200
            assert (
                check(health_pb2.HealthCheckRequest(), timeout=5).status
                == health_pb2.HealthCheckResponse.SERVING
            )
            service.begin_shutdown()
            assert httpx.get(url).status_code == 503  # still accepting, reporting not ready
            status = check(health_pb2.HealthCheckRequest(), timeout=5).status
            assert status == health_pb2.HealthCheckResponse.NOT_SERVING
    finally:
        service.stop_accepting()  # end the delay early
        runner.join(30)


def test_help_renders_every_flag_with_its_description(capsys: pytest.CaptureFixture[str]) -> None:
    """`python -m repnet serve --help` once printed argparse's internal dict: a description held a bare %."""
    with pytest.raises(SystemExit) as exited:
        main(["--help"])
    assert exited.value.code == 0
    out = capsys.readouterr().out
    text = " ".join(out.split())
    assert "'prog':" not in text and "%%" not in text
    # argparse wraps to the terminal's width and may break a line after a hyphen ("single-" / "frame"), so
    # the descriptions are compared with all white space removed
    bare = "".join(out.split())
    for name, info in Settings.model_fields.items():
        assert f"--{name.replace('_', '-')}" in text
        assert "".join((info.description or name).split()) in bare
