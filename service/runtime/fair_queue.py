"""The batch queue shared fairly between the sources of requests (self-clocked fair queuing), and the
chunks it holds: the rows of one request a run takes whole."""

from __future__ import annotations

import heapq
import itertools
from collections import deque
from collections.abc import Hashable, Sized
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

In = TypeVar("In", bound=Sized)  # the input rows of a run
PRUNE_EVERY = 256  # chunks taken between two sweeps of the idle sources
# Chunks of at most this share of a run's capacity (a camera's frame, a one-pose request) are small:
# they run ahead of a large chunk, or ride along in a run beyond its capacity, up to RIDE_ALONG_BUDGET
# of it in all (FairQueue.take_run).
RIDE_ALONG_COST = 1 / 16
RIDE_ALONG_BUDGET = 1 / 4
Out = TypeVar("Out")  # the output rows of a run


@dataclass
class Chunk(Generic[In, Out]):
    """At most max_batch rows of one request, waiting for a run."""

    inputs: In
    transport: str
    enqueued: float  # time.monotonic() when queued
    future: Future[Out]
    source: Hashable = None  # who sent it (a connection, an API key): the queue is shared fairly
    cost: float = 0.0  # what it takes of a run's capacity (max_batch): its rows unless said otherwise
    tag: float = 0.0  # its place in the fair queue: the virtual time its service would finish

    def __len__(self) -> int:
        return len(self.inputs)


@dataclass
class _Source:
    """One source's queued chunks, in order, and the virtual time its last one finishes."""

    chunks: deque[Chunk[Any, Any]]
    finish: float = 0.0
    queued: int = 0  # rows


