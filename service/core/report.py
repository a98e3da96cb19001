"""A request's poses answered one by one (`invalid_poses: report` over HTTP, INVALID_POSES_REPORT over
gRPC Lift): the valid poses are lifted and the others carry their own errors, in request order. The
request's own rules (its pose count, its threshold, a temporal request's track rules) still refuse
it whole."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.inputs import Limits, PoseInput, Prepared
from repnet.core.keypoints import check_request

REPORT = "report"  # invalid_poses: answer the valid poses, each invalid one with its errors
MAX_POSE_ERRORS = 3  # violations listed per unlifted pose (its first ones; error_count says how many)


@dataclass(frozen=True)
class Readable:
    """A request's poses as read from the wire, one by one: those that could be read (in request
    order), each one's position in the request, and why each of the others could not be."""

    poses: list[PoseInput]
    positions: list[int]  # positions[k]: the request index of poses[k]
    unread: dict[int, tuple[Violation, ...]]  # request index -> violations named within the pose


def read_each(
    count: int,
    read: Callable[[int], PoseInput],
    threshold: float | None,
    limits: Limits,
    refused: dict[int, tuple[Violation, ...]] | None = None,
) -> Readable:
    """Every pose of a request of `count` poses read on its own: read(i) converts pose i or raises
    InvalidKeypoints named within the pose, and `refused` gives the poses already refused by the
    wire's schema. The request's own rules (check_request) raise InvalidKeypoints."""
    check_request(count, threshold, limits)
    unread = dict(refused or {})
    poses: list[PoseInput] = []
    positions: list[int] = []
    for i in range(count):
        if i in unread:
            continue
        try:
            poses.append(read(i))
            positions.append(i)
        except InvalidKeypoints as err:
            unread[i] = err.violations
    return Readable(poses, positions, unread)


@dataclass(frozen=True)
class Outcome:
    """Which poses of a request were lifted: per request pose its row among the lifted poses (-1: not
    lifted), and the errors of those not lifted, named within the request (poses[3].keypoints)."""

    rows: npt.NDArray[np.int64]  # (count,)
    errors: tuple[Violation, ...]  # at most MAX_POSE_ERRORS per pose, in request order
    error_count: int  # every violation of every pose not lifted


def outcome(count: int, readable: Readable, prepared: Prepared) -> Outcome:
    """The outcome of a request whose readable poses went through the input rules (`prepared`: their
    violations per readable pose, fields named within the pose, `pose` its index among them)."""
    found: dict[int, tuple[Violation, ...]] = dict(readable.unread)
    for k, violations in enumerate(prepared.violations):
        if violations:
            found[readable.positions[k]] = tuple(replace(v, pose=readable.positions[k]) for v in violations)
    rows = np.full(count, -1, np.int64)
    lifted = [i for i in range(count) if i not in found]
    rows[lifted] = np.arange(len(lifted))
    errors: list[Violation] = []
    total = 0
    for i in sorted(found):
        total += len(found[i])
        errors.extend(replace(v, pose=i).within(f"poses[{i}]") for v in found[i][:MAX_POSE_ERRORS])
    return Outcome(rows, tuple(errors), total)


def spans(rows: npt.NDArray[np.int64], start: int, stop: int) -> tuple[int, int]:
    """The lifted rows of request poses start..stop-1 (increasing, so one range)."""
    part = rows[start:stop]
    found = part[part >= 0]
    return (int(found[0]), int(found[-1]) + 1) if len(found) else (0, 0)


def positions_of(outcome: Outcome) -> Sequence[int]:
    """The request index of each lifted pose, in order."""
    return [int(i) for i in np.flatnonzero(outcome.rows >= 0)]
