"""HTTP adapter: create_app(engine, metrics, limits) with /lift, health, model info and /metrics."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import pydantic_core
from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.exceptions import HTTPException

from service.engine import Engine, offload
from service.errors import (
    MAX_ECHO_CHARS,
    MAX_ERROR_ITEMS,
    InvalidKeypoints,
    LiftError,
    ModelNotReady,
    ModelOutputError,
    Overloaded,
    Violation,
    clip,
)
from service.formats import FORMATS
from service.http_middleware import (
    OUTCOME_KEY,
    STARTED_KEY,
    BodyLimitMiddleware,
    LiftMetricsMiddleware,
    LoadShedMiddleware,
)
from service.http_models import ModelDescription, describe_model
from service.http_temporal import lift_temporal
from service.keypoints import Limits, ModelInput, PoseInput, prepare_request
from service.lifter import ModelInfo, Prediction
from service.metrics import INVALID, Metrics, outcome_of
from service.page import add_page
from service.replies import build_replies
from service.schemas import (
    FRAME_DOC,
    UNKNOWN_FIELD,
    ErrorResponse,
    LiftRequest,
    LiftResponse,
    PoseIn,
)
from service.tracking import TemporalModels

log = logging.getLogger(__name__)

ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorResponse, "description": "The body is not UTF-8 JSON, or is nested too deeply."},
    413: {"model": ErrorResponse, "description": "The body is larger than the limit."},
    422: {"model": ErrorResponse, "description": "A field breaks an input rule; `detail` names it."},
    503: {"model": ErrorResponse, "description": "Queue full or shutting down; retry later."},
}


def _layout_violations(
    pose: PoseIn, width: int, fmt: str, size: tuple[float, float] | None, index: int
) -> list[Violation]:
    """Rules on rows of 3 and 4 values: where their confidence and their pixel scale come from
    (fields named within the pose)."""
    found = []
    if width >= 3 and pose.confidence is not None:
        reason = "give the confidence either as the third value of each joint or as `confidence`, not both"
        found.append(Violation("confidence", reason, "confidence_twice", pose=index))
    if width == 4 and size is None:
        reason = (
            "rows of 4 values are MediaPipe landmarks [x, y, z, visibility] with x and y normalised to "
            "[0, 1]: give image_size [width, height] in pixels to scale them"
        )
        found.append(Violation("image_size", reason, "image_size_needed", pose=index))
    if width == 4 and fmt != "mediapipe33" and fmt in FORMATS:  # an unknown format is named later
        reason = (
            "rows of 4 values are MediaPipe landmarks [x, y, z, visibility]: send format mediapipe33, "
            f"not {fmt}"
        )
        found.append(Violation("keypoints", reason, "layout_format", pose=index))
    return found


def to_pose_input(pose: PoseIn, request: LiftRequest, index: int) -> PoseInput:
    """The wire-independent form of one JSON pose; null joints are marked not present. Rows of
    [x, y, confidence] give the confidence; MediaPipe rows [x, y, z, visibility] are scaled by the
    image size and give the visibility as the confidence. Raises InvalidKeypoints on a bad layout
    (fields named within the pose)."""
    fmt = pose.format or request.format
    size = pose.image_size or request.image_size
    camera = pose.intrinsics or request.intrinsics
    intrinsics = None if camera is None else (*camera.focal_px, *camera.principal_point_px)
    width = next((len(p) for p in pose.keypoints if p is not None), 2)  # every row has it (PoseIn)
    present = np.array([p is not None for p in pose.keypoints], dtype=bool)
    blank = (np.nan,) * width
    rows = np.array([p if p is not None else blank for p in pose.keypoints], dtype=np.float64)
    rows = rows.reshape(-1, width)  # (K, width)
    confidence = None if pose.confidence is None else np.array(pose.confidence, dtype=np.float64)
    if width == 2 and size is None:
        return PoseInput(rows, present, confidence, fmt, intrinsics)
    if found := _layout_violations(pose, width, fmt, size, index):
        raise InvalidKeypoints(found)
    points = rows[:, :2] if size is None else rows[:, :2] * np.asarray(size)  # (K, 2) px
    if width >= 3:  # a missing joint's confidence is never read: 0 keeps the range check quiet
        confidence = np.where(present, rows[:, width - 1], 0.0)
    return PoseInput(points, present, confidence, fmt, intrinsics)


class LiftJSONResponse(JSONResponse):
    """A reply rendered by pydantic-core's JSON serializer: the same values as json.dumps, about
    ten times faster for the float arrays of a batch (a 256-pose reply: 3.6 ms instead of 46 ms).
    A non-finite number, which the model should never produce, is written as null."""

    def render(self, content: Any) -> bytes:
        """`content` as JSON bytes."""
        return pydantic_core.to_json(content, inf_nan_mode="null")


def _prepare(request: LiftRequest, limits: Limits) -> ModelInput:
    poses, threshold = request.poses, request.confidence_threshold
    return prepare_request(len(poses), lambda i: to_pose_input(poses[i], request, i), threshold, limits)


def reply_of(
    info: ModelInfo, inputs: ModelInput, prediction: Prediction, request: LiftRequest
) -> LiftJSONResponse:
    """The 200 answer to a request; ModelOutputError when the model failed on any of its poses."""
    track_ids = [p.track_id for p in request.poses]
    poses = build_replies(inputs, prediction, track_ids=track_ids).check().to_json()
    return LiftJSONResponse({"model_id": info.model_id, "joints": list(info.joint_names), "poses": poses})


def error_item(v: Violation) -> dict[str, Any]:
    """One violation as an item of a 4xx body's `detail`."""
    return {
        "field": v.field,
        "reason": v.reason,
        "message": v.message,
        "code": v.code,
        "pose": v.pose,
        "joint": v.joint,
        "joint_name": v.joint_name,
    }


