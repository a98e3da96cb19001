"""ASGI middleware of the HTTP API: API keys, the body size limit, load shedding, request metrics, headers."""

from __future__ import annotations

import json
import time
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from repnet.core.errors import SPLIT_HINT, Violation
from repnet.server.auth import UNAUTHENTICATED_MESSAGE, ApiKeys
from repnet.server.http.body import OFF_LOOP_BYTES, LargeBodies
from repnet.server.metrics import (
    CANCELLED,
    ERROR,
    INVALID,
    OK,
    OVERLOADED,
    UNAUTHENTICATED,
    UNAVAILABLE,
    Metrics,
)

# Key in the ASGI scope's state where exception handlers leave the outcome of a request.
OUTCOME_KEY = "repnet_outcome"
# Key in the ASGI scope's state: time.perf_counter() when a POST /lift arrived (the parse histogram).
STARTED_KEY = "repnet_started"
LIFT_PATH = "/lift"
NOSNIFF = (b"x-content-type-options", b"nosniff")


class _BodyTooLarge(Exception):
    pass


def body_violation(size: int, limit: int) -> Violation:
    """The violation of a body of at least `size` bytes over the `limit`."""
    reason = f"the request body has {size} bytes or more, the limit is {limit}; {SPLIT_HINT}"
    return Violation("body", reason, "body_too_large")


class BodyLimitMiddleware:
    """Answer 413 once a request body passes max_bytes, by its Content-Length or while streaming."""

    def __init__(self, app: ASGIApp, max_bytes: int, metrics: Metrics) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Pass the request on, or answer 413 once its body passes max_bytes."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if declared is not None and declared > self.max_bytes:
            await self._reject(scope, send, declared)
            return
        received = 0
        exceeded = False

        async def limited_receive() -> Message:
            nonlocal received, exceeded
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    exceeded = True
                    raise _BodyTooLarge
            return message

        async def guarded_send(message: Message) -> None:
            if not exceeded:  # the app's answer to a truncated body is replaced by the 413
                await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except _BodyTooLarge:
            pass
        if exceeded:
            await self._reject(scope, send, received)

    async def _reject(self, scope: Scope, send: Send, size: int) -> None:
        violation = body_violation(size, self.max_bytes)
        self.metrics.reject("http", [violation])
        scope.setdefault("state", {})[OUTCOME_KEY] = INVALID
        item = {
            "field": violation.field,
            "reason": violation.reason,
            "message": violation.message,
            "code": violation.code,
            "pose": None,
            "joint": None,
            "joint_name": None,
        }
        await send_json(send, 413, {"detail": [item], "error_count": 1}, (b"connection", b"close"))


async def send_json(send: Send, status: int, payload: Any, *extra: tuple[bytes, bytes]) -> None:
    """A whole JSON response straight on the ASGI channel, for replies made before the app runs."""
    body = json.dumps(payload).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()), *extra]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


def _is_lift(scope: Scope) -> bool:
    return bool(scope["type"] == "http" and scope["path"] == LIFT_PATH and scope["method"] == "POST")


