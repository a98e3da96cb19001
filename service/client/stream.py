"""gRPC client of the lifting service: LiftStream frame by frame, and the unary Lift."""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from repnet._proto.repnet.v1 import lifter_pb2, lifter_pb2_grpc
from repnet.client.result import ArrayLike, LiftClientError, LiftResult, as_poses
from repnet.core.errors import SPLIT_HINT
from repnet.core.formats import DEFAULT_FORMAT, MODEL_JOINTS

DEFAULT_TARGET = "localhost:50051"


@dataclass(frozen=True)
class Person:
    """One tracked person of a frame with several: (J, 2) keypoints (NaN = missing), its track."""

    track_id: str  # the same person keeps the same id from frame to frame
    keypoints: ArrayLike
    confidence: ArrayLike | None = None
    format: str | None = None  # default: the stream's format


@dataclass(frozen=True)
class Frame:
    """One stream frame: (J, 2) keypoints (NaN = missing) with optional (J,) confidence, or several
    tracked `people`. A pose with a `track_id` (and every person) is answered by the causal temporal
    model from its track's frames so far; the frame_id is then its frame number in time."""

    keypoints: ArrayLike | None = None
    confidence: ArrayLike | None = None
    frame_id: int | None = None  # default: the frame's position in the stream
    format: str | None = None  # default: the stream's format
    track_id: str = ""  # empty: the pose is lifted alone
    people: Sequence[Person] = ()  # instead of keypoints: several people, each with its track
    fps: float | None = None  # frames per second of tracked poses; default: the stream's


@dataclass(frozen=True)
class PersonResult:
    """The answer for one person of a frame, in the frame's order: its result or its error."""

    track_id: str
    result: LiftResult | None
    error: LiftClientError | None


@dataclass(frozen=True)
class FrameResult:
    """The answer to one frame: its result, or the error it got (the stream goes on); for a frame of
    several people, each one's (`people`)."""

    frame_id: int
    result: LiftResult | None
    error: LiftClientError | None
    people: tuple[PersonResult, ...] = ()


_STATUS_NAMES = {code.value[0]: code.name for code in grpc.StatusCode}
_RETRY_CODES = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.RESOURCE_EXHAUSTED)


def _pose_proto(points: np.ndarray, conf: np.ndarray | None, format: str) -> lifter_pb2.Pose2D:
    missing = np.isnan(points).any(axis=1)  # (J,)
    flat = np.where(missing[:, None], 0.0, points).ravel().tolist()
    return lifter_pb2.Pose2D(
        keypoints=flat,
        confidence=[] if conf is None else conf.tolist(),
        missing=missing.tolist() if missing.any() else [],
        format=format,
    )


def proto_field(pose: lifter_pb2.PoseResult) -> Callable[[str], Any]:
    """A field getter of one proto result for LiftResult.from_fields; an unset optional field
    (plausibility, track_id, root_height_source) is None; an empty root_camera_m is read as None."""

    def get(name: str) -> Any:
        if name in ("plausibility", "track_id", "root_height_source") and not pose.HasField(name):
            return None
        return getattr(pose, name)

    return get


def _frame_message(
    i: int,
    frame: ArrayLike | Frame,
    format: str,
    threshold: float | None,
    fps: float | None,
    camera: Camera = None,
) -> lifter_pb2.LiftFrame:
    """The LiftFrame of frame i of a stream, every pose with `camera`'s intrinsics and height; ValueError
    on keypoints of the wrong shape."""
    f = frame if isinstance(frame, Frame) else Frame(frame)
    message = lifter_pb2.LiftFrame(
        frame_id=i if f.frame_id is None else f.frame_id, track_id=f.track_id, confidence_threshold=threshold
    )
    rate = f.fps if f.fps is not None else fps
    if rate is not None and (f.track_id or f.people):
        message.fps = rate
    if f.people:
        for person in f.people:
            pose = _pose_proto(*_one_pose(person.keypoints, person.confidence), person.format or format)
            message.people.add(track_id=person.track_id, pose=_placed(pose, camera))
    elif f.keypoints is not None:
        pose = _pose_proto(*_one_pose(f.keypoints, f.confidence), f.format or format)
        message.pose.CopyFrom(_placed(pose, camera))
    else:
        raise ValueError("a frame needs keypoints or people")
    return message


