"""Large POST /lift bodies (issue 30): decoded and validated off the event loop, and handled one at a
time per worker, with the same answers and errors as FastAPI's own path; a large request that finds
no room is refused at once, before its body is read, while small requests go on."""

from __future__ import annotations

import asyncio
import gc
import json
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from hypothesis import given
from hypothesis import settings as examples
from hypothesis import strategies as st

import repnet.server.http.body as body_module
from repnet.core.errors import Overloaded
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import Lifter
from repnet.server.config import Settings
from repnet.server.http.body import OFF_LOOP_BYTES, CollectorPause, LargeBodies, decode_json
from tests.conftest import POSE_2D, GatedLifter, live_settings
from tests.hardening.conftest import running

JSON = {"content-type": "application/json"}


@pytest.fixture
def settings() -> Settings:
    """The `client` fixture's settings, with room for large bodies."""
    return Settings(host="localhost", grpc_port=0, max_request_poses=256, max_body_bytes=4 * 1024 * 1024)


@pytest.fixture
def engine(engine_factory: Callable[..., LiftBatcher], lifter: Lifter) -> LiftBatcher:
    return engine_factory(lifter, queue_size=1024)


def large_body(poses: int = 200, **request: Any) -> dict[str, Any]:
    """A body of `poses` poses, over OFF_LOOP_BYTES."""
    pose = {"keypoints": (POSE_2D + 0.123456789).tolist()}
    body = {"poses": [dict(pose) for _ in range(poses)], **request}
    assert len(json.dumps(body)) > OFF_LOOP_BYTES
    return body


def both_paths(
    client: TestClient, content: bytes, headers: dict[str, str], monkeypatch: Any
) -> tuple[Any, Any]:
    """(status, body) of `content` off the loop, then on FastAPI's own path (the threshold raised)."""
    off = client.post("/lift", content=content, headers=headers)
    with monkeypatch.context() as patch:
        patch.setattr(body_module, "OFF_LOOP_BYTES", 1 << 30)
        on = client.post("/lift", content=content, headers=headers)
    return (off.status_code, off.json()), (on.status_code, on.json())


@pytest.mark.parametrize("encoding", ["utf-8", "utf-16"])  # json.loads reads both
def test_a_large_body_gets_the_answer_of_fastapis_path(
    client: TestClient, monkeypatch: Any, encoding: str
) -> None:
    content = json.dumps(large_body()).encode(encoding)
    off, on = both_paths(client, content, JSON, monkeypatch)
    assert off[0] == 200 and off == on


def dump(body: Any) -> bytes:
    return json.dumps(body).encode()


BROKEN = {
    "unknown field in the last pose": lambda b: b["poses"][-1].update(elbow=1) or json.dumps(b).encode(),
    "a row of one number": lambda b: b["poses"][150]["keypoints"].__setitem__(3, [1]) or dump(b),
    "NaN coordinates": lambda b: b["poses"][9]["keypoints"].__setitem__(0, [float("nan"), 1]) or dump(b),
    "an unknown temporal mode": lambda b: b.update(temporal="sideways") or json.dumps(b).encode(),
    "JSON cut short": lambda b: json.dumps(b).encode()[:-40],
    "not UTF-8": lambda b: json.dumps(b).encode()[:-10] + b"\xff\xfe" + json.dumps(b).encode()[-10:],
    "nested too deeply": lambda b: b"[" * 100_000 + b"]" * 100_000,
    "a number of 5,000 digits": lambda b: json.dumps(b).encode()[:-2] + b', "fps": ' + b"1" * 5000 + b"}",
    "a detector's raw output": lambda b: json.dumps([{"frame_id": 0, "instances": b["poses"]}]).encode(),
}  # fmt: skip


@pytest.mark.parametrize("how", sorted(BROKEN))
def test_a_broken_large_body_gets_the_refusal_of_fastapis_path(
    client: TestClient, monkeypatch: Any, how: str
) -> None:
    content = BROKEN[how](large_body())
    assert len(content) > OFF_LOOP_BYTES
    off, on = both_paths(client, content, JSON, monkeypatch)
    assert 400 <= off[0] < 500 and off == on, (off, on)


def test_a_large_body_that_is_not_json_is_named_as_such(client: TestClient) -> None:
    reply = client.post(
        "/lift", content=json.dumps(large_body()).encode(), headers={"content-type": "text/plain"}
    )
    assert reply.status_code == 422 and "content-type" in reply.json()["detail"][0]["reason"]


JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.floats(), st.integers(-(2**70), 2**70), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=6), st.dictionaries(st.text(max_size=4), inner,
                                                                          max_size=4)),
    max_leaves=40,
)  # fmt: skip