def error_body(violations: Sequence[Violation]) -> dict[str, Any]:
    """The body of a 4xx: the first MAX_ERROR_ITEMS violations as items, and how many there were."""
    return {
        "detail": [error_item(v) for v in violations[:MAX_ERROR_ITEMS]],
        "error_count": len(violations),
    }


def _loc_part(part: Any) -> str:
    """One step of a pydantic error location in a field name; a key from the request is cut short."""
    return f"[{part}]" if isinstance(part, int) else "." + clip(str(part), MAX_ECHO_CHARS)


def violations_of(errors: Sequence[Any]) -> list[Violation]:
    """Pydantic's errors as Violations, naming the field like the core does: poses[0].keypoints[3]."""
    found = []
    for error in errors:
        loc = [p for p in error.get("loc", ()) if p != "body"]
        if error.get("type") == UNKNOWN_FIELD:  # the key the error is about
            loc.append(str((error.get("ctx") or {}).get("key", "")))
        if error.get("type") == "json_invalid":
            loc = []
        field = "".join(_loc_part(p) for p in loc).lstrip(".") or "body"
        pose = loc[1] if len(loc) > 1 and loc[0] == "poses" and isinstance(loc[1], int) else None
        joint = None
        if (
            pose is not None
            and len(loc) > 3
            and loc[2] in ("keypoints", "confidence")
            and isinstance(loc[3], int)
        ):
            joint = loc[3]
        reason = str(error.get("msg", "invalid"))
        if ctx_error := (error.get("ctx") or {}).get("error"):
            reason = f"{reason}: {ctx_error}"
        code = "malformed_json" if error.get("type") == "json_invalid" else "malformed"
        found.append(Violation(field, reason, code, pose=pose, joint=joint))
    return found


def content_type_violation(content_type: str | None, violations: Sequence[Violation]) -> Violation | None:
    """What to say when the body was not read as JSON because its content-type is not JSON (FastAPI
    then validates the raw body and says "Input should be a valid dictionary"); None otherwise."""
    if (content_type and "json" in content_type.lower()) or not any(v.field == "body" for v in violations):
        return None
    got = f"content-type: {clip(content_type, MAX_ECHO_CHARS)}" if content_type else "no content-type"
    reason = f"expected a JSON body with content-type: application/json, got {got}"
    if content_type and "form" in content_type:
        reason += " (curl -d sends a form: add -H 'content-type: application/json')"
    return Violation("body", reason, "content_type")


def error_response(err: Exception) -> JSONResponse:
    """The answer to a core error: 422 with the violations, 503 to retry, 500 for the model's fault."""
    if isinstance(err, InvalidKeypoints):
        return JSONResponse(error_body(err.violations), status_code=422)
    if isinstance(err, Overloaded | ModelNotReady):
        return JSONResponse({"detail": str(err)}, status_code=503, headers={"Retry-After": "1"})
    if isinstance(err, ModelOutputError):  # counted by the handler; one line, no traceback
        log.error("POST /lift: %s", err)
        return JSONResponse({"detail": str(err)}, status_code=500)
    raise err  # any other LiftError is a server fault: the 500 handler logs it


