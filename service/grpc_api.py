"""gRPC adapter: PoseLifterServicer (Lift, LiftStream), health and reflection; create_server."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from concurrent import futures
from dataclasses import dataclass
from typing import NoReturn

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from service._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from service.engine import Engine
from service.errors import InvalidKeypoints, LiftError, ModelNotReady, Overloaded, Violation
from service.keypoints import DEFAULT_FORMAT, Limits, ModelInput, PoseInput, pose_field, prepare_poses
from service.lifter import Prediction
from service.metrics import ERROR, Metrics, outcome_of

log = logging.getLogger(__name__)

TRANSPORT = "grpc"
# A stream frame that finds the batch queue full waits this long for room before its error result.
STREAM_QUEUE_WAIT_S = 5.0
SERVICE_NAME = lifter_pb2.DESCRIPTOR.services_by_name["PoseLifter"].full_name


def status_of(err: LiftError) -> grpc.StatusCode:
    if isinstance(err, InvalidKeypoints):
        return grpc.StatusCode.INVALID_ARGUMENT
    if isinstance(err, Overloaded):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    if isinstance(err, ModelNotReady):
        return grpc.StatusCode.UNAVAILABLE
    return grpc.StatusCode.INTERNAL


def abort(context: grpc.ServicerContext, err: LiftError) -> NoReturn:
    """The one place where the core's errors become gRPC status codes."""
    context.abort(status_of(err), str(err))


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
    return found


def to_pose_inputs(poses: Sequence[lifter_pb2.Pose2D], default_format: str, prefix: str) -> list[PoseInput]:
    """Proto poses in their wire-independent form; raises InvalidKeypoints on a bad layout."""
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
        inputs.append(PoseInput(points, present, confidence, pose.format or default_format))
    if violations:
        raise InvalidKeypoints(violations)
    return inputs


def to_pose_result(inputs: ModelInput, prediction: Prediction, i: int) -> lifter_pb2.PoseResult:
    return lifter_pb2.PoseResult(
        pose_3d=prediction.pose_3d[i].ravel().tolist(),
        pose_3d_camera=prediction.pose_3d_camera[i].ravel().tolist(),
        camera=prediction.camera[i].ravel().tolist(),
        scale=float(prediction.scale[i]),
        rotation=prediction.rotation[i].ravel().tolist(),
        reprojection=prediction.reprojection[i].ravel().tolist(),
        reprojection_error_px=float(prediction.reprojection_error_px[i]),
        visible=inputs.visible[i].tolist(),
        imputed=inputs.imputed[i].tolist(),
        derived=inputs.derived[i].tolist(),
    )


def frame_error(err: LiftError) -> lifter_pb2.FrameError:
    violations = err.violations if isinstance(err, InvalidKeypoints) else ()
    return lifter_pb2.FrameError(
        code=status_of(err).value[0],
        message=str(err),
        violations=[
            lifter_pb2.FieldViolation(
                field=v.field, reason=v.reason, code=v.code, joint_name=v.joint_name or "", joint=v.joint
            )
            for v in violations
        ],
    )


@dataclass
class _Pending:
    """A stream frame between reading and answering."""

    frame_id: int
    start: float
    inputs: ModelInput | None = None
    future: futures.Future[Prediction] | None = None
    error: LiftError | None = None