@given(value=JSON_VALUES, indent=st.sampled_from([None, 1]))
@examples(max_examples=200, deadline=None, database=None)
def test_decode_json_reads_what_json_loads_reads(value: Any, indent: int | None) -> None:
    text = json.dumps(value, indent=indent).encode()
    assert repr(decode_json(text)) == repr(json.loads(text))  # repr: NaN equals NaN


def test_one_large_request_runs_two_wait_and_the_next_is_refused_at_once() -> None:
    async def scenario() -> list[str]:
        gate, seen = LargeBodies(waiting=2), []
        release = asyncio.Event()

        async def request(name: str) -> None:
            try:
                async with gate:
                    seen.append(f"{name} in")
                    await release.wait()
            except Overloaded as err:
                seen.append(f"{name} refused: {err}")

        tasks = [asyncio.create_task(request(n)) for n in "abc"]
        await asyncio.sleep(0.01)
        assert gate.full()
        await request("d")  # finds one running and two waiting
        release.set()
        await asyncio.gather(*tasks)
        assert not gate.full()
        return seen

    seen = asyncio.run(scenario())
    assert seen[:2] == [
        "a in",
        "d refused: too many large requests in progress (one at a time, 2 waiting); retry later",
    ]
    assert seen[2:] == ["b in", "c in"]


@pytest.fixture
def slow_service(lifter: Lifter) -> Iterator[tuple[str, GatedLifter]]:
    gated = GatedLifter(lifter)
    with running(live_settings(), gated) as service:
        port = service.http.servers[0].sockets[0].getsockname()[1]
        try:
            yield f"http://127.0.0.1:{port}", gated
        finally:
            gated.gate.set()


def test_a_large_request_without_room_is_refused_before_its_body_while_small_ones_are_answered(
    slow_service: tuple[str, GatedLifter],
) -> None:
    url, gated = slow_service
    content = json.dumps(large_body()).encode()
    gated.gate.clear()  # the first large request holds the model
    replies: list[httpx.Response] = []

    def send() -> None:
        replies.append(httpx.post(url + "/lift", content=content, headers=JSON, timeout=60))

    first = threading.Thread(target=send)
    first.start()
    assert gated.entered.wait(10)
    waiting = [threading.Thread(target=send) for _ in range(2)]
    for thread in waiting:
        thread.start()
    time.sleep(2)  # both bodies (70 KB each) sent and waiting for the gate
    refused = httpx.post(url + "/lift", content=content, headers=JSON, timeout=10)
    assert refused.status_code == 503, refused.text
    assert refused.headers["retry-after"] == "1" and "too many large requests" in refused.json()["detail"]
    gated.gate.set()  # the small request and the held ones are answered
    small = httpx.post(url + "/lift", json={"keypoints": POSE_2D.tolist()}, timeout=30)
    assert small.status_code == 200
    for thread in [first, *waiting]:
        thread.join(60)
    assert [r.status_code for r in replies] == [200, 200, 200]


def test_a_large_body_is_handled_with_the_collector_paused_and_it_runs_again_after(
    client: TestClient, monkeypatch: Any
) -> None:
    """The collector's full collections walked a large body's objects again and again (7 a request,
    10-47 ms each with the GIL held): it is paused from the body's decode to its answer, refusals
    included, and runs again after."""
    during: list[bool] = []

    class Watched(body_module._Parsed):
        def __init__(self, model: Any, content: bytes) -> None:
            during.append(gc.isenabled())
            super().__init__(model, content)

    monkeypatch.setattr(body_module, "_Parsed", Watched)
    answered = client.post("/lift", content=dump(large_body()), headers=JSON)
    refused = client.post("/lift", content=BROKEN["NaN coordinates"](large_body()), headers=JSON)
    broken = client.post("/lift", content=BROKEN["JSON cut short"](large_body()), headers=JSON)
    assert [answered.status_code, refused.status_code, broken.status_code] == [200, 422, 422]
    assert during == [False, False, False]
    assert gc.isenabled()


def test_collector_pauses_nest_across_threads_and_leave_it_as_they_found_it() -> None:
    pause, entered, leave = CollectorPause(), threading.Event(), threading.Event()

    def other() -> None:
        with pause:
            entered.set()
            leave.wait(5)

    thread = threading.Thread(target=other)
    with pause:
        assert not gc.isenabled()
        thread.start()
        assert entered.wait(5)
    assert not gc.isenabled()  # the other thread's pause still holds it
    leave.set()
    thread.join(5)
    assert gc.isenabled()
    gc.disable()  # off before the first pause: off after the last
    try:
        with pause:
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
