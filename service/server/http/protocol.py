"""HTTP connections under uvicorn: header and body timers, a header size cap, a cap on open connections
that closes the idle longest first, and a lingering close after an answer sent before the body."""

from __future__ import annotations

import asyncio
import json
import logging
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol

log = logging.getLogger(__name__)

# After an answer sent before its request's body was read (413, 408, 431), the connection keeps
# reading and dropping what the client still sends for at most this long before it closes: a client
# that writes its whole body before it reads gets the answer instead of a reset (nginx's
# lingering_time). The write side is shut at once, so a client that reads sees the answer end.
LINGER_S = 5.0


@dataclass(frozen=True)
class ConnectionLimits:
    """What one connection may take: the timers, the header size, and how many may be open."""

    header_timeout_s: float  # from open (or a later request's first byte) to the end of its headers
    max_header_bytes: int  # request line and headers
    body_timeout_s: float  # for a body to arrive, plus 1 s per body_min_rate bytes received
    body_min_rate: int  # bytes per second
    max_connections: int


class Connections:
    """The open connections of one server (on its event loop), the idle ones in the order they
    became idle: a connection is idle from its opening or its last answer until its next request's
    headers are complete (a connection that sent half a header line is idle)."""

    def __init__(self, limits: ConnectionLimits) -> None:
        self.limits = limits
        self.open = 0
        self._idle: OrderedDict[GuardedHttpProtocol, None] = OrderedDict()

    def admit(self) -> bool:
        """Count a new connection: True, after closing the connection idle longest when the cap is
        reached; False (not counted) when every open connection is serving a request."""
        if self.open >= self.limits.max_connections:
            if not self._idle:
                return False
            oldest, _ = self._idle.popitem(last=False)
            oldest.evict()
        self.open += 1
        return True

    def set_idle(self, connection: GuardedHttpProtocol) -> None:
        """`connection` waits for a request: the newest idle one."""
        self._idle.pop(connection, None)
        self._idle[connection] = None

    def set_busy(self, connection: GuardedHttpProtocol) -> None:
        """`connection` serves a request (or is closing): not to be closed for room."""
        self._idle.pop(connection, None)

    def release(self) -> None:
        """A counted connection closed (or is closing)."""
        self.open -= 1


class _CycleTransport(asyncio.Transport):
    """What uvicorn's request cycle writes to: the connection's transport, with a close that lingers
    when the request's body has not all arrived (an answer sent before the body was read)."""

    def __init__(self, protocol: GuardedHttpProtocol) -> None:
        super().__init__()
        self._protocol = protocol

    def write(self, data: bytes | bytearray | memoryview) -> None:
        """Send `data`."""
        self._protocol.transport.write(data)

    def is_closing(self) -> bool:
        """The connection is closing."""
        return self._protocol.transport.is_closing()

    def close(self) -> None:
        """Close once the answer is out, lingering while the client may still be sending its body."""
        self._protocol.close_after_answer()

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        """The connection's transport's extra info."""
        return self._protocol.transport.get_extra_info(name, default)


class GuardedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the timers and caps uvicorn lacks: its keep-alive timer
    starts only after a first answer, so a connection that never completes a request stays open
    forever, holding a file descriptor (and, with a huge header line, memory). guarded_protocol()
    makes the subclass that knows its server's Connections."""

    guard: Connections  # uvicorn's own `connections` is the server's set of protocols

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._limits = self.guard.limits
        self._timer: asyncio.TimerHandle | None = None
        self._counted = False
        self._in_headers = True  # waiting for a request's line and headers to end
        self._header_bytes = 0
        self._body_done = True
        self._body_bytes = 0
        self._body_started = 0.0
        self._lingering = False

    # Connection events
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """Count the connection (making room by closing the idle longest) and start its header timer."""
        super().connection_made(transport)  # type: ignore[arg-type]
        if not self.guard.admit():
            self._answer_and_close(503, "too many connections; retry later", (b"retry-after", b"1"))
            return
        self._counted = True
        self.guard.set_idle(self)
        self._arm(self._limits.header_timeout_s, self._header_timed_out)

    def connection_lost(self, exc: Exception | None) -> None:
        """Stop the timers and uncount the connection."""
        self._cancel_timer()
        self._release()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        """Parse `data` (dropped while lingering); a header block past the cap is answered 431."""
        if self._lingering:
            return
        super().data_received(data)
        if self._in_headers and not self._lingering and not self.transport.is_closing():
            self._header_bytes += len(data)
            if self._header_bytes > self._limits.max_header_bytes:
                reason = f"the request line and headers are larger than {self._limits.max_header_bytes} bytes"
                self._answer_and_close(431, reason)

    # Parser callbacks
    def on_message_begin(self) -> None:
        """A request's first byte: a later request on a kept-alive connection gets the header timer."""
        super().on_message_begin()
        if not self._in_headers:
            self._in_headers = True
            self._header_bytes = 0
            self._arm(self._limits.header_timeout_s, self._header_timed_out)

    def on_headers_complete(self) -> None:
        """Headers done: the connection is busy and its body timer starts."""
        self._in_headers = False
        self._header_bytes = 0
        self._body_done = False
        self._body_bytes = 0
        self._body_started = self.loop.time()
        self.guard.set_busy(self)
        self._arm(self._limits.body_timeout_s, self._check_body)
        super().on_headers_complete()
        if self.cycle is not None:
            self.cycle.transport = _CycleTransport(self)

    def on_body(self, body: bytes) -> None:
        """Count the body's bytes for its minimum rate."""
        self._body_bytes += len(body)
        super().on_body(body)

    def on_message_complete(self) -> None:
        """The whole body arrived; a connection whose answer is already sent is idle again."""
        self._body_done = True
        self._cancel_timer()
        super().on_message_complete()
        if self.cycle is not None and self.cycle.response_complete and not self.pipeline:
            self.guard.set_idle(self)

    def on_response_complete(self) -> None:
        """An answer is sent: once its body has arrived too, the connection is idle."""
        super().on_response_complete()
        if self._body_done and not self.pipeline and not self.transport.is_closing():
            self.guard.set_idle(self)

    def send_400_response(self, msg: str) -> None:
        """A request the parser rejects (e.g. both Content-Length and Transfer-Encoding): 400 as JSON
        with the headers of every reply, then close with a linger."""
        self._answer_and_close(400, msg)

    # Closing
    def evict(self) -> None:
        """Close this idle connection to make room for a new one."""
        self._release()
        self._cancel_timer()
        self.transport.close()

    def close_after_answer(self) -> None:
        """Close once the answer is written; linger while the request's body is still arriving."""
        if self._body_done or self.transport.is_closing():
            self.transport.close()
        else:
            self._linger()

    def _answer_and_close(self, status: int, detail: str, *extra: tuple[bytes, bytes]) -> None:
        """Answer `status` with a JSON detail straight on the connection (the app has not answered
        and will not: its request sees a disconnect), then close with a linger."""
        if self.cycle is not None and not self.cycle.response_complete:
            if self.cycle.response_started:  # half an answer is out: nothing valid can follow
                self.cycle.disconnected = True
                self.transport.close()
                return
            self.cycle.disconnected = True
            self.cycle.message_event.set()
        body = json.dumps({"detail": detail}).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
            (b"x-content-type-options", b"nosniff"),
            *extra,
        ]
        self.transport.write(STATUS_LINE[status] + b"".join(n + b": " + v + b"\r\n" for n, v in headers))
        self.transport.write(b"\r\n" + body)
        self._linger()

    def _linger(self) -> None:
        self._lingering = True
        self.guard.set_busy(self)
        self.flow.resume_reading()
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self._arm(LINGER_S, self.transport.close)

    def _release(self) -> None:
        self.guard.set_busy(self)
        if self._counted:
            self._counted = False
            self.guard.release()

    # Timers
    def _arm(self, delay: float, callback: Callable[[], None]) -> None:
        self._cancel_timer()
        self._timer = self.loop.call_later(delay, callback)

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _header_timed_out(self) -> None:
        """No complete request line and headers in time: 408 when part of a request came, else close."""
        self._timer = None
        if not self._in_headers or self.transport.is_closing():
            return
        if self._header_bytes:
            self._answer_and_close(408, "the request line and headers took too long to arrive")
        else:
            self._release()
            self.transport.close()

    def _check_body(self) -> None:
        """The body's deadline: body_timeout_s, plus 1 s per body_min_rate bytes received; 408 past it."""
        self._timer = None
        if self._body_done or self.transport.is_closing():
            return
        now = self.loop.time()
        if self.flow.read_paused:  # the server is not reading (the app has not asked yet): not the client
            self._body_started, self._body_bytes = now, 0
            self._arm(self._limits.body_timeout_s, self._check_body)
            return
        allowed = self._limits.body_timeout_s + self._body_bytes / self._limits.body_min_rate
        left = self._body_started + allowed - now
        if left > 0:
            self._arm(left, self._check_body)
        elif self.cycle is not None and self.cycle.response_complete:
            self.transport.close()  # answered already: the rest of the body is not needed
        else:
            limits = self._limits
            reason = (
                f"the request body arrived too slowly (it has {limits.body_timeout_s:g} s, plus 1 s per "
                f"{limits.body_min_rate} bytes received)"
            )
            self._answer_and_close(408, reason)


def guarded_protocol(limits: ConnectionLimits) -> type[GuardedHttpProtocol]:
    """The protocol class of one server: its connections share one Connections under `limits`."""
    return type("HttpProtocol", (GuardedHttpProtocol,), {"guard": Connections(limits)})
