"""The batch queue's fair share: self-clocked fair queuing between sources, small chunks riding along or
running ahead of large ones, and each source's share of the queue."""

from __future__ import annotations

from concurrent.futures import Future
from typing import Any

import pytest

from repnet.core.errors import Overloaded
from repnet.runtime.batcher import Batcher
from repnet.runtime.fair_queue import Chunk, FairQueue


class Rows(list[int]):
    def slice(self, start: int, stop: int) -> Rows:
        return Rows(self[start:stop])


def chunk(source: str, rows: int = 1, cost: float | None = None) -> Chunk[Any, Any]:
    return Chunk(Rows(range(rows)), "test", 0.0, Future(), source, float(rows if cost is None else cost))


def drain(queue: FairQueue) -> list[Any]:
    order = []
    while queue:
        order.append(queue.pop().source)
    return order


def test_a_source_that_sends_little_leaves_before_a_flood_queued_earlier() -> None:
    queue = FairQueue()
    for _ in range(8):
        queue.push(chunk("flood", 64))
    first = queue.pop()  # a run of the flood is under way
    assert first.source == "flood"
    queue.push(chunk("camera"))
    assert drain(queue) == ["camera"] + ["flood"] * 7


def test_equal_sources_take_turns_and_a_heavier_chunk_waits_longer() -> None:
    queue = FairQueue()
    for _ in range(3):
        queue.push(chunk("a", 10))
        queue.push(chunk("b", 10))
    assert drain(queue) == ["a", "b", "a", "b", "a", "b"]
    for _ in range(2):
        queue.push(chunk("big", 40))  # finish tags 70 and 110 (the virtual time is 30)
    for _ in range(4):
        queue.push(chunk("small", 10))  # 40, 50, 60, 70
    assert drain(queue) == ["small", "small", "small", "big", "small", "big"]


def test_a_stream_sending_one_chunk_at_a_time_is_charged_for_what_it_used() -> None:
    queue = FairQueue()
    for _ in range(3):  # each of its chunks comes once the one before has been taken for a run
        queue.push(chunk("stream", 64))
        assert queue.pop().source == "stream"
    queue.push(chunk("stream", 64))
    queue.push(chunk("camera"))  # comes later, goes first: its one row finishes before the stream's 64
    assert drain(queue) == ["camera", "stream"]


def test_an_idle_source_earns_no_credit_and_is_forgotten_once_its_debt_is_paid() -> None:
    queue = FairQueue()
    queue.push(chunk("a", 10))
    assert drain(queue) == ["a"]
    assert queue.sources == {}  # idle and paid: nothing kept for it
    for _ in range(5):
        queue.push(chunk("b", 10))  # finish tags 20, 30, ..., 60
    assert [queue.pop().source for _ in range(3)] == ["b", "b", "b"]  # the virtual time is 40
    late = chunk("a", 10)
    queue.push(late)
    assert late.tag == 50  # it starts from the time now (40), not from its finish long ago (10)
    assert drain(queue) == ["b", "a", "b"]  # a tie at 50 goes to the chunk queued first
    for name in range(1000):  # many sources, each gone once served
        queue.push(chunk(str(name)))
    drain(queue)
    assert queue.sources == {} and not queue


def test_small_chunks_ride_along_in_tag_order_within_their_budget() -> None:
    queue = FairQueue()
    for _ in range(4):
        queue.push(chunk("flood", 64))  # 64, 128, 192, 256
    assert queue.pop().source == "flood"  # a run of the flood under way: the virtual time is 64
    queue.push(chunk("other", 64))  # 128
    for name in range(20):
        queue.push(chunk(f"camera{name}", 1))  # 65 each
    riders = queue.take_small(max_cost=4, budget=16)
    assert [c.source for c in riders] == [f"camera{n}" for n in range(16)]  # the budget: 16 of 20
    assert all(queue.queued_by(c.source) == 0 for c in riders)
    assert queue.take_small(max_cost=0.5, budget=16) == []  # nothing that small
    assert drain(queue) == [f"camera{n}" for n in range(16, 20)] + ["flood", "other", "flood", "flood"]


def test_a_run_led_by_a_small_chunk_takes_no_large_one() -> None:
    queue = FairQueue()
    for _ in range(4):
        queue.push(chunk("flood", 64))  # 64, 128, 192, 256
    assert queue.pop().source == "flood"  # a run of the flood under way: the virtual time is 64
    queue.push(chunk("camera"))  # 65: next, and three of the flood's chunks would fit beside it
    assert [c.source for c in queue.take_run(256)] == ["camera"]  # a short run, not one of 193 rows
    assert [c.source for c in queue.take_run(256)] == ["flood"] * 3


def test_small_chunks_run_ahead_of_a_large_one_that_leads_but_only_once_in_a_row() -> None:
    queue = FairQueue()
    for _ in range(2):
        queue.push(chunk("a", 64))  # 64, 128
        queue.push(chunk("b", 64))  # 64, 128
    assert queue.pop().source == "a"  # a's run under way: the virtual time is 64, b's first is due
    queue.push(chunk("camera1"))  # 65: after b's 64, it would wait for b's run
    assert [c.source for c in queue.take_run(256)] == ["camera1"]  # it runs first, alone
    queue.push(chunk("camera2"))  # 66: b's chunk has been put off once, so it leads now
    assert [c.source for c in queue.take_run(256)] == ["b", "camera2", "a", "b"]
    assert not queue


def test_removed_chunks_leave_the_order_of_the_rest_unchanged() -> None:
    queue = FairQueue()
    chunks = [chunk(s, 5) for s in "abcab"]
    for c in chunks:
        queue.push(c)
    taken = queue.remove({id(chunks[1].future), id(chunks[3].future)})
    assert sorted(c.source for c in taken) == ["a", "b"]
    assert queue.queued_by("a") == 5 and queue.queued_by("b") == 5
    assert drain(queue) == ["a", "c", "b"]  # tags 0, 0 and 5: b's first chunk went


class Echo(Batcher[Rows, Rows]):
    def _run(self, parts: list[Rows]) -> Rows:
        return Rows(x for p in parts for x in p)

    def _join(self, parts: list[Rows]) -> Rows:
        return Rows(x for p in parts for x in p)


def test_one_source_holds_at_most_its_share_of_the_queue_and_others_still_fit() -> None:
    batcher = Echo(None, max_batch=4, max_wait_s=0.0, queue_size=32, name="echo")
    with batcher._cond:  # hold the worker off: nothing runs while the queue fills
        assert batcher.source_share == 8  # a quarter of the queue, at least one run
        batcher._enqueue(batcher._chunks(Rows(range(8)), "test", "flood"), 8, "flood")
        with pytest.raises(Overloaded, match="this client's share of the batch queue is full"):
            batcher._enqueue(batcher._chunks(Rows(range(1)), "test", "flood"), 1, "flood")
        batcher._enqueue(batcher._chunks(Rows(range(8)), "test", "other"), 8, "other")
        big = batcher._chunks(Rows(range(16)), "test", "alone")  # one request larger than a share
        futures = batcher._enqueue(big, 16, "alone")
    assert batcher.join([f.result(timeout=10) for f in futures]) == list(range(16))
    batcher.close(10)
