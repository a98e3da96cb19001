"""HTTP sheds load by requests in flight: beyond the limit a /lift is answered 503 with Retry-After
at once, however small (the pose queue alone let 1024 one-pose requests in), while health and
readiness keep answering."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import httpx
import pytest

from repnet.runtime.lifter import Lifter
from repnet.server.app import Service
from repnet.server.config import Settings
from tests.conftest import POSE_2D, GatedLifter
from tests.hardening.conftest import http_url, running

MAX_IN_FLIGHT = 8
BURST = 64  # one-pose requests at once: far below the 4096-pose queue
WAIT_S = 20.0  # how long the test waits for the refusals (they should take milliseconds)


@pytest.fixture
def shedding(lifter: Lifter) -> Iterator[tuple[Service, GatedLifter]]:
    gated = GatedLifter(lifter)
    settings = Settings(host="127.0.0.1", http_port=0, grpc_port=0, intra_op_threads=1, queue_size=4096,
                        http_max_in_flight=MAX_IN_FLIGHT, shutdown_grace_s=5)  # fmt: skip
    try:
        with running(settings, gated) as service:
            yield service, gated
    finally:
        gated.gate.set()


async def probe(url: str, path: str) -> float:
    """Seconds for GET `path` on a fresh connection; it must be 200."""
    start = time.perf_counter()
    async with httpx.AsyncClient(timeout=10) as client:
        assert (await client.get(f"{url}{path}")).status_code == 200
    return time.perf_counter() - start


async def burst(url: str, gated: GatedLifter) -> tuple[list[tuple[int, float, str | None]], list[float]]:
    """BURST requests at once while the model is held: MAX_IN_FLIGHT of them wait for it, the rest
    must be refused; then the model runs. Returns (status, seconds, Retry-After) per request and the
    probe latencies measured while the model was held."""
    body = {"poses": [{"keypoints": POSE_2D.tolist()}]}
    limits = httpx.Limits(max_connections=BURST)
    async with httpx.AsyncClient(base_url=url, limits=limits, timeout=60) as client:

        async def one() -> tuple[int, float, str | None]:
            start = time.perf_counter()
            response = await client.post("/lift", json=body)
            if response.status_code == 200:
                assert len(response.json()["poses"][0]["pose_3d"]) == 17
            return response.status_code, time.perf_counter() - start, response.headers.get("retry-after")

        gated.gate.clear()
        tasks = [asyncio.create_task(one()) for _ in range(BURST)]
        deadline = time.monotonic() + WAIT_S
        probes: list[float] = []
        while sum(t.done() for t in tasks) < BURST - MAX_IN_FLIGHT and time.monotonic() < deadline:
            probes += [await probe(url, "/readyz"), await probe(url, "/healthz")]
            await asyncio.sleep(0.05)
        gated.gate.set()
        return list(await asyncio.gather(*tasks)), probes


def test_requests_beyond_the_in_flight_limit_get_503_at_once(shedding: tuple[Service, GatedLifter]) -> None:
    service, gated = shedding
    url = http_url(service)
    answers, probes = asyncio.run(burst(url, gated))
    statuses = sorted(status for status, _, _ in answers)
    assert statuses.count(503) == BURST - MAX_IN_FLIGHT and statuses.count(200) == MAX_IN_FLIGHT, statuses
    refused = sorted(seconds for status, seconds, _ in answers if status == 503)
    assert refused[len(refused) // 2] < 2.0, refused  # at once, not after the model ran
    assert {retry for status, _, retry in answers if status == 503} == {"1"}
    assert probes and max(probes) < 1.0, probes
    value = service.metrics.registry.get_sample_value
    labels = {"transport": "http", "method": "Lift"}
    assert value("repnet_requests_total", {**labels, "outcome": "overloaded"}) == BURST - MAX_IN_FLIGHT
    assert value("repnet_requests_total", {**labels, "outcome": "ok"}) == MAX_IN_FLIGHT
    # The limit frees up as requests finish: sequential requests are all served.
    for _ in range(3):
        assert httpx.post(f"{url}/lift", json={"keypoints": POSE_2D.tolist()}, timeout=30).status_code == 200
