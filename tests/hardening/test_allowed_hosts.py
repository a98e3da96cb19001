"""The Host allow-list (issue 30: DNS rebinding): a service bound to a loopback address answers the
names a browser on this machine sends and refuses any other Host before any route runs;
REPNET_ALLOWED_HOSTS sets the names, `*` turns the check off, and a network bind has none by default."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from repnet.runtime.lifter import Lifter
from repnet.server.config import LOOPBACK_NAMES, Settings, trusted_hosts
from tests.conftest import LiveService, live_settings, running_service


@pytest.fixture(scope="module")
def loopback(lifter: Lifter) -> Iterator[LiveService]:
    with running_service(live_settings(), lifter) as live:
        yield live


def status(url: str, host: str, path: str = "/healthz") -> int:
    return httpx.get(f"{url}{path}", headers={"host": host}, timeout=10).status_code


def test_a_loopback_bind_answers_the_local_names_with_their_ports(loopback: LiveService) -> None:
    port = loopback.http_url.rsplit(":", 1)[1]
    for host in ("localhost", f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}", "LOCALHOST"):
        assert status(loopback.http_url, host) == 200, host


def test_a_rebound_name_is_refused_on_every_route(loopback: LiveService) -> None:
    for path in ("/healthz", "/v1/model", "/", "/metrics"):
        reply = httpx.get(f"{loopback.http_url}{path}", headers={"host": "attacker.example:8000"}, timeout=10)
        assert reply.status_code == 400 and "host" in reply.text.lower(), path
    lift = httpx.post(f"{loopback.http_url}/lift", json={"poses": []}, headers={"host": "evil"}, timeout=10)
    assert lift.status_code == 400  # refused before the body is read or validated
    assert status(loopback.http_url, "localhost.attacker.example") == 400


def test_the_setting_names_the_hosts_or_turns_the_check_off(lifter: Lifter) -> None:
    with running_service(live_settings(allowed_hosts="repnet.internal, *.example.org"), lifter) as live:
        assert status(live.http_url, "repnet.internal:443") == 200
        assert status(live.http_url, "a.example.org") == 200
        assert status(live.http_url, "localhost") == 400  # the list given replaces the default
    with running_service(live_settings(allowed_hosts="*"), lifter) as live:
        assert status(live.http_url, "anything.example") == 200


def test_the_default_follows_the_bind_address() -> None:
    assert trusted_hosts(Settings(host="127.0.0.1")) == list(LOOPBACK_NAMES)
    assert trusted_hosts(Settings(host="::1")) == list(LOOPBACK_NAMES)
    assert trusted_hosts(Settings(host="localhost")) == list(LOOPBACK_NAMES)
    assert trusted_hosts(Settings(host="0.0.0.0")) is None  # the container: any, unless set
    assert trusted_hosts(Settings(host="0.0.0.0", allowed_hosts="a.example")) == ["a.example"]
