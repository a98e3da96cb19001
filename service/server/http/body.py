"""A large POST body parsed, validated and answered one at a time per worker, off the event loop.

FastAPI parses and validates a route's body on the event loop: a 6,000-pose temporal request (1.7 to
3.6 MB of JSON) held the loop for 150 to 300 ms, and 8 clients sending such bodies back to back kept
it busy nearly all the time, so a one-pose request or `/readyz` waited over a second; their
requests' work then ran side by side, each holding its poses, replies and windows at once (+780 MB),
until the batch queue refused most of them after their parsing was paid for (issue 30).

`off_loop_route` makes a route whose body over OFF_LOOP_BYTES (about 100 poses) is decoded and
validated on a worker thread (the thread's validators give up the GIL every few milliseconds; the
one C call that does not, the JSON decode, takes about 20 ms for 3.6 MB), and whose large requests
go one at a time per worker, parse to answer, through a LargeBodies gate. A large request that finds
the gate busy waits (costing no CPU) behind at most `waiting` others; beyond, it is refused at once
with 503 and Retry-After: its body is not even decoded. Small bodies take FastAPI's own path and do
not wait. The answers, errors included, are the same on both paths: the same JSON decoder errors,
and pydantic's errors at FastAPI's `body` location. While a large request is handled, Python's
cyclic collector is paused (CollectorPause): its full collections walked the body's objects again
and again, each a stall of the whole worker.
"""

from __future__ import annotations

import asyncio
import email.message
import gc
import json
import threading
from collections.abc import Callable, Coroutine
from typing import Any

import pydantic_core
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import BaseModel, ValidationError
from starlette.requests import Request
from starlette.responses import Response

from repnet.core.errors import Overloaded
from repnet.runtime.replies import Replies

REPLY_CHUNK = 256  # poses rendered at once
OFF_LOOP_BYTES = 64 * 1024  # about 100 poses of JSON; below, the work costs the loop < 10 ms

Handler = Callable[[Request], Coroutine[Any, Any, Response]]


def decode_json(body: bytes) -> Any:
    """The JSON value of `body`, the same as json.loads gives (and the same errors): pydantic-core's
    decoder, about 2.5x faster and allocating less, where it reads the body; json.loads otherwise
    (it also reads UTF-16 and a BOM, and nests deeper), so every refusal is json.loads's own."""
    try:
        return pydantic_core.from_json(body, allow_inf_nan=True)
    except ValueError:
        return json.loads(body)


def reply_json(content: Any) -> bytes:
    """A reply as JSON, by pydantic-core's serializer: the same values as json.dumps, about ten
    times faster for the float arrays of a batch (a 256-pose reply: 3.6 ms instead of 46 ms). A
    non-finite number, which the model should never produce, is written as null."""
    return pydantic_core.to_json(content, inf_nan_mode="null")


def replies_json(head: dict[str, Any], replies: Replies) -> bytes:
    """`head` with `poses`, the replies, last: the same bytes as reply_json({**head, "poses":
    replies.to_json()}), made REPLY_CHUNK poses at a time, so that the Python lists of only one
    chunk exist at once (all 6,000 poses of a temporal request as lists took about 150 MB)."""
    start = reply_json({**head, "poses": []})  # ...,"poses":[]}
    chunks = [
        reply_json(replies.slice(i, i + REPLY_CHUNK).to_json())[1:-1]
        for i in range(0, len(replies), REPLY_CHUNK)
    ]
    return b"".join((start[:-2], b",".join(chunks), b"]}"))


def is_json(content_type: str | None) -> bool:
    """Whether FastAPI reads a body of this content-type as JSON (application/json or +json)."""
    if not content_type:
        return False
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    json_subtype = subtype == "json" or subtype.endswith("+json")
    return message.get_content_maintype() == "application" and json_subtype


class _Parsed:
    """What the worker thread made of a body: the validated model, or why it is refused."""

    def __init__(self, model: type[BaseModel], body: bytes) -> None:
        self.value: Any = None
        self.decode_error: BaseException | None = None  # json.loads's: FastAPI answers it as it does
        self.errors: list[dict[str, Any]] | None = None  # pydantic's, at FastAPI's body location
        try:
            data = decode_json(body)
        except (ValueError, RecursionError) as err:  # JSONDecodeError and UnicodeDecodeError included
            self.decode_error = err
            return
        try:
            self.value = model.model_validate(data, from_attributes=True)  # as FastAPI's field does
        except ValidationError as err:
            self.value = data
            self.errors = [{**e, "loc": ("body", *e["loc"])} for e in err.errors(include_url=False)]


