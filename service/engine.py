"""Engine: the dynamic batcher that coalesces poses from every transport into shared session runs."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, fields
from typing import Any, TypeVar

import numpy as np

from service import geometry
from service.errors import ModelNotReady, ModelOutputError, Overloaded
from service.keypoints import ModelInput
from service.lifter import Lifter, Prediction
from service.lookalike import format_warnings
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


Rows = TypeVar("Rows", Prediction, ModelInput)
Reply = TypeVar("Reply")

# Requests of at most this many poses are converted on the caller's event loop by lift_async:
# cheaper than the hop to a worker thread and back.
INLINE_POSES = 8
# The Prediction arrays a reply carries per pose, in reply order.
RESULT_ARRAYS = (
    "pose_3d",
    "pose_3d_camera",
    "camera",
    "scale",
    "rotation",
    "reprojection",
    "reprojection_error_px",
)


def concat_rows(parts: Sequence[Rows]) -> Rows:
    """Join Predictions (or ModelInputs) of consecutive pose ranges into one, in order."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    joined = {f.name: [getattr(p, f.name) for p in parts] for f in fields(first)}
    columns: dict[str, Any] = {k: None if v[0] is None else np.concatenate(v) for k, v in joined.items()}
    return type(first)(**columns)  # None: an optional output the model does not have


def result_columns(inputs: ModelInput, prediction: Prediction, flat: bool = False) -> dict[str, list[Any]]:
    """Every reply field for all poses as Python values, one list item per pose (a few ndarray.tolist
    calls for the whole batch instead of several per pose; tolist on float32 gives the same floats as
    converting to float64 first). `flat`: each pose's matrices as one flat list, as proto carries them."""
    n = len(prediction)
    columns: dict[str, list[Any]] = {}
    for name in RESULT_ARRAYS:
        values = getattr(prediction, name)
        columns[name] = (values.reshape(n, -1) if flat and values.ndim > 1 else values).tolist()
    given = np.flatnonzero(~np.isnan(inputs.intrinsics[:, 0]))
    if len(given):  # turned along the ray to the person: the camera-frame orientation
        k = inputs.intrinsics[given]
        ray = geometry.ray_rotation(inputs.keypoints_2d[given], inputs.visible[given], k[:, :2], k[:, 2:])
        turned = geometry.rotate_to_camera(prediction.pose_3d[given], ray @ prediction.rotation[given])
        rows = (turned.reshape(len(given), -1) if flat else turned).tolist()
        for i, pose in zip(given.tolist(), rows, strict=True):
            columns["pose_3d_camera"][i] = pose
    for name in ("visible", "imputed", "derived"):
        columns[name] = getattr(inputs, name).tolist()
    # None per pose when the model has no plausibility output: null over HTTP, unset in proto.
    plausibility = prediction.plausibility
    columns["plausibility"] = [None] * n if plausibility is None else plausibility.tolist()
    columns["warnings"] = format_warnings(inputs, prediction)
    return columns


def _wake(room: asyncio.Future[None]) -> None:
    if not room.done():  # a waiter that timed out cancelled its future
        room.set_result(None)


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

    async def lift_async(
        self,
        count: int,
        prepare: Callable[[], ModelInput],
        reply: Callable[[ModelInput, Prediction], Reply],
        transport: str,
        started: float | None = None,
    ) -> Reply:
        """prepare() the `count` poses of a request, queue them, await their runs and build the
        reply, for adapters on an event loop. Up to INLINE_POSES poses are converted on the loop;
        larger requests on a worker thread, so that the loop keeps serving the others. The parse
        histogram gets the time from `started` (time.perf_counter(), default now) to prepared inputs."""
        loop = asyncio.get_running_loop()
        started = time.perf_counter() if started is None else started
        inline = count <= INLINE_POSES
        try:
            inputs = prepare() if inline else await loop.run_in_executor(None, prepare)
        finally:
            if self.metrics is not None:
                self.metrics.parse_seconds.labels(transport=transport).observe(time.perf_counter() - started)
        prediction = concat_rows([await asyncio.wrap_future(f) for f in self.submit(inputs, transport)])
        return (
            reply(inputs, prediction)
            if inline
            else await loop.run_in_executor(None, reply, inputs, prediction)
        )

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
        return concat_rows([f.result() for f in futures])

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
        failed = np.zeros(0, dtype=np.int64)  # rows of the batch the model failed on
        try:
            keypoints = np.concatenate([c.keypoints_2d for c in batch])  # (B, J, 2)
            visible = np.concatenate([c.visible for c in batch])  # (B, J)
            try:
                prediction = self.lifter.lift(keypoints, visible)
            except ModelOutputError as err:
                if self.metrics is not None:
                    self.metrics.model_output_errors.inc(len(err.rows))
                if not isinstance(err.partial, Prediction):
                    raise
                prediction, failed = err.partial, np.array(err.rows, dtype=np.int64)
        except Exception as err:  # handed to every caller of the batch; each adapter logs it once
            for chunk in batch:
                chunk.future.set_exception(err)
            return
        if self.metrics is not None:
            self.metrics.inference_seconds.observe(time.monotonic() - start)
            self.metrics.batch_size.observe(len(prediction))
            if prediction.plausibility is not None and not len(failed):
                self.metrics.observe_plausibility(prediction.plausibility)
        offset = 0
        for chunk in batch:
            stop = offset + len(chunk)
            mine = failed[(failed >= offset) & (failed < stop)]
            if len(mine):  # the requests the failed poses belong to fail; the others are answered
                chunk.future.set_exception(
                    ModelOutputError((mine - offset).tolist(), prediction.slice(offset, stop))
                )
            else:
                chunk.future.set_result(prediction.slice(offset, stop))
            offset = stop
