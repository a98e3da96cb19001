"""POST /lift with `invalid_poses: report`: each pose read on its own, the valid ones lifted, the
others answered null with their errors (repnet.core.report)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

from repnet.core.errors import Violation
from repnet.core.inputs import Limits, PoseInput
from repnet.core.report import Outcome, Readable, read_each, spans
from repnet.runtime.replies import Replies
from repnet.server.http.body import REPLY_CHUNK, reply_json
from repnet.server.http.errors import error_item, violations_of
from repnet.server.http.schemas import LiftRequest


def refused_poses(request: LiftRequest) -> dict[int, tuple[Violation, ...]]:
    """The poses the request's schema refused (PoseRefused), each with its violations named within
    the pose (keypoints[3]), as the whole-request error would name them within the request."""
    found = {}
    for i, pose in enumerate(request.poses):
        if errors := pose.refusal:
            named = violations_of([{**e, "loc": ("poses", i, *e["loc"])} for e in errors])
            found[i] = tuple(replace(v, field=v.field.removeprefix(f"poses[{i}].")) for v in named)
    return found


def read_poses(request: LiftRequest, limits: Limits, read: Callable[[int], PoseInput]) -> Readable:
    """The request's poses read one by one (read_each): its own rules refuse it whole."""
    threshold = request.confidence_threshold
    return read_each(len(request.poses), read, threshold, limits, refused_poses(request))


def report_json(head: dict[str, Any], replies: Replies, outcome: Outcome) -> bytes:
    """`head` with `poses` (a lifted pose's reply, null for the others, in request order), `errors`
    and `error_count`; REPLY_CHUNK poses rendered at a time (body.replies_json)."""
    start = reply_json({**head, "poses": []})  # ...,"poses":[]}
    chunks = []
    for a in range(0, len(outcome.rows), REPLY_CHUNK):
        rows = outcome.rows[a : a + REPLY_CHUNK]
        lo, hi = spans(outcome.rows, a, a + REPLY_CHUNK)
        listed = iter(replies.slice(lo, hi).to_json())
        chunks.append(reply_json([next(listed) if r >= 0 else None for r in rows])[1:-1])
    tail = reply_json({"errors": [error_item(v) for v in outcome.errors], "error_count": outcome.error_count})
    return b"".join((start[:-2], b",".join(chunks), b"],", tail[1:]))
