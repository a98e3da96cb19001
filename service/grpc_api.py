"""gRPC adapter: PoseLifterServicer (Lift, LiftStream), health and reflection; create_server."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator, Sequence
from concurrent import futures
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from service._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from service.engine import Engine, concat_rows, result_columns
from service.errors import (
    MAX_ERROR_ITEMS,
    InvalidKeypoints,
    LiftError,
    ModelNotReady,
    ModelOutputError,
    Overloaded,
    Violation,
    clip,
)
from service.keypoints import DEFAULT_FORMAT, Limits, ModelInput, PoseInput, pose_field, prepare_poses
from service.lifter import Prediction
from service.metrics import OVERLOADED, Metrics, outcome_of

log = logging.getLogger(__name__)

TRANSPORT = "grpc"
# A stream frame that finds the batch queue full waits this long for room before its error result.
STREAM_QUEUE_WAIT_S = 5.0
SERVICE_NAME = lifter_pb2.DESCRIPTOR.services_by_name["PoseLifter"].full_name
# The longest status message: it travels in a header, and one over grpc's metadata limit (8 KiB
# soft, 16 KiB hard, after percent-encoding) reaches the client as RESOURCE_EXHAUSTED instead.
MAX_STATUS_CHARS = 1000
INTERNAL_MESSAGE = "internal error while lifting; this is a server fault"


def status_message(err: Exception) -> str:
    return clip(str(err), MAX_STATUS_CHARS)


def status_of(err: LiftError) -> grpc.StatusCode:
    if isinstance(err, InvalidKeypoints):
        return grpc.StatusCode.INVALID_ARGUMENT
    if isinstance(err, Overloaded):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    if isinstance(err, ModelNotReady):
        return grpc.StatusCode.UNAVAILABLE
    return grpc.StatusCode.INTERNAL


def _structure_violations(pose: lifter_pb2.Pose2D, field: str) -> list[Violation]:
    """Layout rules that JSON expresses by nesting and proto by counts."""
    found = []
    values = len(pose.keypoints)
    if values % 2:
        found.append(
            Violation(
                f"{field}.keypoints",
                f"expected 2 values (x, y) per joint, got {values} values",
                "joint_count",
            )
        )
    if pose.missing and len(pose.missing) != values // 2:
        reason = f"expected no values or one per joint ({values // 2}), got {len(pose.missing)}"
        found.append(Violation(f"{field}.missing", reason, "missing_count"))
    if pose.HasField("intrinsics"):
        found += intrinsics_violations(pose.intrinsics, f"{field}.intrinsics")
    return found


def intrinsics_violations(camera: lifter_pb2.CameraIntrinsics, field: str) -> list[Violation]:
    """fx, fy must be finite and > 0, cx, cy finite."""
    found = []
    for name in ("fx", "fy", "cx", "cy"):
        value = getattr(camera, name)
        if not math.isfinite(value) or (name in ("fx", "fy") and value <= 0):
            rule = "finite and > 0" if name in ("fx", "fy") else "finite"
            found.append(Violation(f"{field}.{name}", f"must be {rule}, got {value}", "intrinsics"))
    return found


def _intrinsics(camera: lifter_pb2.CameraIntrinsics) -> tuple[float, float, float, float]:
    return (camera.fx, camera.fy, camera.cx, camera.cy)


def to_pose_inputs(
    poses: Sequence[lifter_pb2.Pose2D],
    default_format: str,
    prefix: str,
    default_intrinsics: lifter_pb2.CameraIntrinsics | None = None,
) -> list[PoseInput]:
    """Proto poses in their wire-independent form; raises InvalidKeypoints on a bad layout.
    default_intrinsics: those of poses without their own (checked by the caller)."""
    violations: list[Violation] = []
    inputs = []
    for i, pose in enumerate(poses):
        if found := _structure_violations(pose, pose_field(prefix, i)):
            violations.extend(
                Violation(v.field, v.reason, v.code, pose=i if prefix == "poses" else None) for v in found
            )
            continue
        points = np.array(pose.keypoints, dtype=np.float64).reshape(-1, 2)
        present = ~np.array(pose.missing, dtype=bool) if pose.missing else np.ones(len(points), dtype=bool)
        confidence = np.array(pose.confidence, dtype=np.float64) if pose.confidence else None
        camera = pose.intrinsics if pose.HasField("intrinsics") else default_intrinsics
        intrinsics = None if camera is None else _intrinsics(camera)
        inputs.append(PoseInput(points, present, confidence, pose.format or default_format, intrinsics))
    if violations:
        raise InvalidKeypoints(violations)
    return inputs


def pose_results(inputs: ModelInput, prediction: Prediction) -> list[lifter_pb2.PoseResult]:
    columns = result_columns(inputs, prediction, flat=True)
    return [lifter_pb2.PoseResult(**{k: v[i] for k, v in columns.items()}) for i in range(len(prediction))]


def frame_error(err: LiftError) -> lifter_pb2.FrameError:
    violations = err.violations if isinstance(err, InvalidKeypoints) else ()
    return lifter_pb2.FrameError(
        code=status_of(err).value[0],
        message=status_message(err),
        violations=[
            lifter_pb2.FieldViolation(
                field=v.field, reason=v.reason, code=v.code, joint_name=v.joint_name or "", joint=v.joint
            )
            for v in violations[:MAX_ERROR_ITEMS]
        ],
    )


@dataclass
class _Group:
    """Stream frames read together: prepared in one call and queued as one engine request."""

    frames: list[tuple[int, float]]  # (frame_id, perf_counter when read) per frame
    errors: list[LiftError | None]  # per frame: why it gets no pose
    rows: list[int]  # per frame: its row in `inputs`, -1 for a frame with an error
    inputs: ModelInput | None = None  # the frames without an error, in order
    futures: list[futures.Future[Prediction]] = field(default_factory=list)

    def done(self) -> bool:
        return all(f.done() for f in self.futures)


class PoseLifterServicer:
    """Implements repnet.v1.PoseLifter (grpc.aio) on the shared Engine.

    Every call runs on the gRPC server's event loop; only onnxruntime runs elsewhere (the engine's
    worker thread), and a large unary request is converted on a worker thread.

    Lift calls and open streams have limits of their own (the server's maximum_concurrent_rpcs
    would count health checks too, and let idle streams lock everything out); a call beyond its
    limit is refused with RESOURCE_EXHAUSTED and counted. A stream with nothing in progress that
    sends no frame for `stream_idle_timeout_s` is closed with DEADLINE_EXCEEDED.
    """

    def __init__(
        self,
        engine: Engine,
        metrics: Metrics,
        limits: Limits,
        stream_window: int = 256,
        *,
        max_unary: int = 32,
        max_streams: int = 64,
        stream_idle_timeout_s: float = 60.0,
    ) -> None:
        self.engine = engine
        self.metrics = metrics
        self.limits = limits
        self.stream_window = stream_window
        self.max_unary = max_unary
        self.max_streams = max_streams
        self.stream_idle_timeout_s = stream_idle_timeout_s
        self.model_id = engine.lifter.info.model_id
        self.joints = list(engine.lifter.info.joint_names)
        self._unary = 0  # Lift calls in progress; both counters live on the server's one event loop
        self._streams = 0  # LiftStream calls open

    async def _refuse(self, context: grpc.aio.ServicerContext[Any, Any], method: str, message: str) -> None:
        self.metrics.finish(TRANSPORT, method, OVERLOADED, 0.0)
        await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, message)

    async def Lift(
        self, request: lifter_pb2.LiftRequest, context: grpc.aio.ServicerContext[Any, Any]
    ) -> lifter_pb2.LiftResponse:
        if self._unary >= self.max_unary:
            await self._refuse(
                context, "Lift", f"too many Lift calls in progress (limit {self.max_unary}); retry later"
            )
        threshold = request.confidence_threshold if request.HasField("confidence_threshold") else None
        prepare = partial(self._prepare_request, request, threshold)
        self._unary += 1
        try:
            with self.metrics.track(TRANSPORT, "Lift"):
                results = await self.engine.lift_async(len(request.poses), prepare, pose_results, TRANSPORT)
        except LiftError as err:
            if isinstance(err, ModelOutputError):  # counted by the engine; one line, no traceback
                log.error("Lift: %s", err)
            await context.abort(status_of(err), status_message(err))
        except Exception:  # counted as an error by track(); the client gets no exception class
            log.exception("Lift failed")
            await context.abort(grpc.StatusCode.INTERNAL, INTERNAL_MESSAGE)
        finally:
            self._unary -= 1
        return lifter_pb2.LiftResponse(model_id=self.model_id, joints=self.joints, poses=results)

    def _prepare_request(self, request: lifter_pb2.LiftRequest, threshold: float | None) -> ModelInput:
        default = request.intrinsics if request.HasField("intrinsics") else None
        if default is not None and (found := intrinsics_violations(default, "intrinsics")):
            raise InvalidKeypoints(found)
        poses = to_pose_inputs(request.poses, request.format or DEFAULT_FORMAT, "poses", default)
        return prepare_poses(poses, self.limits, threshold)

    async def LiftStream(
        self,
        request_iterator: AsyncIterator[lifter_pb2.LiftFrame],
        context: grpc.aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[lifter_pb2.LiftFrameResult]:
        """A reader task collects frames; this generator takes every frame read so far, prepares them
        in one call, queues them as one request and answers the groups in order as their runs finish.
        Frames are taken only while none of this stream's groups waits for a run, so the frames that
        arrive during a run become the next group: the per-frame cost stays small and one stream
        fills batches instead of waiting for each frame's run. At most stream_window frames are read
        and not yet answered (backpressure: the reader stops reading)."""
        if self._streams >= self.max_streams:
            await self._refuse(
                context, "LiftStream", f"too many open streams (limit {self.max_streams}); retry later"
            )
        loop = asyncio.get_running_loop()
        inbox: list[tuple[lifter_pb2.LiftFrame, float]] = []
        wake = asyncio.Event()  # something may be actionable: frames, a finished run, the end
        room = asyncio.Semaphore(self.stream_window)
        ended = False
        unreadable: Exception | None = None  # why the next frame could not be read

        async def read() -> None:
            nonlocal ended, unreadable
            try:
                async for frame in request_iterator:
                    await room.acquire()
                    inbox.append((frame, time.perf_counter()))
                    wake.set()
            except Exception as err:  # bytes that are not a LiftFrame: answer what came before, then fail
                unreadable = err
            finally:  # the client half-closed, cancelled or the call failed: nothing more to read
                ended = True
                wake.set()

        def on_done(_: object) -> None:  # called on the engine's thread
            with contextlib.suppress(RuntimeError):  # the loop closed: the server has stopped
                loop.call_soon_threadsafe(wake.set)

        gauge = self.metrics.in_flight.labels(transport=TRANSPORT)
        pending: deque[_Group] = deque()
        in_flight = 0  # frames taken from the inbox and not yet answered
        self._streams += 1
        self.metrics.open_streams.inc()
        reader = asyncio.create_task(read())
        try:

            def can_take() -> bool:  # frames wait, and none of this stream's groups waits for a run
                return bool(inbox) and (not pending or pending[-1].done())

            while True:
                wake.clear()
                if can_take():
                    taken = inbox[:]
                    inbox.clear()
                    gauge.inc(len(taken))
                    in_flight += len(taken)
                    for a in range(0, len(taken), self.engine.max_batch):
                        group = await self._submit(taken[a : a + self.engine.max_batch])
                        for future in group.futures:
                            future.add_done_callback(on_done)
                        pending.append(group)
                while pending and pending[0].done():
                    for result in self._answer(pending.popleft()):
                        yield result
                        gauge.dec()
                        in_flight -= 1
                        room.release()
                if ended and not inbox and not pending:
                    if unreadable is not None:
                        reason = f"a frame cannot be decoded as a LiftFrame ({unreadable}); the stream ends"
                        await context.abort(grpc.StatusCode.INVALID_ARGUMENT, reason)
                    return
                if not can_take() and not (pending and pending[0].done()):
                    if in_flight or inbox or ended:
                        await wake.wait()
                    elif not await self._wait_for_frames(wake):
                        self.metrics.idle_streams_closed.inc()
                        reason = (
                            f"no frame for {self.stream_idle_timeout_s:g} s: the stream is closed as idle "
                            "(REPNET_STREAM_IDLE_TIMEOUT_S)"
                        )
                        await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, reason)
        finally:
            reader.cancel()
            self._streams -= 1
            self.metrics.open_streams.dec()
            gauge.dec(in_flight)  # frames queued but never answered (the client went away)

    async def _wait_for_frames(self, wake: asyncio.Event) -> bool:
        """Wait for `wake` on an idle stream; False if stream_idle_timeout_s passed first."""
        try:
            await asyncio.wait_for(wake.wait(), self.stream_idle_timeout_s)
        except asyncio.TimeoutError:
            return False
        return True

    def _prepare(
        self, poses: list[PoseInput], threshold: float | None, frames: list[int], group: _Group
    ) -> list[tuple[list[int], ModelInput]]:
        """Prepare poses of one threshold in one call; when that fails, frame by frame, so each
        frame gets the answer it would get alone."""
        try:
            return [(frames, prepare_poses(poses, self.limits, threshold, prefix="pose"))]
        except InvalidKeypoints:
            if len(poses) == 1:
                raise
        parts = []
        for k, pose in zip(frames, poses, strict=True):
            try:
                parts.append(([k], prepare_poses([pose], self.limits, threshold, prefix="pose")))
            except InvalidKeypoints as err:
                group.errors[k] = err
        return parts

    async def _submit(self, taken: list[tuple[lifter_pb2.LiftFrame, float]]) -> _Group:
        """Check and convert a group of frames, then queue the valid ones as one request."""
        group = _Group([(f.frame_id, t) for f, t in taken], [None] * len(taken), [-1] * len(taken))
        by_threshold: dict[float | None, tuple[list[PoseInput], list[int]]] = {}
        for k, (frame, _) in enumerate(taken):
            threshold = frame.confidence_threshold if frame.HasField("confidence_threshold") else None
            try:
                (pose,) = to_pose_inputs([frame.pose], frame.pose.format or DEFAULT_FORMAT, "pose")
            except InvalidKeypoints as err:
                group.errors[k] = err
                continue
            poses, indices = by_threshold.setdefault(threshold, ([], []))
            poses.append(pose)
            indices.append(k)
        parts: list[tuple[list[int], ModelInput]] = []
        for threshold, (poses, indices) in by_threshold.items():
            try:
                parts.extend(self._prepare(poses, threshold, indices, group))
            except InvalidKeypoints as err:
                group.errors[indices[0]] = err
        if not parts:
            return group
        rows = [k for indices, _ in parts for k in indices]
        inputs = concat_rows([p for _, p in parts])
        try:
            group.futures = await self.engine.submit_async(inputs, TRANSPORT, wait_s=STREAM_QUEUE_WAIT_S)
        except LiftError as err:  # queue full for too long, or shutting down
            for k in rows:
                group.errors[k] = err
            return group
        group.inputs = inputs
        for row, k in enumerate(rows):
            group.rows[k] = row
        return group

    def _results(self, group: _Group, failed_rows: set[int]) -> list[Prediction]:
        """The group's Predictions; rows the model failed on are added to `failed_rows` (their
        stand-in values are never sent), so that only their frames get an error result."""
        parts, offset = [], 0
        for future in group.futures:
            try:
                part = future.result()
            except ModelOutputError as err:  # counted by the engine; one line, no traceback
                if not isinstance(err.partial, Prediction):
                    raise
                log.error("LiftStream: frames %d..: %s", group.frames[0][0], err)
                part = err.partial
                failed_rows.update(offset + r for r in err.rows)
            parts.append(part)
            offset += len(part)
        return parts

    def _answer(self, group: _Group) -> Iterator[lifter_pb2.LiftFrameResult]:
        """The group's results in frame order; a failed run gives its frames an error result."""
        columns: dict[str, list[Any]] = {}
        failure: LiftError | None = None
        failed_rows: set[int] = set()  # rows the model gave non-finite output for
        if group.inputs is not None:
            try:
                prediction = concat_rows(self._results(group, failed_rows))
                columns = result_columns(group.inputs, prediction, flat=True)
            except Exception:  # one run's fault must not end the stream
                log.exception("LiftStream: lifting frames %d.. failed", group.frames[0][0])
                failure = LiftError("internal error while lifting this frame")
        for k, (frame_id, start) in enumerate(group.frames):
            error, row = group.errors[k], group.rows[k]
            if row in failed_rows:
                error = ModelOutputError([row])
            if error is None and row >= 0 and failure is None:
                pose = lifter_pb2.PoseResult(**{name: values[row] for name, values in columns.items()})
                result = lifter_pb2.LiftFrameResult(frame_id=frame_id, model_id=self.model_id, pose=pose)
            else:
                error = error or failure
                assert error is not None
                result = lifter_pb2.LiftFrameResult(
                    frame_id=frame_id, model_id=self.model_id, error=frame_error(error)
                )
                if isinstance(error, InvalidKeypoints):
                    self.metrics.reject(TRANSPORT, error.violations)
            self.metrics.finish(TRANSPORT, "LiftStream", outcome_of(error), time.perf_counter() - start)
            yield result


