"""Engine: the dynamic batcher that coalesces ModelInputs from every transport into shared Lifter runs."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from service.errors import ModelNotReady, Overloaded
from service.keypoints import ModelInput
from service.lifter import Lifter, Prediction
from service.metrics import Metrics


@dataclass
class _Chunk:
    """At most max_batch poses of one request, waiting for a run."""

    keypoints_2d: np.ndarray  # (n, J, 2)
    visible: np.ndarray  # (n, J)
    transport: str
    enqueued: float  # time.monotonic() when queued
    future: Future[Prediction]

    def __len__(self) -> int:
        return int(self.keypoints_2d.shape[0])


T = TypeVar("T")

# Adapters prepare and answer requests of at most this many poses on their event loop (offload):
# cheaper than the hop to a worker thread and back (docs/BENCHMARKS.md).
INLINE_POSES = 8


async def offload(count: int, work: Callable[..., T], *args: Any) -> T:
    """work(*args), the CPU work of a request of `count` poses (input rules, reply building): on the
    caller's event loop up to INLINE_POSES poses, else on a worker thread, so that the loop keeps
    serving the other requests meanwhile."""
    if count <= INLINE_POSES:
        return work(*args)
    return await asyncio.get_running_loop().run_in_executor(None, work, *args)


def _wake(room: asyncio.Future[None]) -> None:
    if not room.done():  # a waiter that timed out cancelled its future
        room.set_result(None)


class Engine:
    """One worker thread runs one Lifter on batches of queued ModelInputs; adapters get Predictions.

    An idle batcher runs a request at once; under load (work queued during the last run) a batch
    starts when max_batch poses are queued or max_wait_s after the last run ended. Requests larger
    than max_batch are split into chunks. The queue holds at most queue_size poses: a request that
    does not fit is refused at once with Overloaded. The engine knows no reply and no wire format.

    An Engine batches for one model: a service with several models would hold one Engine per model
    (app.py builds them, adapters pick one by the request's model), each batching its own runs.
    """

    def __init__(
        self, lifter: Lifter, metrics: Metrics | None, *, max_batch: int, max_wait_s: float, queue_size: int
    ) -> None:
        if max_batch < 1 or queue_size < 1 or max_wait_s < 0:
            raise ValueError("max_batch and queue_size must be >= 1 and max_wait_s >= 0")
        self.lifter = lifter
        self.metrics = metrics
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.queue_size = queue_size
        self._queue: deque[_Chunk] = deque()
        # Coroutines in submit_async waiting for room, woken on their own loops.
        self._room_waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        self._queued = 0  # poses in _queue
        self._closed = False
        self._serving = True  # False once shutdown begins: readiness off, queued work still done
        self._cond = threading.Condition()
        self._worker = threading.Thread(target=self._run, name="repnet-batcher", daemon=True)
        self._worker.start()

    @property
    def ready(self) -> bool:
        """The model is loaded and the server is not shutting down (readiness, gRPC health)."""
        return self._serving and not self._closed

    def stop_serving(self) -> None:
        """Report not ready from now on; requests already arriving are still served."""
        self._serving = False

    def submit(self, inputs: ModelInput, transport: str, wait_s: float = 0.0) -> list[Future[Prediction]]:
        """Queue `inputs` (all or nothing); one future per chunk of at most max_batch poses.

        A full queue raises Overloaded at once, or after waiting up to `wait_s` for room (streams
        wait: their own window already bounds what they hold, so a busy moment slows them down
        instead of failing their frames).
        """
        chunks = self._chunks(inputs, transport)
        with self._cond:
            deadline = time.monotonic() + wait_s
            while self._must_wait(len(inputs)):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            return self._enqueue(chunks, len(inputs))

    async def submit_async(
        self, inputs: ModelInput, transport: str, wait_s: float = 0.0
    ) -> list[Future[Prediction]]:
        """Engine.submit for coroutines: waiting for room suspends the caller, not its event loop."""
        loop = asyncio.get_running_loop()
        chunks = self._chunks(inputs, transport)
        deadline = time.monotonic() + wait_s
        while True:
            with self._cond:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._must_wait(len(inputs)):
                    return self._enqueue(chunks, len(inputs))
                room: asyncio.Future[None] = loop.create_future()
                self._room_waiters.append((loop, room))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(room, remaining)

    async def lift_async(self, inputs: ModelInput, transport: str) -> Prediction:
        """Queue `inputs` (Overloaded at once when the queue is full) and await their Prediction in
        input order, for adapters on an event loop. When the caller is cancelled (a gRPC call
        cancelled or past its deadline), every chunk of it still queued is dropped."""
        futures = self.submit(inputs, transport)
        try:
            return Prediction.join([await asyncio.wrap_future(f) for f in futures])
        except asyncio.CancelledError:
            self.drop(futures)
            raise

    def drop(self, futures: list[Future[Prediction]]) -> int:
        """Take the chunks of `futures` that are still queued out of the queue and cancel them (a
        chunk in a run already finishes); the number of poses dropped."""
        wanted = {id(f) for f in futures}
        with self._cond:
            dropped = [c for c in self._queue if id(c.future) in wanted]
            if not dropped:
                return 0
            self._queue = deque(c for c in self._queue if id(c.future) not in wanted)
            poses = sum(len(c) for c in dropped)
            self._queued -= poses
            self._set_depth()
            self._room_freed()
        for chunk in dropped:
            chunk.future.cancel()
        return poses

    def _chunks(self, inputs: ModelInput, transport: str) -> list[_Chunk]:
        return [
            _Chunk(
                inputs.keypoints_2d[a : a + self.max_batch],
                inputs.visible[a : a + self.max_batch],
                transport,
                0.0,
                Future(),
            )
            for a in range(0, len(inputs), self.max_batch)
        ]

    def _must_wait(self, n: int) -> bool:
        """n poses do not fit now but would once the queue drains (call with _cond held)."""
        return self._queued + n > self.queue_size and n <= self.queue_size and not self._closed

    def _enqueue(self, chunks: list[_Chunk], n: int) -> list[Future[Prediction]]:
        """Queue the chunks of n poses, or raise why not (call with _cond held)."""
        if self._closed:
            raise ModelNotReady("the server is shutting down and accepts no new requests")
        if self._queued + n > self.queue_size:
            raise Overloaded(
                f"the batch queue is full ({self._queued} of {self.queue_size} poses waiting, "
                f"{n} more requested); retry later"
            )
        now = time.monotonic()
        for chunk in chunks:
            chunk.enqueued = now
            self._queue.append(chunk)
        self._queued += n
        self._set_depth()
        self._cond.notify_all()
        return [c.future for c in chunks]

    def _room_freed(self) -> None:
        """Wake whoever waits for room in the queue, threads and coroutines (call with _cond held)."""
        self._cond.notify_all()
        for loop, room in self._room_waiters:
            with contextlib.suppress(RuntimeError):  # that loop has closed: nobody waits any more
                loop.call_soon_threadsafe(_wake, room)
        self._room_waiters.clear()

    def lift(self, inputs: ModelInput, transport: str) -> Prediction:
        """Queue `inputs`, wait for their runs and return their Prediction in input order."""
        futures = self.submit(inputs, transport)
        return Prediction.join([f.result() for f in futures])

    def close(self, timeout: float | None = None) -> bool:
        """Refuse new work, finish everything queued, stop the worker; False if it timed out."""
        with self._cond:
            self._closed = True
            self._room_freed()  # waiting submitters learn that the server is shutting down
        self._worker.join(timeout)
        return not self._worker.is_alive()

    def _set_depth(self) -> None:
        if self.metrics is not None:
            self.metrics.queue_depth.set(self._queued)

    def _take_batch(self) -> list[_Chunk]:
        """Block until a batch is due, then take it from the queue; [] once closed and empty.

        An idle batcher runs the first request at once: waiting could only add latency to a lone
        request. Work that queued up while the last run ran means load: then the batch gets up to
        max_wait_s to fill, so that runs stay large when poses arrive faster than single runs end.
        """
        with self._cond:
            idle = not self._queue
            while not self._queue:
                if self._closed:
                    return []
                self._cond.wait()
            if not idle:
                deadline = time.monotonic() + self.max_wait_s
                while self._queued < self.max_batch and not self._closed:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    self._cond.wait(remaining)
            batch = [self._queue.popleft()]
            total = len(batch[0])
            while self._queue and total + len(self._queue[0]) <= self.max_batch:
                total += len(self._queue[0])
                batch.append(self._queue.popleft())
            self._queued -= total
            self._set_depth()
            self._room_freed()
        return batch

    def _run(self) -> None:
        while batch := self._take_batch():
            batch = [c for c in batch if c.future.set_running_or_notify_cancel()]
            if batch:
                self._run_batch(batch)

    def _run_batch(self, batch: list[_Chunk]) -> None:
        start = time.monotonic()
        if self.metrics is not None:
            for chunk in batch:
                self.metrics.queue_wait_seconds.labels(transport=chunk.transport).observe(
                    start - chunk.enqueued
                )
        try:
            keypoints = np.concatenate([c.keypoints_2d for c in batch])  # (B, J, 2)
            visible = np.concatenate([c.visible for c in batch])  # (B, J)
            prediction = self.lifter.lift(keypoints, visible)
        except Exception as err:  # handed to every caller of the batch; each adapter logs it once
            for chunk in batch:
                chunk.future.set_exception(err)
            return
        if self.metrics is not None:
            self.metrics.inference_seconds.observe(time.monotonic() - start)
            self.metrics.batch_size.observe(len(prediction))
            if prediction.plausibility is not None and not prediction.failed.any():
                self.metrics.observe_plausibility(prediction.plausibility)
        offset = 0
        for chunk in batch:  # rows the model failed on are marked in the Prediction (failed)
            stop = offset + len(chunk)
            chunk.future.set_result(prediction.slice(offset, stop))
            offset = stop