# A stream's camera: (fx, fy, cx, cy) px or None, and the person's skeleton height in m or None.
Camera = tuple[Sequence[float] | None, float | None] | None


def _placed(pose: lifter_pb2.Pose2D, camera: Camera) -> lifter_pb2.Pose2D:
    """`pose` with the camera's intrinsics and the person's height, where given (root_camera_m)."""
    intrinsics, height = camera or (None, None)
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        pose.intrinsics.CopyFrom(lifter_pb2.CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy))
    if height is not None:
        pose.person_height_m = float(height)
    return pose


def _one_pose(keypoints: ArrayLike, confidence: ArrayLike | None) -> tuple[np.ndarray, np.ndarray | None]:
    """(J, 2) points and (J,) confidence of one pose; ValueError on other shapes."""
    conf = None if confidence is None else np.asarray(confidence)[None]
    points, checked = as_poses(np.asarray(keypoints)[None], conf)
    return points[0], None if checked is None else checked[0]


def _error(e: lifter_pb2.FrameError) -> LiftClientError:
    details = [
        {"field": v.field, "reason": v.reason, "code": v.code, "joint_name": v.joint_name}
        for v in e.violations
    ]
    return LiftClientError(e.message, _STATUS_NAMES.get(e.code, str(e.code)), details)


def _frame_result(answer: lifter_pb2.LiftFrameResult) -> FrameResult:
    """A LiftFrameResult read: the pose, or the frame's error, and each person's."""
    people = []
    for person in answer.people:
        if person.WhichOneof("result") == "pose":
            found = LiftResult.from_fields(proto_field(person.pose), MODEL_JOINTS, answer.model_id)
            people.append(PersonResult(person.track_id, found, None))
        else:
            people.append(PersonResult(person.track_id, None, _error(person.error)))
    kind = answer.WhichOneof("result")
    result = (
        LiftResult.from_fields(proto_field(answer.pose), MODEL_JOINTS, answer.model_id)
        if kind == "pose"
        else None
    )
    error = _error(answer.error) if kind == "error" else None
    return FrameResult(answer.frame_id, result, error, tuple(people))


def _rpc_error(err: grpc.RpcError) -> LiftClientError:
    if isinstance(err, grpc.Call):
        details = err.details() or str(err)
        if _too_large(err):  # gRPC's own words ("Received message larger than max (N vs. M)")
            details = f"{details}: the request is over the service's message limit; {SPLIT_HINT}"
        return LiftClientError(details, err.code().name)
    return LiftClientError(str(err))


def _too_large(err: grpc.RpcError) -> bool:
    """A call refused for its message size (RESOURCE_EXHAUSTED as an overload is, but no retry helps)."""
    return (
        isinstance(err, grpc.Call)
        and err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        and "larger than max" in (err.details() or "")
    )