class FairQueue:
    """The batch queue, shared fairly between sources (self-clocked fair queuing by cost).

    A chunk's tag is the virtual time its service would finish: its cost after its source's last
    chunk's finish, or after the virtual time now if that is later. Chunks leave in tag order, and
    the virtual time is the tag of the chunk last taken (Golestani, "A Self-Clocked Fair Queueing
    Scheme for Broadband Applications", INFOCOM 1994). So a source that sends little (a camera's one
    pose a frame, one HTTP request) is served in the next run whatever others have queued: its small
    cost puts it ahead of every large chunk queued; one that sends much waits behind its own work,
    not the others'. Ordering by start times instead (start-time fair queuing) made a light request
    wait one chunk of every busy source: ~8 runs behind 8 flooding streams. A chunk due no earlier
    than a light one may still be in the run under way, so small chunks also ride along in a run
    that large ones fill (take_small), and they run ahead of a large one, in a short run of their
    own, rather than wait for the length of its run (take_run). An idle source earns no credit: it
    starts from the virtual time now. Memory: one entry per source with work queued or a finish
    ahead of the virtual time (the others are dropped as they are served, and swept every
    PRUNE_EVERY chunks).
    """

    def __init__(self) -> None:
        self.sources: dict[Hashable, _Source] = {}
        self._heads: list[tuple[float, int, Hashable]] = []  # each source's first chunk: (tag, seq, source)
        self._seq = itertools.count()
        self._pops = 0
        self.virtual = 0.0
        self.rows = 0  # rows queued, all sources
        self.cost = 0.0  # their cost
        self._put_off = False  # the last run was small chunks run ahead of a large one (take_run)

    def __bool__(self) -> bool:
        return bool(self._heads)

    def queued_by(self, source: Hashable) -> int:
        """Rows `source` has queued."""
        found = self.sources.get(source)
        return found.queued if found is not None else 0

    def push(self, chunk: Chunk[Any, Any]) -> None:
        """Queue a chunk behind its source's others."""
        source = self.sources.get(chunk.source)
        if source is None:
            source = self.sources[chunk.source] = _Source(deque(), self.virtual)
        chunk.tag = max(self.virtual, source.finish) + chunk.cost
        source.finish = chunk.tag
        source.queued += len(chunk)
        source.chunks.append(chunk)
        self._count(chunk, 1)
        if len(source.chunks) == 1:
            heapq.heappush(self._heads, (chunk.tag, next(self._seq), chunk.source))

    def first(self) -> Chunk[Any, Any]:
        """The chunk that leaves next (the queue is not empty)."""
        return self.sources[self._heads[0][2]].chunks[0]

    def pop(self) -> Chunk[Any, Any]:
        """Take the chunk that leaves next; the virtual time moves to its tag."""
        _, _, key = heapq.heappop(self._heads)
        source = self.sources[key]
        chunk = source.chunks.popleft()
        source.queued -= len(chunk)
        self._count(chunk, -1)
        self.virtual = max(self.virtual, chunk.tag)
        if source.chunks:
            heapq.heappush(self._heads, (source.chunks[0].tag, next(self._seq), key))
        elif source.finish <= self.virtual:  # idle, and no debt: it would start from the time now
            del self.sources[key]
        self._pops += 1
        if self._pops % PRUNE_EVERY == 0:
            self._prune()
        return chunk

    def _count(self, chunk: Chunk[Any, Any], sign: int) -> None:
        self.rows += sign * len(chunk)
        self.cost += sign * chunk.cost

    def take_run(self, capacity: float) -> list[Chunk[Any, Any]]:
        """The chunks of the next run (the queue is not empty): the first whatever its cost (a
        request larger than a run), those after it in tag order while their cost fits `capacity`,
        then the small ones that ride along (take_small).

        Small chunks do not wait for the length of a large one's run (a camera's frame behind a
        1,024-pose call's part): a run led by a small chunk takes small ones only, and when a large
        chunk leads while small ones wait, they run first, alone, in a short run of their own. That
        puts a large chunk off by one short run, never two in a row, so a stream of small chunks
        cannot hold it off."""
        small = capacity * RIDE_ALONG_COST
        if self.first().cost > small and not self._put_off:
            alone = self.take_small(small, capacity)
            if alone:
                self._put_off = True
                return alone
        self._put_off = False
        batch = [self.pop()]
        cost = batch[0].cost
        largest = small if cost <= small else capacity
        while self and (head := self.first()).cost <= largest and cost + head.cost <= capacity:
            batch.append(self.pop())
            cost += head.cost
        return batch + self.take_small(small, capacity * RIDE_ALONG_BUDGET)

    def take_small(self, max_cost: float, budget: float) -> list[Chunk[Any, Any]]:
        """Take, in tag order, the sources' first chunks of at most `max_cost` each, `budget` in all:
        the small ones (a camera's frame, a one-pose request) that ride along in a run that large
        chunks fill, or that run ahead of a large one alone (take_run)."""
        taken: list[Chunk[Any, Any]] = []
        for _, _, key in sorted(self._heads):
            chunk = self.sources[key].chunks[0]
            if chunk.cost <= max_cost and chunk.cost <= budget:
                taken.append(chunk)
                budget -= chunk.cost
            if budget < 1:
                break
        if not taken:
            return taken
        for chunk in taken:
            source = self.sources[chunk.source]
            source.chunks.popleft()
            source.queued -= len(chunk)
            self._count(chunk, -1)
            self.virtual = max(self.virtual, chunk.tag)
        self._heads = [(s.chunks[0].tag, next(self._seq), k) for k, s in self.sources.items() if s.chunks]
        heapq.heapify(self._heads)
        self._prune()
        return taken

    def _prune(self) -> None:
        """Forget the idle sources whose debt is paid (their finish is behind the virtual time)."""
        self.sources = {k: s for k, s in self.sources.items() if s.chunks or s.finish > self.virtual}

    def remove(self, wanted: set[int]) -> list[Chunk[Any, Any]]:
        """Take out the chunks whose future's id is in `wanted`; the chunks taken."""
        taken: list[Chunk[Any, Any]] = []
        for source in list(self.sources.values()):
            kept = deque(c for c in source.chunks if id(c.future) not in wanted)
            if len(kept) == len(source.chunks):
                continue
            taken += [c for c in source.chunks if id(c.future) in wanted]
            source.chunks = kept
            source.queued = sum(len(c) for c in kept)
        for chunk in taken:
            self._count(chunk, -1)
        if taken:
            self._prune()
            self._heads = [(s.chunks[0].tag, next(self._seq), k) for k, s in self.sources.items() if s.chunks]
            heapq.heapify(self._heads)
        return taken
