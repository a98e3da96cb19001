"""Point 5 of the reliability issue: small HTTP protocol gaps, each answered as documented.

On main: HEAD on /, /healthz and /readyz got 405; API replies had no X-Content-Type-Options;
/lift/ was redirected to an absolute URL built from the request's Host header; a client that wrote
a whole over-limit body before reading saw a reset instead of its 413; a 5,000-digit number was
called "invalid UTF-8 or nested too deeply".
"""

from __future__ import annotations

import json
import socket

import httpx

from bench.server import ServiceProcess
from tests.conftest import POSE_2D

BODY_LIMIT = 4 * 1024 * 1024  # the default REPNET_MAX_BODY_BYTES of the module's service


def test_head_on_the_page_and_probes_is_200_without_a_body(service_process: ServiceProcess) -> None:
    for path in ("/", "/healthz", "/readyz"):
        response = httpx.head(service_process.url + path, timeout=10)
        assert response.status_code == 200 and response.content == b"", (path, response.status_code)


def test_api_replies_say_nosniff(service_process: ServiceProcess) -> None:
    body = {"poses": [{"keypoints": POSE_2D.tolist()}]}
    replies = [
        httpx.post(service_process.url + "/lift", json=body, timeout=30),
        httpx.post(service_process.url + "/lift", json={"poses": []}, timeout=30),
        httpx.get(service_process.url + "/v1/model", timeout=30),
        httpx.get(service_process.url + "/readyz", timeout=30),
        httpx.get(service_process.url + "/nowhere", timeout=30),
    ]
    for response in replies:
        assert response.headers.get("x-content-type-options") == "nosniff", response.request.url


def test_a_trailing_slash_is_not_redirected_to_the_requests_host(service_process: ServiceProcess) -> None:
    response = httpx.post(
        service_process.url + "/lift/", json={}, headers={"host": "evil.example"}, timeout=10
    )
    assert not 300 <= response.status_code < 400 or not response.headers["location"].startswith("http")
    assert "evil.example" not in response.headers.get("location", "")


def test_an_over_limit_body_written_whole_before_reading_gets_its_413(
    service_process: ServiceProcess,
) -> None:
    body = b"[" + b"0," * (BODY_LIMIT // 2 + 4096) + b"0]"
    head = (
        b"POST /lift HTTP/1.1\r\nhost: 127.0.0.1\r\ncontent-type: application/json\r\n"
        b"content-length: %d\r\n\r\n" % len(body)
    )
    with socket.create_connection(("127.0.0.1", service_process.http_port), timeout=30) as sock:
        sock.sendall(head + body)  # the whole body, before reading anything
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    status, _, rest = answer.partition(b"\r\n")
    assert status == b"HTTP/1.1 413 Request Entity Too Large", answer[:200]
    detail = json.loads(rest.partition(b"\r\n\r\n")[2])
    assert detail["detail"][0]["code"] == "body_too_large"


def test_a_number_of_thousands_of_digits_gets_a_message_about_numbers(
    service_process: ServiceProcess,
) -> None:
    rows = [[1, 2]] * 16
    text = json.dumps({"poses": [{"keypoints": rows}]}).replace("1", "1" * 5000, 1)
    response = httpx.post(
        service_process.url + "/lift",
        content=text,
        headers={"content-type": "application/json"},
        timeout=30,
    )
    assert response.status_code == 400
    reason = response.json()["detail"][0]["reason"]
    assert "number" in reason and "digits" in reason and "UTF-8" not in reason, reason
