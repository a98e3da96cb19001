"""How gRPC answers a core error: its status code, its message cut to a status header, and a stream
frame's error result within what the frame's other error results leave (ErrorRoom)."""

from __future__ import annotations

import grpc

from repnet._proto.repnet.v1 import lifter_pb2
from repnet.core.errors import MAX_ERROR_ITEMS, InvalidKeypoints, LiftError, ModelNotReady, Overloaded, clip
from repnet.runtime.tracks import TrackLimitReached

MAX_STATUS_CHARS = 1000
MAX_ERROR_CHARS = 16 * 1024  # of one frame's error messages and reasons together (ErrorRoom)
BRIEF_MESSAGE_CHARS = 80  # a person's error message once a frame's ErrorRoom is spent


def status_message(err: Exception) -> str:
    """An error's message, cut to fit a status header."""
    return clip(str(err), MAX_STATUS_CHARS)


def status_of(err: LiftError) -> grpc.StatusCode:
    """The status code a core error is answered with (a track refused for a limit on open tracks:
    RESOURCE_EXHAUSTED, as a quota is, though it names its field as a bad input does)."""
    if isinstance(err, TrackLimitReached):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    if isinstance(err, InvalidKeypoints):
        return grpc.StatusCode.INVALID_ARGUMENT
    if isinstance(err, Overloaded):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    if isinstance(err, ModelNotReady):
        return grpc.StatusCode.UNAVAILABLE
    return grpc.StatusCode.INTERNAL


def frame_error(err: LiftError, room: ErrorRoom | None = None) -> lifter_pb2.FrameError:
    """A stream frame's error result: the status code, message and violations Lift would give, within
    what `room` (the frame's other error results) leaves."""
    room = ErrorRoom() if room is None else room
    violations = (err.violations if isinstance(err, InvalidKeypoints) else ())[: room.items]
    message = status_message(err) if room.chars > 0 else clip(str(err), BRIEF_MESSAGE_CHARS)
    room.items -= len(violations)
    room.chars -= len(message) + sum(len(v.reason) + len(v.field) for v in violations)
    return lifter_pb2.FrameError(
        code=status_of(err).value[0],
        message=message,
        violations=[
            lifter_pb2.FieldViolation(
                field=v.field, reason=v.reason, code=v.code, joint_name=v.joint_name or "", joint=v.joint
            )
            for v in violations
        ],
    )


class ErrorRoom:
    """What one frame's error results may still hold in all: MAX_ERROR_ITEMS violations and
    MAX_ERROR_CHARS of messages and reasons, as an HTTP error reply. Past them, a person's error keeps
    its code and a message of BRIEF_MESSAGE_CHARS: a frame of 1,024 bad people is answered in fewer
    bytes than it sent, not 19 times more."""

    def __init__(self) -> None:
        self.items = MAX_ERROR_ITEMS
        self.chars = MAX_ERROR_CHARS