def _log_failure(done: futures.Future[None]) -> None:
    if not done.cancelled() and (err := done.exception()) is not None:
        log.error("updating the gRPC health status failed: %s", err)


class Health:
    """The standard gRPC health service, set from any thread: SERVING or NOT_SERVING for the whole
    server ("") and for repnet.v1.PoseLifter."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.servicer = health.aio.HealthServicer()
        self.serving = False  # what was reported last

    def _call(self, coroutine: Coroutine[Any, Any, None]) -> None:
        """Schedule `coroutine` on the server's loop without waiting for it: the caller may be a signal
        handler, which must not block on another thread (that thread may wait for a lock the
        interrupted code holds). Calls scheduled later, such as the server's stop, run after it."""
        try:
            done = asyncio.run_coroutine_threadsafe(coroutine, self.loop)
        except RuntimeError:  # the loop has closed: the server has stopped, there is nobody to tell
            coroutine.close()
            return
        done.add_done_callback(_log_failure)

    async def set_status(self, serving: bool) -> None:
        status = (
            health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
        )
        for name in ("", SERVICE_NAME):
            await self.servicer.set(name, status)
        self.serving = serving

    def enter_graceful_shutdown(self) -> None:
        """NOT_SERVING from now on, whatever is set later (what SIGTERM does first)."""
        self._call(self.servicer.enter_graceful_shutdown())
        self.serving = False


