"""Fixtures of the hardening tests: the real service as a `python -m repnet serve` child process."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from bench.server import ServiceProcess
from repnet.runtime.lifter import Lifter
from repnet.server.app import Service, build_service
from repnet.server.config import Settings

# Small limits keep generated and overload requests cheap on a 2-core CI machine.
SMALL_LIMITS = ("--max-request-poses", "16", "--queue-size", "64", "--intra-op-threads", "1")


@pytest.fixture(scope="module")
def service_process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceProcess]:
    """The service with the bundled model; it must exit 0 on SIGTERM at the end of the module."""
    log = tmp_path_factory.mktemp("service") / "service.log"
    service = ServiceProcess(*SMALL_LIMITS, log=log).start()
    try:
        yield service
        status = service.terminate()
        assert status == 0, f"exit status {status}; log:\n{log.read_text()[-4000:]}"
    finally:
        service.kill()


@contextmanager
def running(settings: Settings, lifter: Lifter) -> Iterator[Service]:
    """Both servers of build_service(settings, lifter) in this process (a lifter that tests can
    slow down or break), on a thread until the block ends; then shut down."""
    service = build_service(settings, lifter)
    thread = threading.Thread(target=service.run, name="hardening-service", daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not service.http.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the service did not start"
        time.sleep(0.02)
    try:
        yield service
    finally:
        service.begin_shutdown()
        thread.join(timeout=15)


def http_url(service: Service) -> str:
    return f"http://127.0.0.1:{service.http.servers[0].sockets[0].getsockname()[1]}"