class PoseLifterServicer:
    """Implements repnet.v1.PoseLifter on the shared Engine."""

    def __init__(self, engine: Engine, metrics: Metrics, limits: Limits, stream_window: int = 256) -> None:
        self.engine = engine
        self.metrics = metrics
        self.limits = limits
        self.stream_window = stream_window
        self.model_id = engine.lifter.info.model_id
        self.joints = list(engine.lifter.info.joint_names)

    def Lift(self, request: lifter_pb2.LiftRequest, context: grpc.ServicerContext) -> lifter_pb2.LiftResponse:
        threshold = request.confidence_threshold if request.HasField("confidence_threshold") else None
        try:
            with self.metrics.track(TRANSPORT, "Lift"):
                poses = to_pose_inputs(request.poses, request.format or DEFAULT_FORMAT, "poses")
                inputs = prepare_poses(poses, self.limits, threshold)
                prediction = self.engine.lift(inputs, TRANSPORT)
                results = [to_pose_result(inputs, prediction, i) for i in range(len(inputs))]
        except LiftError as err:
            abort(context, err)
        return lifter_pb2.LiftResponse(model_id=self.model_id, joints=self.joints, poses=results)

    def LiftStream(
        self, request_iterator: Iterator[lifter_pb2.LiftFrame], context: grpc.ServicerContext
    ) -> Iterator[lifter_pb2.LiftFrameResult]:
        """Frames are read and queued by a helper thread while this one answers them in order,
        so one stream fills batches instead of waiting for each frame's run."""
        window: queue.Queue[_Pending | None] = queue.Queue(maxsize=self.stream_window)  # None: the end
        stop = threading.Event()
        reader = threading.Thread(
            target=self._read_frames,
            args=(request_iterator, window, stop),
            name="repnet-stream-reader",
            daemon=True,
        )
        self.metrics.open_streams.inc()
        reader.start()
        try:
            while (item := window.get()) is not None:
                yield self._answer(item)
        finally:
            stop.set()  # the client has gone (or the server stops): the reader ends soon
            reader.join(timeout=1.0)
            self.metrics.open_streams.dec()
            while not window.empty():  # frames read but never answered
                if window.get_nowait() is not None:
                    self.metrics.in_flight.labels(transport=TRANSPORT).dec()

    def _read_frames(
        self,
        frames: Iterable[lifter_pb2.LiftFrame],
        window: queue.Queue[_Pending | None],
        stop: threading.Event,
    ) -> None:
        try:
            for frame in frames:
                item = self._submit(frame)
                while not stop.is_set():  # a full window holds the reader back (backpressure)
                    try:
                        window.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                else:  # the answering side stopped before this frame got in
                    self.metrics.in_flight.labels(transport=TRANSPORT).dec()
                    return
        except grpc.RpcError:  # the client cancelled or the call ended: nothing more to read
            pass
        finally:
            _put_end(window, stop)

    def _submit(self, frame: lifter_pb2.LiftFrame) -> _Pending:
        item = _Pending(frame.frame_id, time.perf_counter())
        self.metrics.in_flight.labels(transport=TRANSPORT).inc()
        threshold = frame.confidence_threshold if frame.HasField("confidence_threshold") else None
        try:
            poses = to_pose_inputs([frame.pose], frame.pose.format or DEFAULT_FORMAT, "pose")
            item.inputs = prepare_poses(poses, self.limits, threshold, prefix="pose")
            item.future = self.engine.submit(item.inputs, TRANSPORT, wait_s=STREAM_QUEUE_WAIT_S)[0]
        except LiftError as err:
            item.error = err
        return item

    def _answer(self, item: _Pending) -> lifter_pb2.LiftFrameResult:
        result = lifter_pb2.LiftFrameResult(frame_id=item.frame_id, model_id=self.model_id)
        outcome = outcome_of(item.error)
        try:
            if item.future is not None and item.inputs is not None:
                result.pose.CopyFrom(to_pose_result(item.inputs, item.future.result(), 0))
        except Exception:  # one frame's fault must not end the stream
            log.exception("LiftStream frame %d failed", item.frame_id)
            item.error, outcome = LiftError("internal error while lifting this frame"), ERROR
        if item.error is not None:
            result.error.CopyFrom(frame_error(item.error))
            if isinstance(item.error, InvalidKeypoints):
                self.metrics.reject(TRANSPORT, item.error.violations)
        self.metrics.in_flight.labels(transport=TRANSPORT).dec()
        self.metrics.finish(TRANSPORT, "LiftStream", outcome, time.perf_counter() - item.start)
        return result


def _put_end(window: queue.Queue[_Pending | None], stop: threading.Event) -> None:
    while not stop.is_set():
        try:
            window.put(None, timeout=0.1)
            return
        except queue.Full:
            continue


def set_serving(servicer: health.HealthServicer, serving: bool) -> None:
    """Report the whole server and the PoseLifter service as SERVING or NOT_SERVING."""
    status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
    for name in ("", SERVICE_NAME):
        servicer.set(name, status)


def create_server(
    engine: Engine,
    metrics: Metrics,
    limits: Limits,
    address: str,
    *,
    health_servicer: health.HealthServicer,
    workers: int = 32,
    max_message_bytes: int = 4 << 20,
    stream_window: int = 256,
) -> tuple[grpc.Server, int]:
    """A gRPC server (not started) bound to `address`; returns it and the bound port.

    Each open stream holds one of `workers` threads; calls beyond that get RESOURCE_EXHAUSTED.
    """
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="repnet-grpc"),
        maximum_concurrent_rpcs=workers,
        # so_reuseport 0: a second server on a taken port fails instead of sharing it.
        options=[("grpc.max_receive_message_length", max_message_bytes), ("grpc.so_reuseport", 0)],
    )
    servicer = PoseLifterServicer(engine, metrics, limits, stream_window)
    lifter_pb2_grpc.add_PoseLifterServicer_to_server(servicer, server)  # type: ignore[no-untyped-call]
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    set_serving(health_servicer, engine.ready)
    names = (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME)
    reflection.enable_server_reflection(names, server)
    try:
        port = server.add_insecure_port(address)
    except RuntimeError as err:  # grpc's way to say the port is taken
        raise OSError(f"cannot bind the gRPC server to {address}: {err}") from err
    if port == 0:
        raise OSError(f"cannot bind the gRPC server to {address}")
    return server, port
