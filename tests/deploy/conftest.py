"""Fixtures for deploy tests: the real service started as `python -m repnet serve` on free localhost ports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.deploy.helpers import RunningService, free_port

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def running_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningService]:
    """`python -m repnet serve` with the bundled model; stopped with SIGTERM, which must exit 0."""
    http_port, grpc_port = free_port(), free_port()
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "REPNET_HOST": "127.0.0.1", "REPNET_HTTP_PORT": str(http_port),
           "REPNET_GRPC_PORT": str(grpc_port), "REPNET_INTRA_OP_THREADS": "1",
           "PYTHONPATH": path}  # fmt: skip
    log = (tmp_path_factory.mktemp("service") / "service.log").open("wb")
    process = subprocess.Popen([sys.executable, "-m", "repnet", "serve"], cwd=ROOT, env=env, stdout=log,
                               stderr=subprocess.STDOUT)  # fmt: skip
    service = RunningService(f"http://127.0.0.1:{http_port}", f"127.0.0.1:{grpc_port}", process)
    try:
        deadline = time.monotonic() + 60
        while True:
            if process.poll() is not None:
                pytest.fail(f"service exited with {process.returncode}: {Path(log.name).read_text()[-2000:]}")
            try:
                if httpx.get(f"{service.http_url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"service not ready in 60 s: {Path(log.name).read_text()[-2000:]}")
            time.sleep(0.2)
        yield service
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        log.close()
    assert process.returncode == 0, f"exit code {process.returncode} after SIGTERM"