class _ParsedRequest(Request):
    """A request whose json() is what the worker thread made of the body: FastAPI then validates
    a model instance, which costs nothing."""

    parsed: _Parsed | None = None

    async def json(self) -> Any:
        if self.parsed is None:
            return await super().json()
        if self.parsed.decode_error is not None:
            raise self.parsed.decode_error
        return self.parsed.value


class CollectorPause:
    """Python's cyclic garbage collector held off while large bodies' requests are handled.

    Decoding and validating a 6,000-pose body makes about 200,000 Python containers that live until
    its request is answered. Each time a quarter more containers than the last full collection left
    had come, the collector walked all of them again: 7 full collections a request, 10-47 ms each with
    the GIL held, freeing almost nothing, so every other request and `/readyz` of the worker waited
    (docs/BENCHMARKS.md, "The collector and large bodies"). The requests' own paths make no cyclic
    garbage (tests/service/test_pipeline.py, test_stream.py): what is freed is freed by reference
    counts, paused or not; cycles made meanwhile wait for the first collection after the pause.
    Process-wide, as the collector is: pauses (`with pause:`) nest across threads and event loops, and
    the collector runs again when the last one ends, if it ran when the first began."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held = 0
        self._resume = False

    def __enter__(self) -> None:
        with self._lock:
            if self._held == 0:
                self._resume = gc.isenabled()
                gc.disable()
            self._held += 1

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._held -= 1
            if self._held == 0 and self._resume:
                gc.enable()


COLLECTOR_PAUSE = CollectorPause()  # one per process: the collector is


class LargeBodies:
    """One large request at a time (per worker: one per event loop), `waiting` more queued; beyond,
    Overloaded at once (503). The one that holds the gate holds the collector's pause too
    (COLLECTOR_PAUSE): what it frees before it leaves, reference counts free."""

    def __init__(self, waiting: int) -> None:
        self.waiting = waiting
        self._turn = asyncio.Semaphore(1)
        self._queued = 0

    @property
    def refusal(self) -> str:
        """What a large request that finds no room is told."""
        return f"too many large requests in progress (one at a time, {self.waiting} waiting); retry later"

    def full(self) -> bool:
        """Whether a large request arriving now would be refused (its body need not be read)."""
        return self._turn.locked() and self._queued >= self.waiting

    async def __aenter__(self) -> None:
        if self.full():
            raise Overloaded(self.refusal)
        self._queued += 1
        try:
            await self._turn.acquire()
        finally:
            self._queued -= 1
        COLLECTOR_PAUSE.__enter__()

    async def __aexit__(self, *exc: object) -> None:
        COLLECTOR_PAUSE.__exit__(*exc)
        self._turn.release()


def off_loop_route(model: type[BaseModel], gate: LargeBodies) -> type[APIRoute]:
    """A route class for a route whose body is `model`: a JSON body over OFF_LOOP_BYTES is decoded
    and validated on a worker thread, and the request handled, while it holds `gate` (and with it the
    collector's pause)."""

    class OffLoopBodyRoute(APIRoute):
        def get_route_handler(self) -> Handler:
            handle = super().get_route_handler()

            async def handler(request: Request) -> Response:
                parsed = _ParsedRequest(request.scope, request.receive)
                body = await parsed.body()
                if len(body) <= OFF_LOOP_BYTES or not is_json(request.headers.get("content-type")):
                    return await handle(parsed)
                async with gate:  # and the collector's pause
                    loop = asyncio.get_running_loop()
                    parsed.parsed = await loop.run_in_executor(None, _Parsed, model, body)
                    try:
                        if parsed.parsed.errors is not None:
                            raise RequestValidationError(parsed.parsed.errors, body=parsed.parsed.value)
                        return await handle(parsed)
                    finally:  # the body's objects are freed before the collector runs again
                        parsed.parsed = None

            return handler

    return OffLoopBodyRoute