class StreamClient:
    """gRPC client: `for r in StreamClient("host:50051").stream(frames): ...` over LiftStream.

    `target` is host:port, or `dns:///name:port` to spread calls over every address the name
    resolves to (round_robin; e.g. the headless Service of deploy/k8s: one connection per pod).
    `api_key`: sent as `authorization: Bearer KEY` metadata; `tls`: a TLS channel, whose server
    certificate chains to `ca_file` (PEM; None: the system's CAs). `model`: the model_id every
    request and frame names (GET /v1/models; None: the service's default).
    """

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        *,
        timeout: float | None = None,
        retries: int = 3,
        backoff: float = 0.1,
        max_message_bytes: int = 4 << 20,
        api_key: str | None = None,
        tls: bool = False,
        ca_file: str | Path | None = None,
        model: str | None = None,
    ) -> None:
        self.target, self.timeout, self.retries, self.backoff = target, timeout, retries, backoff
        self.model_id = model or ""
        options = [
            ("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.lb_policy_name", "round_robin"),  # pick_first, the default, calls one address only
        ]
        self._metadata = None if api_key is None else (("authorization", f"Bearer {api_key}"),)
        if tls or ca_file is not None:
            roots = None if ca_file is None else Path(ca_file).read_bytes()
            credentials = grpc.ssl_channel_credentials(root_certificates=roots)
            self._channel = grpc.secure_channel(target, credentials, options=options)
        else:
            self._channel = grpc.insecure_channel(target, options=options)
        self._stub = lifter_pb2_grpc.PoseLifterStub(self._channel)  # type: ignore[no-untyped-call]

    def __enter__(self) -> StreamClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the gRPC channel."""
        self._channel.close()

    def stream(
        self,
        frames: Iterable[ArrayLike | Frame],
        *,
        format: str = DEFAULT_FORMAT,
        confidence_threshold: float | None = None,
        fps: float | None = None,
        intrinsics: Sequence[float] | None = None,
        person_height_m: float | None = None,
    ) -> Generator[FrameResult, None, None]:
        """Send frames as they come and yield one FrameResult per frame, in order.

        A bad frame yields a FrameResult with `error` set (a person's: in `people`); a failed call
        raises LiftClientError, and so does a frame that cannot be sent (after the results of the
        frames before it). `fps`: the frame rate of tracked poses (Frame.track_id, Frame.people)
        that do not give their own. `intrinsics` (fx, fy, cx, cy) px and `person_height_m` go with every
        pose (root_camera_m). Frame results carry the model's joint names (LiftFrameResult has none on
        the wire).
        """
        unsent: list[LiftClientError] = []

        def requests() -> Iterator[lifter_pb2.LiftFrame]:
            i = 0
            try:
                for i, frame in enumerate(frames):
                    message = _frame_message(
                        i, frame, format, confidence_threshold, fps, (intrinsics, person_height_m)
                    )
                    message.model = self.model_id
                    yield message
            except Exception as err:  # gRPC would swallow it on its own thread: raised below
                unsent.append(LiftClientError(f"frame {i} cannot be sent: {getattr(err, 'message', err)}"))

        call = self._stub.LiftStream(requests(), timeout=self.timeout, metadata=self._metadata)
        try:
            for answer in call:
                yield _frame_result(answer)
        except grpc.RpcError as err:
            raise _rpc_error(err) from err
        finally:
            call.cancel()  # a no-op once the call ended; stops it when the caller breaks off early
        if unsent:
            raise unsent[0]

    def lift_batch(
        self,
        keypoints: ArrayLike,
        *,
        format: str = DEFAULT_FORMAT,
        confidence: ArrayLike | None = None,
        confidence_threshold: float | None = None,
        intrinsics: Sequence[float] | None = None,
        person_height_m: float | None = None,
    ) -> list[LiftResult]:
        """Lift (N, J, 2) poses with the unary Lift, retrying UNAVAILABLE and RESOURCE_EXHAUSTED;
        `intrinsics` and `person_height_m` as for stream."""
        points, conf = as_poses(keypoints, confidence)
        camera = (intrinsics, person_height_m)
        poses = [
            _placed(_pose_proto(p, None if conf is None else conf[i], format), camera)
            for i, p in enumerate(points)
        ]
        request = lifter_pb2.LiftRequest(
            poses=poses, format=format, model=self.model_id, confidence_threshold=confidence_threshold
        )
        for attempt in range(self.retries + 1):
            try:
                response = self._stub.Lift(request, timeout=self.timeout, metadata=self._metadata)
                joints, model_id = response.joints, response.model_id
                return [LiftResult.from_fields(proto_field(p), joints, model_id) for p in response.poses]
            except grpc.RpcError as err:
                retry = isinstance(err, grpc.Call) and err.code() in _RETRY_CODES and not _too_large(err)
                if not retry or attempt == self.retries:
                    raise _rpc_error(err) from err
                time.sleep(self.backoff * 2**attempt)
        raise AssertionError("unreachable: the last attempt returns or raises")
