"""gRPC adapter: PoseLifterServicer (Lift, LiftStream): proto <-> PoseInput and replies, limits, errors."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from functools import partial
from typing import Any

import grpc

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core import report
from repnet.core.contract import MAX_FRAME, MAX_TRACK_ID
from repnet.core.errors import (
    InvalidKeypoints,
    LiftError,
    ModelOutputError,
    Violation,
    clip,
)
from repnet.core.formats import DEFAULT_FORMAT
from repnet.core.inputs import Limits, PoseInput
from repnet.core.keypoints import check_threshold, read_request
from repnet.runtime.batcher import offload
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.pipeline import Job, Lifted
from repnet.runtime.plans import TemporalModels
from repnet.runtime.tracks import fps_violations
from repnet.server.auth import client_identity
from repnet.server.grpc.errors import ErrorRoom, frame_error, status_message, status_of
from repnet.server.grpc.input import image_size_violations, intrinsics_violations, to_pose_input
from repnet.server.metrics import OVERLOADED, Metrics, outcome_of
from repnet.server.stream import (
    POSE_FIELD,
    Answer,
    Answers,
    FrameIn,
    PersonIn,
    StreamIdle,
    UnreadableFrame,
    answer_stream,
)

log = logging.getLogger(__name__)

TRANSPORT = "grpc"
SERVICE_NAME = lifter_pb2.DESCRIPTOR.services_by_name["PoseLifter"].full_name
# The longest status message: it travels in a header, and one over grpc's metadata limit (8 KiB
# soft, 16 KiB hard, after percent-encoding) reaches the client as RESOURCE_EXHAUSTED instead.
INTERNAL_MESSAGE = "internal error while lifting; this is a server fault"
Context = grpc.aio.ServicerContext[Any, Any]


def frame_violations(message: lifter_pb2.LiftFrame, max_people: int) -> list[Violation]:
    """A frame's own rules: a pose or people, not both, at most `max_people` of them (a request's
    pose limit: one frame's poses always fit the batch queue); people each with a track id of their
    own; the frame rate of tracked poses."""
    several = len(message.people) > 0
    if several and message.HasField("pose"):
        return [Violation("people", "give the frame's pose or its people, not both", "pose_and_people")]
    if len(message.people) > max_people:
        count = len(message.people)
        reason = f"{count} people in one frame, the limit is {max_people} (REPNET_MAX_REQUEST_POSES)"
        return [Violation("people", reason, "too_many_people")]
    found, seen = [], set()
    for k, person in enumerate(message.people):
        if not person.track_id or len(person.track_id) > MAX_TRACK_ID:
            reason = f"every person needs a track_id of 1 to {MAX_TRACK_ID} characters"
            found.append(Violation(f"people[{k}].track_id", reason, "track_id"))
        elif person.track_id in seen:
            reason = f"track {clip(person.track_id, 100)!r} comes twice in this frame"
            found.append(Violation(f"people[{k}].track_id", reason, "track_repeated"))
        seen.add(person.track_id)
    if len(message.track_id) > MAX_TRACK_ID:
        found.append(Violation("track_id", f"at most {MAX_TRACK_ID} characters", "track_id"))
    if several or message.track_id:
        found += fps_violations(message.fps or None, "fps")
        if message.frame_id > MAX_FRAME:
            reason = f"a tracked frame's number is at most {MAX_FRAME} (2^53 - 1), got {message.frame_id}"
            found.append(Violation("frame_id", reason, "frame_range"))
    return found


def proto_response(model_id: str, joints: list[str], lifted: Lifted) -> lifter_pb2.LiftResponse:
    """A Lift's answer, built on the batcher's thread with each PoseResult in place; InvalidKeypoints
    naming every pose that breaks a rule, ModelOutputError when the model failed on any of its poses."""
    lifted.prepared.check()
    assert lifted.replies is not None  # the job asks for them
    poses = lifted.replies.check().proto_fields()
    return lifter_pb2.LiftResponse(model_id=model_id, joints=joints, poses=poses)


def proto_report(
    metrics: Metrics, count: int, readable: report.Readable, model_id: str, joints: list[str], lifted: Lifted
) -> lifter_pb2.LiftResponse:
    """The answer of an INVALID_POSES_REPORT Lift (on the batcher's thread): an empty PoseResult for
    each pose not lifted (counted as rejected input, once per reason) and a PoseError naming why;
    ModelOutputError when the model failed on any pose."""
    assert lifted.replies is not None  # the job asks for them
    result = report.outcome(count, readable, lifted.prepared)
    metrics.reject(TRANSPORT, result.errors)
    replies = iter(lifted.replies.check().proto_fields())
    poses = [next(replies) if row >= 0 else {} for row in result.rows]
    by_pose: dict[int, list[Violation]] = {}
    for v in result.errors:
        by_pose.setdefault(v.pose or 0, []).append(v)
    room = ErrorRoom()
    errors = [
        lifter_pb2.PoseError(pose=i, error=frame_error(InvalidKeypoints(found), room))
        for i, found in by_pose.items()
    ]
    return lifter_pb2.LiftResponse(model_id=model_id, joints=joints, poses=poses, errors=errors)


class PoseLifterServicer:
    """Implements repnet.v1.PoseLifter (grpc.aio) on the shared LiftBatcher.

    Every call runs on the gRPC server's event loop; only onnxruntime runs elsewhere (the engine's
    worker thread), and the input rules and replies of many poses run on worker threads.

    Lift calls and open streams have limits of their own (the server's maximum_concurrent_rpcs
    would count health checks too, and let idle streams lock everything out); a call beyond its
    limit is refused with RESOURCE_EXHAUSTED and counted. A stream with nothing in progress that
    sends no frame for `stream_idle_timeout_s` is closed with DEADLINE_EXCEEDED.
    """

    def __init__(
        self,
        engine: LiftBatcher | Catalog,
        metrics: Metrics,
        limits: Limits,
        *,
        stream_window_poses: int,
        max_unary: int,
        max_streams: int,
        stream_idle_timeout_s: float,
        temporal: TemporalModels | None = None,
        max_client_streams: int | None = None,
    ) -> None:
        self.models = Catalog.of(engine, temporal is not None)  # a request's `model` picks one
        self.metrics = metrics
        self.limits = limits
        self.stream_window_poses = stream_window_poses
        self.max_unary = max_unary
        self.max_streams = max_streams
        self.stream_idle_timeout_s = stream_idle_timeout_s
        self.temporal = temporal
        self.joints = list(self.models.default_engine.lifter.info.joint_names)  # every model's (app.py)
        self._unary = 0  # Lift calls in progress; both counters live on the server's one event loop
        self._streams = 0  # LiftStream calls open
        self.max_client_streams = max_streams if max_client_streams is None else max_client_streams
        self._client_streams: dict[str, int] = {}  # by client_of (only those with one open)

    async def _refuse(self, context: Context, method: str, message: str) -> None:
        self.metrics.finish(TRANSPORT, method, OVERLOADED, 0.0)
        await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, message)

    async def Lift(self, request: lifter_pb2.LiftRequest, context: Context) -> lifter_pb2.LiftResponse:
        """Lift a batch of poses: one PoseResult per pose, in order, or one status for the call."""
        if self._unary >= self.max_unary:
            await self._refuse(
                context, "Lift", f"too many Lift calls in progress (limit {self.max_unary}); retry later"
            )
        count = len(request.poses)
        self._unary += 1
        try:
            with self.metrics.track(TRANSPORT, "Lift"):
                with self.metrics.parsing(TRANSPORT):
                    engine = self.models.pick(request.model)
                    readable, threshold = await offload(count, self._read_request, request)
                head = (engine.model, self.joints)
                if request.invalid_poses == lifter_pb2.INVALID_POSES_REPORT:
                    finish = partial(proto_report, self.metrics, count, readable, *head)
                else:
                    finish = partial(proto_response, *head)
                job = Job(finish, readable.poses, threshold=threshold)
                response: lifter_pb2.LiftResponse = await engine.run_async(
                    job, TRANSPORT, source=context.peer()
                )
        except LiftError as err:
            if isinstance(err, ModelOutputError):  # counted by track(); one line, no traceback
                log.error("Lift: %s", err)
            await context.abort(status_of(err), status_message(err))
        except Exception:  # counted as an error by track(); the client gets no exception class
            log.exception("Lift failed")
            await context.abort(grpc.StatusCode.INTERNAL, INTERNAL_MESSAGE)
        finally:
            self._unary -= 1
        return response

    def _read_request(self, request: lifter_pb2.LiftRequest) -> tuple[report.Readable, float | None]:
        """A Lift's poses as read from the wire, and its threshold: read_request's rules, or with
        INVALID_POSES_REPORT read_each's (each pose on its own)."""
        default = request.intrinsics if request.HasField("intrinsics") else None
        size = request.image_size if request.HasField("image_size") else None
        found = [] if default is None else intrinsics_violations(default, "intrinsics")
        if found := found + ([] if size is None else image_size_violations(size, "image_size")):
            raise InvalidKeypoints(found)
        threshold = request.confidence_threshold if request.HasField("confidence_threshold") else None
        poses, fmt = request.poses, request.format or DEFAULT_FORMAT
        height = request.person_height_m if request.HasField("person_height_m") else None

        def read(i: int) -> PoseInput:
            return to_pose_input(poses[i], fmt, default, size, height)

        if request.invalid_poses == lifter_pb2.INVALID_POSES_REPORT:
            return report.read_each(len(poses), read, threshold, self.limits), threshold
        everything = read_request(len(poses), read, threshold, self.limits)
        return report.Readable(everything, list(range(len(poses))), {}), threshold

    async def LiftStream(
        self, request_iterator: AsyncIterator[lifter_pb2.LiftFrame], context: Context
    ) -> AsyncIterator[lifter_pb2.LiftFrameResult]:
        """One result per frame, in order (stream.answer_stream: the frames read while a run is in
        progress are lifted together, at most stream_window_poses poses are held)."""
        if self._streams >= self.max_streams:
            await self._refuse(
                context, "LiftStream", f"too many open streams (limit {self.max_streams}); retry later"
            )
        key = next((v for k, v in context.invocation_metadata() or () if k == "authorization"), None)
        client = client_identity(key if isinstance(key, str) else None, context.peer())
        if self._client_streams.get(client, 0) >= self.max_client_streams:
            reason = f"this client has too many open streams (limit {self.max_client_streams}); retry later"
            await self._refuse(context, "LiftStream", reason)
        gauge = self.metrics.in_flight.labels(transport=TRANSPORT)
        held = 0  # frames read and not answered

        async def frames() -> AsyncIterator[FrameIn]:
            nonlocal held
            async for message in request_iterator:
                held += 1
                gauge.inc()
                yield self._frame(message)

        self._streams += 1
        self._client_streams[client] = self._client_streams.get(client, 0) + 1
        self.metrics.open_streams.inc()
        answers = answer_stream(
            frames(),
            self.models,
            self.limits,
            self._results,
            window=self.stream_window_poses,
            idle_timeout_s=self.stream_idle_timeout_s,
            transport=TRANSPORT,
            temporal=self.temporal,
            source=context.peer(),  # the batch queue is shared fairly between connections
        )
        try:
            async for results in answers:
                for result, answer in results:
                    yield result
                    held -= 1
                    gauge.dec()
                    self._count(answer)
        except StreamIdle as err:
            self.metrics.idle_streams_closed.inc()
            reason = f"{err}: the stream is closed as idle (REPNET_STREAM_IDLE_TIMEOUT_S)"
            await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, reason)
        except UnreadableFrame as err:
            reason = f"a frame cannot be decoded as a LiftFrame ({err}); the stream ends"
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, reason)
        finally:
            await answers.aclose()
            self._streams -= 1
            if (left := self._client_streams.pop(client) - 1) > 0:
                self._client_streams[client] = left
            self.metrics.open_streams.dec()
            gauge.dec(held)  # frames read but never answered (the client went away)

    def _frame(self, message: lifter_pb2.LiftFrame) -> FrameIn:
        """A frame read from the wire: its pose or people (layout, threshold, tracks and fps
        checked), or why it has none."""
        read_at = time.perf_counter()
        frame_id, several = message.frame_id, len(message.people) > 0
        model = message.model or self.models.default
        try:
            threshold = message.confidence_threshold if message.HasField("confidence_threshold") else None
            cut = check_threshold(threshold, self.limits)
            if found := frame_violations(message, self.limits.max_request_poses):
                raise InvalidKeypoints(found)
            tracked = self.temporal is not None and (several or bool(message.track_id))
            if (wrong := self.models.violation(message.model, tracked)) is not None:
                raise InvalidKeypoints([wrong])
        except InvalidKeypoints as err:
            known = model in self.models.engines  # an unknown name is never echoed as a model_id
            return FrameIn(frame_id, read_at, error=err, model=model if known else self.models.default)
        fps = float(message.fps)
        if not several:
            try:
                pose = to_pose_input(message.pose, message.pose.format or DEFAULT_FORMAT, None, threshold=cut)
            except InvalidKeypoints as err:
                named = InvalidKeypoints([v.within(POSE_FIELD) for v in err.violations])
                return FrameIn(frame_id, read_at, error=named, model=model)
            return FrameIn(
                frame_id,
                read_at,
                pose,
                None,
                message.track_id,
                fps,
                model=model,
            )
        people = []
        for k, person in enumerate(message.people):
            field = f"people[{k}]"
            try:
                pose = to_pose_input(person.pose, person.pose.format or DEFAULT_FORMAT, None, threshold=cut)
            except InvalidKeypoints as err:
                named = InvalidKeypoints([v.within(f"{field}.pose") for v in err.violations])
                people.append(PersonIn(person.track_id, f"{field}.pose", error=named))
                continue
            people.append(PersonIn(person.track_id, f"{field}.pose", pose))
        return FrameIn(frame_id, read_at, track_id="", fps=fps, people=tuple(people), model=model)

    def _results(self, answered: Answers) -> list[tuple[lifter_pb2.LiftFrameResult, Answer]]:
        """A group's LiftFrameResults in frame order, each beside its answer."""
        poses = answered.replies.proto_fields() if answered.replies is not None else []
        out = []
        for answer in answered.items:
            fields: dict[str, Any] = {"frame_id": answer.frame.frame_id, "model_id": answer.frame.model}
            if isinstance(answer.outcome, LiftError):
                fields["error"] = frame_error(answer.outcome)
            elif answer.outcome is not None:
                fields["pose"] = poses[answer.outcome]
            result = lifter_pb2.LiftFrameResult(**fields)
            room = ErrorRoom()  # shared by the frame's people
            for person, outcome in zip(answer.frame.people or (), answer.people, strict=True):
                if isinstance(outcome, LiftError):
                    result.people.add(track_id=person.track_id, error=frame_error(outcome, room))
                else:
                    result.people.add(track_id=person.track_id, pose=poses[outcome])
            out.append((result, answer))
        return out

    def _count(self, answer: Answer) -> None:
        """Count a frame once its result is sent: its outcome and latency, and what its error says."""
        error = answer.error
        if error is not None:
            self.metrics.count_error(TRANSPORT, error)
        seconds = time.perf_counter() - answer.frame.read_at
        self.metrics.finish(TRANSPORT, "LiftStream", outcome_of(error), seconds)