class GrpcServer:
    """A grpc.aio server on its own event loop thread, driven from synchronous code.

    Built by create_server (bound, not started); start() serves; stop(grace) stops accepting calls,
    gives the calls in progress `grace` seconds and returns an Event set once it has stopped.
    """

    def __init__(self, build: Callable[[Health], Coroutine[Any, Any, tuple[grpc.aio.Server, int]]]) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="repnet-grpc", daemon=True)
        self._thread.start()
        self.health = Health(self.loop)
        self._stopped: threading.Event | None = None
        try:
            self.server, self.port = asyncio.run_coroutine_threadsafe(build(self.health), self.loop).result()
        except BaseException:
            self._close_loop()
            raise

    def start(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.start(), self.loop).result()

    def stop(self, grace: float | None) -> threading.Event:
        if self._stopped is None:
            self._stopped = threading.Event()
            stopping = asyncio.run_coroutine_threadsafe(self.server.stop(grace), self.loop)
            threading.Thread(
                target=self._finish, args=(stopping,), name="repnet-grpc-stop", daemon=True
            ).start()
        return self._stopped

    def _finish(self, stopping: futures.Future[None]) -> None:
        try:
            stopping.result()
        except Exception:
            log.exception("the gRPC server did not stop cleanly")
        finally:
            self._close_loop()
            if self._stopped is not None:
                self._stopped.set()

    def _close_loop(self) -> None:
        """Stop the event loop thread and close the loop (from any thread but the loop's own)."""
        if not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(timeout=10)
            if not self.loop.is_running():
                self.loop.close()