class LoadShedMiddleware:
    """While max_in_flight POST /lift requests are in progress, answer the next with 503 and
    Retry-After at once. The batch queue's limit counts poses, so it would let 1024 one-pose
    requests in (p99 8 s), and it is reached only after each body is parsed; this bound keeps the
    event loop's own queue short, so that health, readiness and metrics, which pass untouched,
    answer in milliseconds under any load.

    A request takes its slot only once its whole body has arrived: a client that sends headers and
    then trickles its body (or nothing) holds no slot, so a few hundred of them cannot refuse
    everyone else (the connection layer, service/http_protocol.py, answers them 408). When the
    slots are already all taken as a request arrives, it is refused before its body is read."""

    def __init__(self, app: ASGIApp, max_in_flight: int, large: LargeBodies | None = None) -> None:
        self.app = app
        self.max_in_flight = max_in_flight
        self.in_flight = 0  # on the server's one event loop: no lock
        self.large = large  # a large body that would find no room is refused before it is read

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Read a POST /lift's body, then pass it on while fewer than max_in_flight are in
        progress, else answer 503 at once."""
        if not _is_lift(scope):
            await self.app(scope, receive, send)
            return
        if self.in_flight >= self.max_in_flight:
            await self._refuse(scope, send)
            return
        if self.large is not None and self.large.full() and (_content_length(scope) or 0) > OFF_LOOP_BYTES:
            scope.setdefault("state", {})[OUTCOME_KEY] = OVERLOADED
            await send_json(send, 503, {"detail": self.large.refusal}, (b"retry-after", b"1"))
            return
        body = await _read_body(receive)
        if body is None:  # the client went away (or the connection layer timed it out)
            scope.setdefault("state", {})[OUTCOME_KEY] = CANCELLED
            return
        if self.in_flight >= self.max_in_flight:
            await self._refuse(scope, send)
            return
        self.in_flight += 1
        try:
            await self.app(scope, _replay(body, receive), send)
        finally:
            self.in_flight -= 1

    async def _refuse(self, scope: Scope, send: Send) -> None:
        scope.setdefault("state", {})[OUTCOME_KEY] = OVERLOADED
        detail = f"too many requests in progress (limit {self.max_in_flight}); retry later"
        await send_json(send, 503, {"detail": detail}, (b"retry-after", b"1"))


async def _read_body(receive: Receive) -> list[Message] | None:
    """Every http.request message of a body, up to the last; None if the client disconnects first."""
    messages = []
    while True:
        message = await receive()
        if message["type"] != "http.request":
            return None
        messages.append(message)
        if not message.get("more_body", False):
            return messages


def _replay(messages: list[Message], receive: Receive) -> Receive:
    """A receive channel that gives `messages` again, then whatever `receive` gives (a disconnect)."""
    pending = list(messages)

    async def replay() -> Message:
        return pending.pop(0) if pending else await receive()

    return replay


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


class SecurityHeadersMiddleware:
    """`X-Content-Type-Options: nosniff` on every reply that does not set it itself: a browser must
    not guess a reply's type (an error quoting a request's text read as HTML)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Pass the request on; add the header to its reply."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                if not any(name.lower() == NOSNIFF[0] for name, _ in headers):
                    message = {**message, "headers": [*headers, NOSNIFF]}
            await send(message)

        await self.app(scope, receive, send_with_headers)


class ApiKeyMiddleware:
    """POST /lift and /v1/* need `Authorization: Bearer KEY` with a key of `keys`; otherwise 401
    with one message whatever was wrong (missing, malformed or unknown key). Health, readiness,
    metrics, the page and the API docs stay open."""

    def __init__(self, app: ASGIApp, keys: ApiKeys) -> None:
        self.app = app
        self.keys = keys

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Pass the request on, or answer 401."""
        if scope["type"] != "http" or not _needs_key(scope["path"]):
            await self.app(scope, receive, send)
            return
        header = next((v for n, v in scope.get("headers", []) if n == b"authorization"), None)
        if self.keys.accepts_header(None if header is None else header.decode("latin-1")):
            await self.app(scope, receive, send)
            return
        scope.setdefault("state", {})[OUTCOME_KEY] = UNAUTHENTICATED
        await send_json(send, 401, {"detail": UNAUTHENTICATED_MESSAGE}, (b"www-authenticate", b"Bearer"))


def _needs_key(path: str) -> bool:
    return path == LIFT_PATH or path.startswith("/v1/")


def outcome_of_status(status: int, state: dict[str, Any]) -> str:
    """The outcome label of an HTTP answer; exception handlers may have said it precisely."""
    if OUTCOME_KEY in state:
        return str(state[OUTCOME_KEY])
    if status < 400:
        return OK
    if status < 500:
        return INVALID
    return UNAVAILABLE if status == 503 else ERROR


class LiftMetricsMiddleware:
    """Count, time and classify POST /lift requests, rejections before the route included."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Pass POST /lift on, counting and timing it by its outcome."""
        if not _is_lift(scope):
            await self.app(scope, receive, send)
            return
        state: dict[str, Any] = scope.setdefault("state", {})
        status = 500  # if the app fails before answering

        async def recording_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        gauge = self.metrics.in_flight.labels(transport="http")
        gauge.inc()
        start = time.perf_counter()
        state[STARTED_KEY] = start
        try:
            await self.app(scope, receive, recording_send)
        finally:
            gauge.dec()
            outcome = outcome_of_status(status, state)
            self.metrics.finish("http", "Lift", outcome, time.perf_counter() - start)