def add_error_handlers(app: FastAPI, metrics: Metrics) -> None:
    """The one error path of the API: core errors, pydantic's and FastAPI's 400 as JSON error bodies."""

    @app.exception_handler(LiftError)
    async def handle_lift_error(request: Request, err: Exception) -> JSONResponse:
        setattr(request.state, OUTCOME_KEY, outcome_of(err))
        metrics.count_error("http", err)
        return error_response(err)

    @app.exception_handler(RequestValidationError)
    async def handle_validation_error(request: Request, err: Exception) -> JSONResponse:
        if (started := getattr(request.state, STARTED_KEY, None)) is not None:  # rejected while parsed
            metrics.parse_seconds.labels(transport="http").observe(time.perf_counter() - started)
        violations = violations_of(err.errors() if isinstance(err, RequestValidationError) else [])
        if not_json := content_type_violation(request.headers.get("content-type"), violations):
            violations = [not_json]
        setattr(request.state, OUTCOME_KEY, INVALID)
        metrics.reject("http", violations)
        return JSONResponse(error_body(violations), status_code=422)

    @app.exception_handler(HTTPException)
    async def handle_http_error(request: Request, err: Exception) -> Response:
        """FastAPI answers 400 to a body it cannot decode (not UTF-8, nested too deep): name it."""
        if not isinstance(err, HTTPException):
            raise err
        if err.status_code != 400 or request.url.path != "/lift":
            return await http_exception_handler(request, err)
        reason = "the body cannot be decoded as JSON (invalid UTF-8 or nested too deeply)"
        violation = Violation("body", reason, "malformed_json")
        setattr(request.state, OUTCOME_KEY, INVALID)
        metrics.reject("http", [violation])
        return JSONResponse(error_body([violation]), status_code=400)


def create_app(
    engine: Engine,
    metrics: Metrics,
    limits: Limits,
    *,
    max_body_bytes: int,
    ui: bool,
    max_in_flight: int,
    temporal: TemporalModels | None = None,
) -> FastAPI:
    """The FastAPI app; it shares `engine` (and so the onnxruntime session) with the gRPC server.
    `ui`: also serve the web page at GET / (service/page.py). Beyond `max_in_flight` POST /lift
    requests in progress, the next is answered 503 at once."""
    info = engine.lifter.info
    app = FastAPI(
        title="RepNet pose lifting",
        version="1.0.0",
        description="Lifts 2D human keypoints to a 3D pose and a weak-perspective camera "
        "(RepNet, Wandt & Rosenhahn, CVPR 2019).\n\n" + FRAME_DOC,
    )
    app.add_middleware(BodyLimitMiddleware, max_bytes=max_body_bytes, metrics=metrics)
    app.add_middleware(LoadShedMiddleware, max_in_flight=max_in_flight)  # counted by the metrics
    app.add_middleware(LiftMetricsMiddleware, metrics=metrics)  # added last: outermost

    add_error_handlers(app, metrics)

    @app.post("/lift", response_model=LiftResponse, responses=ERRORS, summary="Lift 2D poses to 3D")
    async def lift(request: LiftRequest, http: Request) -> Response:
        """Lift one pose or a batch: each reply has the 3D pose, camera and reprojection."""
        count = len(request.poses)
        started = getattr(http.state, STARTED_KEY, None)  # since the body arrived
        if request.temporal != "off":

            def read(i: int) -> PoseInput:
                return to_pose_input(request.poses[i], request, i)

            body = await lift_temporal(request, engine, temporal, limits, metrics, started, read)
            return LiftJSONResponse(body)
        with metrics.parsing("http", started):
            inputs = await offload(count, _prepare, request, limits)
        prediction = await engine.lift_async(inputs, "http")
        return await offload(count, reply_of, info, inputs, prediction, request)

    @app.get("/healthz", summary="The process is up")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get(
        "/readyz",
        summary="The model is loaded and the server accepts work",
        responses={503: {"model": ErrorResponse}},
    )
    async def readyz() -> Response:
        if not engine.ready:
            return JSONResponse({"detail": "shutting down"}, status_code=503)
        return JSONResponse({"status": "ready", "model_id": info.model_id})

    @app.get("/v1/model", response_model=ModelDescription, summary="Model, joints, formats and limits")
    async def model() -> ModelDescription:
        return describe_model(info, limits, engine, max_body_bytes, temporal)

    @app.get("/metrics", summary="Prometheus metrics", response_class=Response)
    async def prometheus() -> Response:
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    if ui:
        add_page(app)
    return app