def create_server(
    engine: Engine,
    metrics: Metrics,
    limits: Limits,
    address: str,
    *,
    workers: int = 32,
    max_streams: int = 64,
    stream_idle_timeout_s: float = 60.0,
    max_message_bytes: int = 4 << 20,
    stream_window: int = 256,
) -> GrpcServer:
    """A gRPC server (not started) bound to `address`, with health (`.health`) and reflection.

    At most `workers` Lift calls and `max_streams` open streams at once; calls beyond get
    RESOURCE_EXHAUSTED. Health and reflection have no limit: a health check always answers.
    """

    async def build(status: Health) -> tuple[grpc.aio.Server, int]:
        server = grpc.aio.server(
            # so_reuseport 0: a second server on a taken port fails instead of sharing it.
            options=[("grpc.max_receive_message_length", max_message_bytes), ("grpc.so_reuseport", 0)],
        )
        servicer = PoseLifterServicer(
            engine,
            metrics,
            limits,
            stream_window,
            max_unary=workers,
            max_streams=max_streams,
            stream_idle_timeout_s=stream_idle_timeout_s,
        )
        lifter_pb2_grpc.add_PoseLifterServicer_to_server(servicer, server)  # type: ignore[no-untyped-call]
        health_pb2_grpc.add_HealthServicer_to_server(status.servicer, server)
        names = (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME)
        reflection.enable_server_reflection(names, server)
        try:
            port = server.add_insecure_port(address)
        except RuntimeError as err:  # grpc's way to say the port is taken
            raise OSError(f"cannot bind the gRPC server to {address}: {err}") from err
        if port == 0:
            raise OSError(f"cannot bind the gRPC server to {address}")
        await status.set_status(engine.ready)
        return server, port

    return GrpcServer(build)
