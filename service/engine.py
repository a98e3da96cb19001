"""Engine: the dynamic batcher that coalesces poses from every transport into shared session runs."""

from __future__ import annotations

import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, fields

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


def concat_predictions(parts: list[Prediction]) -> Prediction:
    """Join predictions of consecutive pose ranges back into one."""
    if len(parts) == 1:
        return parts[0]
    return Prediction(
        **{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Prediction)}
    )


class Engine:
    """One worker thread runs the Lifter on batches of queued requests.

    An idle batcher runs a request at once; under load (work queued during the last run) a batch
    starts when max_batch poses are queued or max_wait_s after the last run ended. Requests larger
    than max_batch are split into chunks. The queue holds at most
    queue_size poses: a request that does not fit is refused at once with Overloaded.
    """

    def __init__(
        self,
        lifter: Lifter,
        metrics: Metrics | None = None,
        *,
        max_batch: int = 256,
        max_wait_s: float = 0.0005,
        queue_size: int = 4096,
    ) -> None:
        if max_batch < 1 or queue_size < 1 or max_wait_s < 0:
            raise ValueError("max_batch and queue_size must be >= 1 and max_wait_s >= 0")
        self.lifter = lifter
        self.metrics = metrics
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.queue_size = queue_size
        self._queue: deque[_Chunk] = deque()
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
        n = len(inputs)
        chunks = [
            _Chunk(
                inputs.keypoints_2d[a : a + self.max_batch],
                inputs.visible[a : a + self.max_batch],
                transport,
                0.0,
                Future(),
            )
            for a in range(0, n, self.max_batch)
        ]
        with self._cond:
            deadline = time.monotonic() + wait_s
            while self._queued + n > self.queue_size and n <= self.queue_size and not self._closed:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
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

    def lift(self, inputs: ModelInput, transport: str) -> Prediction:
        """Queue `inputs`, wait for their runs and return their Prediction in input order."""
        futures = self.submit(inputs, transport)
        return concat_predictions([f.result() for f in futures])

    def close(self, timeout: float | None = None) -> bool:
        """Refuse new work, finish everything queued, stop the worker; False if it timed out."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
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
            self._cond.notify_all()  # submitters waiting for room
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
        offset = 0
        for chunk in batch:
            chunk.future.set_result(prediction.slice(offset, offset + len(chunk)))
            offset += len(chunk)
