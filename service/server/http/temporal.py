"""POST /lift with `temporal` causal or offline: a request's tracked poses lifted as clips."""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import replace

import numpy as np

from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.inputs import Limits, ModelInput, PoseInput
from repnet.core.keypoints import prepare_poses, prepare_request
from repnet.core.report import REPORT, Outcome, outcome, positions_of
from repnet.runtime.batcher import offload
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.lifter import ModelInfo, Prediction
from repnet.runtime.plans import Plan, TemporalModels, clip_plan, clip_violations, run_plan
from repnet.runtime.replies import TemporalRows, build_replies
from repnet.server.http.body import replies_json
from repnet.server.http.report import read_poses, report_json
from repnet.server.http.schemas import LiftRequest
from repnet.server.metrics import Metrics

TRANSPORT = "http"


def track_violations(request: LiftRequest, temporal: TemporalModels | None) -> list[Violation]:
    """The rules of a temporal request: its model is loaded, fps is given, each tracked pose has a
    frame number, and no frame of a track comes twice."""
    engine = None if temporal is None else temporal.engines.get(request.temporal)
    if engine is None:
        reason = f"this service has no {request.temporal} temporal model (REPNET_TEMPORAL); send temporal off"
        return [Violation("temporal", reason, "no_temporal_model")]
    track_ids = [pose.track_id for pose in request.poses]
    return clip_violations(track_ids, [pose.frame for pose in request.poses], request.fps)


Read = Callable[[int], PoseInput]  # pose i of the request in its wire-independent form


def prepare_temporal(
    request: LiftRequest, limits: Limits, temporal: TemporalModels | None, read: Read
) -> tuple[ModelInput, Outcome | None]:
    """The model input of a temporal request (at most max_temporal_poses): all its poses, valid;
    else InvalidKeypoints with the track rules' and the poses' violations. With `invalid_poses:
    report`, its valid poses and the outcome (a pose not lifted is a gap in its track); only the
    request's and the track rules refuse it."""
    if found := track_violations(request, temporal):
        raise InvalidKeypoints(found)
    assert temporal is not None  # track_violations says when it is missing
    wider = replace(limits, max_request_poses=temporal.max_poses)
    if request.invalid_poses != REPORT:
        return prepare_request(len(request.poses), read, request.confidence_threshold, wider), None
    readable = read_poses(request, wider, read)
    prepared = prepare_poses(readable.poses, wider, request.confidence_threshold)
    return prepared.inputs, outcome(len(request.poses), readable, prepared)


def lifted_positions(request: LiftRequest, result: Outcome | None) -> Sequence[int]:
    """The request index of each row of the model input: every pose, or those lifted."""
    return range(len(request.poses)) if result is None else positions_of(result)


def plan_of(
    request: LiftRequest,
    temporal: TemporalModels,
    inputs: ModelInput,
    prediction: Prediction,
    result: Outcome | None = None,
) -> Plan:
    """The temporal windows of the request's tracked poses (those lifted, with `result`)."""
    engine = temporal.engines[request.temporal]
    poses = [request.poses[i] for i in lifted_positions(request, result)]  # one per row of inputs
    tracked = [k for k, p in enumerate(poses) if p.track_id is not None]
    rows = np.array(tracked, np.int64)
    track_ids = [str(poses[k].track_id) for k in tracked]
    frames = np.array([poses[k].frame for k in tracked], np.int64)
    fps = float(request.fps or 0.0)  # given: track_violations checked it
    return clip_plan(rows, track_ids, frames, fps, engine.lifter.contract, inputs, prediction)


def temporal_body(
    info: ModelInfo,
    inputs: ModelInput,
    prediction: Prediction,
    rows: TemporalRows,
    request: LiftRequest,
    result: Outcome | None = None,
) -> bytes:
    """The 200 answer's JSON (ModelOutputError when a model failed on any pose), tracks echoed;
    rendered here, off the event loop (6,000 poses: tens of milliseconds)."""
    track_ids = [request.poses[i].track_id for i in lifted_positions(request, result)]
    replies = build_replies(inputs, prediction, rows, track_ids).check()
    head = {"model_id": info.model_id, "joints": list(info.joint_names)}
    return replies_json(head, replies) if result is None else report_json(head, replies, result)


async def lift_temporal(
    request: LiftRequest,
    engine: LiftBatcher,
    temporal: TemporalModels | None,
    limits: Limits,
    metrics: Metrics,
    started: float | None,
    read: Read,
    source: Hashable = None,
) -> bytes:
    """The JSON of the answer: every pose lifted alone, then each tracked pose again from its
    track's window."""
    count = len(request.poses)
    with metrics.parsing(TRANSPORT, started):
        inputs, result = await offload(count, prepare_temporal, request, limits, temporal, read)
    if result is not None:  # invalid_poses report: the poses not lifted, counted as a refusal's
        metrics.reject(TRANSPORT, result.errors)
    assert temporal is not None  # prepare_temporal refuses the request without it
    prediction = await engine.predict_async(inputs, TRANSPORT, source=source)
    plan = await offload(count, plan_of, request, temporal, inputs, prediction, result)
    rows = await run_plan(temporal.engines[request.temporal], plan, TRANSPORT, source=source)
    info = engine.lifter.info
    return await offload(count, temporal_body, info, inputs, prediction, rows, request, result)
