"""The dynamic batcher that coalesces the requests of every transport into shared model runs (one
worker thread per model), and where an adapter's CPU work runs (offload). The two kinds of model's
batchers are runtime.batchers'."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Callable, Hashable, Iterable
from concurrent.futures import Future
from typing import Any, Generic, Protocol, TypeVar

from repnet.core.errors import ModelNotReady, Overloaded
from repnet.runtime.fair_queue import Chunk, FairQueue
from repnet.runtime.window import Window


class Rows(Protocol):
    """What a batcher splits and joins: N rows that slice."""

    def __len__(self) -> int: ...

    def slice(self, start: int, stop: int) -> Any:
        """Rows start..stop-1."""


class BatchMetrics(Protocol):
    """What a batcher reports of its queue and runs (the server's Metrics; None reports nothing)."""

    def batch_queued(self, model: str, depth: int) -> None:
        """`depth` poses wait for a run of `model`."""

    def batch_waited(self, model: str, transport: str, seconds: float) -> None:
        """A request's chunk waited `seconds` in the queue before its run."""

    def batch_ran(self, model: str, seconds: float, size: int) -> None:
        """A run of `size` poses took `seconds`."""

    def poses_lifted(self, model: str, transport: str, count: int) -> None:
        """`count` poses of a `transport` request were lifted."""

    def observe_plausibility(self, model: str, values: Iterable[float]) -> None:
        """The plausibility of a run's answers."""


In = TypeVar("In", bound=Rows)  # the input rows of a run
Out = TypeVar("Out", bound=Rows)  # the output rows of a run
T = TypeVar("T")


# Adapters prepare and answer requests of at most this many poses on their event loop (offload):
# cheaper than the hop to a worker thread and back (docs/BENCHMARKS.md).
INLINE_POSES = 8
MAX_BATCH = 256  # most poses (or windows) in one model run by default (REPNET_MAX_BATCH)
SOURCE_SHARE = 0.25  # most of the queue one source may hold (see Batcher.source_share)


async def offload(count: int, work: Callable[..., T], *args: Any) -> T:
    """work(*args), the CPU work of a request of `count` poses (input rules, replies): on the caller's
    event loop up to INLINE_POSES poses, else on a worker thread (the loop serves others meanwhile)."""
    if count <= INLINE_POSES:
        return work(*args)
    return await asyncio.get_running_loop().run_in_executor(None, work, *args)


def settle(waiter: asyncio.Future[None]) -> None:
    """Wake the task that awaits `waiter`, unless it has given up (a waiter that timed out cancelled
    its future) or was woken already."""
    if not waiter.done():
        waiter.set_result(None)


class Batcher(Generic[In, Out]):
    """One worker thread runs one model on batches of queued requests' rows; adapters get its answers.

    A request that finds nothing queued after the last run runs at once, unless another source is
    expected to send within company_wait_s of it (a paced camera's next frame); under load (work
    queued during the last run) a batch starts when max_batch poses are queued or max_wait_s after
    the last run ended (runtime.window.Window). Requests larger than max_batch are split into
    chunks. The queue holds at most queue_size poses: a request that does not fit is refused at once
    with Overloaded. The engine knows no reply and no wire format.

    A batcher runs one model (a service holds one per model; adapters pick one by the request). A
    subclass says how a batch runs (_run) and how answers join (_join).
    """

    def __init__(
        self,
        metrics: BatchMetrics | None,
        *,
        max_batch: int,
        max_wait_s: float,
        queue_size: int,
        name: str,
        company_wait_s: float = 0.0,
    ) -> None:
        if max_batch < 1 or queue_size < 1:
            raise ValueError("max_batch and queue_size must be >= 1")
        self.metrics = metrics
        self.model = name  # the model it runs: its metrics' `model` label, its thread's name
        self.max_batch = max_batch
        self.window = Window(max_wait_s, company_wait_s)  # when a batch is due
        self.queue_size = queue_size
        self._queue = FairQueue()
        # Coroutines in submit_async waiting for room, woken on their own loops.
        self._room_waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        self._closed = False
        self._serving = True  # False once shutdown begins: readiness off, queued work still done
        self._cond = threading.Condition()
        self._worker = threading.Thread(target=self._work, name=f"repnet-{name}", daemon=True)
        self._worker.start()

    @property
    def ready(self) -> bool:
        """The model is loaded and the server is not shutting down (readiness, gRPC health)."""
        return self._serving and not self._closed

    def stop_serving(self) -> None:
        """Report not ready from now on; requests already arriving are still served."""
        self._serving = False

    def _run(self, parts: list[In]) -> Out:
        """One model run on the rows of several requests, in order (the worker thread)."""
        raise NotImplementedError

    def _join(self, parts: list[Out]) -> Out:
        """The answers of consecutive rows as one."""
        raise NotImplementedError

    def _observe(self, answer: Out) -> None:
        """Record what a run's answers say in the metrics (nothing by default)."""

    def submit(
        self, inputs: In, transport: str, wait_s: float = 0.0, source: Hashable = None
    ) -> list[Future[Out]]:
        """Queue `inputs` (all or nothing); one future per chunk of at most max_batch poses.

        `source`: who sent them (a connection; None: this request alone), for the fair share of the
        queue (FairQueue; one source holds at most source_share). A full queue (or share) raises
        Overloaded at once, or after waiting up to `wait_s` for room (streams wait: their window
        bounds what they hold, so a busy moment slows them down instead of failing their frames).
        """
        named, source = source is not None, object() if source is None else source
        chunks = self._chunks(inputs, transport, source)
        with self._cond:
            deadline = time.monotonic() + wait_s
            while self._must_wait(len(inputs), source):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            return self._enqueue(chunks, len(inputs), source, named)

    async def submit_async(
        self, inputs: In, transport: str, wait_s: float = 0.0, source: Hashable = None
    ) -> list[Future[Out]]:
        """Batcher.submit for coroutines: waiting for room suspends the caller, not its event loop."""
        loop = asyncio.get_running_loop()
        named, source = source is not None, object() if source is None else source
        chunks = self._chunks(inputs, transport, source)
        deadline = time.monotonic() + wait_s
        while True:
            with self._cond:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._must_wait(len(inputs), source):
                    return self._enqueue(chunks, len(inputs), source, named)
                room: asyncio.Future[None] = loop.create_future()
                self._room_waiters.append((loop, room))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(room, remaining)

    async def lift_async(
        self, inputs: In, transport: str, wait_s: float = 0.0, source: Hashable = None
    ) -> Out:
        """Queue `inputs` (Overloaded when the queue stays full for wait_s) and await their answers
        in input order, for adapters on an event loop. When the caller is cancelled (a gRPC call
        cancelled or past its deadline), every chunk of it still queued is dropped."""
        futures = await self.submit_async(inputs, transport, wait_s, source)
        try:
            return self._join([await asyncio.wrap_future(f) for f in futures])
        except asyncio.CancelledError:
            self.drop(futures)
            raise

    def drop(self, futures: list[Future[Out]]) -> int:
        """Take the chunks of `futures` that are still queued out of the queue and cancel them (a
        chunk in a run already finishes); the number of rows dropped."""
        wanted = {id(f) for f in futures}
        with self._cond:
            dropped = self._queue.remove(wanted)
            if not dropped:
                return 0
            self._set_depth()
            self._room_freed()
        for chunk in dropped:
            chunk.future.cancel()
        return sum(len(c) for c in dropped)

    def join(self, parts: list[Out]) -> Out:
        """The answers of a request's runs (its futures' results) as one."""
        return self._join(parts)

    def _chunks(self, inputs: In, transport: str, source: Hashable) -> list[Chunk[In, Out]]:
        n, step = len(inputs), self.max_batch
        chunks: list[Chunk[In, Out]] = []
        for a in range(0, n, step):
            part = inputs.slice(a, min(a + step, n))
            chunks.append(Chunk(part, transport, 0.0, Future(), source, self._cost(part)))
        return chunks

    def _cost(self, inputs: In) -> float:
        """What a chunk takes of a run's capacity of max_batch: its rows (a subclass may weigh them)."""
        return float(len(inputs))

    @property
    def source_share(self) -> int:
        """Most poses one source may have queued: SOURCE_SHARE of the queue, at least one run's
        (beyond that, one request of any size when it has nothing else queued)."""
        return max(self.max_batch, int(self.queue_size * SOURCE_SHARE))

    def _over_share(self, n: int, source: Hashable) -> bool:
        held = self._queue.queued_by(source)
        return held > 0 and held + n > self.source_share

    def _must_wait(self, n: int, source: Hashable) -> bool:
        """n poses do not fit now but would once the queue drains (call with _cond held)."""
        full = self._queue.rows + n > self.queue_size or self._over_share(n, source)
        return full and n <= self.queue_size and not self._closed

    def _enqueue(
        self, chunks: list[Chunk[In, Out]], n: int, source: Hashable, named: bool = False
    ) -> list[Future[Out]]:
        """Queue the chunks of n poses, or raise why not (call with _cond held); a `named` source's
        arrival is remembered (a one-off request's is not: it never sends again)."""
        if self._closed:
            raise ModelNotReady("the server is shutting down and accepts no new requests")
        if self._queue.rows + n > self.queue_size:
            raise Overloaded(
                f"the batch queue is full ({self._queue.rows} of {self.queue_size} poses waiting, "
                f"{n} more requested); retry later"
            )
        if self._over_share(n, source):
            raise Overloaded(
                f"this client's share of the batch queue is full ({self._queue.queued_by(source)} of "
                f"{self.source_share} poses waiting, {n} more requested); retry later"
            )
        now = time.monotonic()
        if named:
            self.window.arrived(source, now)
        for chunk in chunks:
            chunk.enqueued = now
            self._queue.push(chunk)
        self._set_depth()
        self._cond.notify_all()
        return [c.future for c in chunks]

    def _room_freed(self) -> None:
        """Wake whoever waits for room in the queue, threads and coroutines (call with _cond held)."""
        self._cond.notify_all()
        for loop, room in self._room_waiters:
            with contextlib.suppress(RuntimeError):  # that loop has closed: nobody waits any more
                loop.call_soon_threadsafe(settle, room)
        self._room_waiters.clear()

    def lift(self, inputs: In, transport: str) -> Out:
        """Queue `inputs`, wait for their runs and return their answers in input order."""
        return self._join([f.result() for f in self.submit(inputs, transport)])

    def close(self, timeout: float | None = None) -> bool:
        """Refuse new work, finish everything queued, stop the worker; False if it timed out."""
        with self._cond:
            self._closed = True
            self._room_freed()  # waiting submitters learn that the server is shutting down
        self._worker.join(timeout)
        return not self._worker.is_alive()

    def _set_depth(self) -> None:
        if self.metrics is not None:
            self.metrics.batch_queued(self.model, self._queue.rows)

    def _take_batch(self) -> list[Chunk[In, Out]]:
        """Block until a batch is due (runtime.window.Window; at once when max_batch of cost waits),
        then take it from the queue (FairQueue.take_run); [] once closed and empty."""
        with self._cond:
            loaded = bool(self._queue)  # work queued while the last run ran: others are sending too
            while not self._queue:
                if self._closed:
                    return []
                self._cond.wait()
            deadline, company = self.window.deadlines(self._queue.first().enqueued, loaded)
            while self._queue.cost < self.max_batch and not self._closed:
                now = time.monotonic()
                until = self.window.due(now, deadline, company, self._queue.queued_by, self._queue.rows)
                if until <= now:
                    break
                self._cond.wait(until - now)
            batch = self._queue.take_run(self.max_batch)
            self._set_depth()
            self._room_freed()
        return batch

    def _work(self) -> None:
        ended = time.monotonic()  # when the last run ended
        while batch := self._take_batch():
            batch = [c for c in batch if c.future.set_running_or_notify_cancel()]
            if batch:
                started = time.monotonic()
                self._run_batch(batch)
                now = time.monotonic()
                self.window.ran(started, now, ended)
                ended = now

    def _run_batch(self, batch: list[Chunk[In, Out]]) -> None:
        start = time.monotonic()
        if self.metrics is not None:
            for chunk in batch:
                self.metrics.batch_waited(self.model, chunk.transport, start - chunk.enqueued)
        try:
            answer = self._run([c.inputs for c in batch])
        except Exception as err:  # handed to every caller of the batch; each adapter logs it once
            for chunk in batch:
                chunk.future.set_exception(err)
            return
        if self.metrics is not None:
            lifted = self._lifted(answer, batch)
            if sum(lifted):  # a run happened
                self.metrics.batch_ran(self.model, time.monotonic() - start, sum(lifted))
            for chunk, count in zip(batch, lifted, strict=True):
                self.metrics.poses_lifted(self.model, chunk.transport, count)
            self._observe(answer)
        for chunk, result in zip(batch, self._results(answer, batch), strict=True):
            if isinstance(result, Exception):  # this chunk's own failure (a job's finish raised)
                chunk.future.set_exception(result)
            else:
                chunk.future.set_result(result)

    def _lifted(self, answer: Out, batch: list[Chunk[In, Out]]) -> list[int]:
        """How many rows of each chunk the run lifted (all of them, unless a subclass knows better)."""
        return [len(c) for c in batch]

    def _results(self, answer: Out, batch: list[Chunk[In, Out]]) -> list[Any]:
        """Each chunk's part of a run's answer (rows the model failed on are marked in it: failed)."""
        found, offset = [], 0
        for chunk in batch:
            found.append(answer.slice(offset, offset + len(chunk)))
            offset += len(chunk)
        return found
