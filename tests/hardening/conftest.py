"""Fixtures of the hardening tests: the real service as a `python -m service` child process."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from bench.server import ServiceProcess

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
