"""HTTP adapter: create_app(models, metrics, limits) with /lift, health, model info and /metrics."""

from __future__ import annotations

import logging
from collections.abc import Hashable
from functools import partial
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.middleware.trustedhost import TrustedHostMiddleware

from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.formats import FORMATS
from repnet.core.inputs import Limits, PoseInput
from repnet.core.keypoints import read_request
from repnet.core.report import REPORT, Readable, outcome
from repnet.core.version import VERSION
from repnet.runtime.batcher import offload
from repnet.runtime.batchers import LiftBatcher
from repnet.runtime.catalog import Catalog
from repnet.runtime.lifter import ModelInfo
from repnet.runtime.pipeline import Job, Lifted
from repnet.runtime.plans import TemporalModels
from repnet.server.auth import ApiKeys
from repnet.server.http.api_docs import add_docs
from repnet.server.http.body import LargeBodies, off_loop_route, replies_json
from repnet.server.http.errors import add_error_handlers
from repnet.server.http.middleware import (
    STARTED_KEY,
    ApiKeyMiddleware,
    BodyLimitMiddleware,
    LiftMetricsMiddleware,
    LoadShedMiddleware,
    SecurityHeadersMiddleware,
)
from repnet.server.http.model_routes import add_model_routes
from repnet.server.http.page import add_page
from repnet.server.http.report import read_poses, report_json
from repnet.server.http.responses import ErrorResponse, LiftResponse
from repnet.server.http.schemas import FRAME_DOC, LiftRequest, PoseIn
from repnet.server.http.temporal import lift_temporal
from repnet.server.metrics import Metrics

log = logging.getLogger(__name__)

ERRORS: dict[int | str, dict[str, Any]] = {
    400: {
        "model": ErrorResponse,
        "description": "The body is not UTF-8 JSON, is nested too deeply, or has a number of "
        "thousands of digits.",
    },
    401: {"model": ErrorResponse, "description": "No valid API key (only when REPNET_API_KEYS_FILE is set)."},
    413: {"model": ErrorResponse, "description": "The body is larger than the limit."},
    422: {"model": ErrorResponse, "description": "A field breaks an input rule; `detail` names it."},
    503: {"model": ErrorResponse, "description": "Queue full or shutting down; retry later."},
}


def peer_of(http: Request) -> Hashable:
    """Who sent a request, for the batch queue's fair share: its connection (address and port)."""
    client = http.client
    return ("http", client.host, client.port) if client is not None else None


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
    height = request.person_height_m if pose.person_height_m is None else pose.person_height_m
    width = next((len(p) for p in pose.keypoints if p is not None), 2)  # every row has it (PoseIn)
    present = np.array([p is not None for p in pose.keypoints], dtype=bool)
    blank = (np.nan,) * width
    rows = np.array([p if p is not None else blank for p in pose.keypoints], dtype=np.float64)
    rows = rows.reshape(-1, width)  # (K, width)
    confidence = None if pose.confidence is None else np.array(pose.confidence, dtype=np.float64)
    if width == 2 and size is None:
        return PoseInput(rows, present, confidence, fmt, intrinsics, person_height_m=height)
    if found := _layout_violations(pose, width, fmt, size, index):
        raise InvalidKeypoints(found)
    points = rows[:, :2] if size is None else rows[:, :2] * np.asarray(size)  # (K, 2) px
    if width >= 3:  # a missing joint's confidence is never read: 0 keeps the range check quiet
        confidence = np.where(present, rows[:, width - 1], 0.0)
    return PoseInput(points, present, confidence, fmt, intrinsics, person_height_m=height)


def _read(request: LiftRequest, limits: Limits) -> list[PoseInput]:
    poses, threshold = request.poses, request.confidence_threshold
    return read_request(len(poses), lambda i: to_pose_input(poses[i], request, i), threshold, limits)


def _report_body(info: ModelInfo, metrics: Metrics, count: int, readable: Readable, lifted: Lifted) -> bytes:
    """The 200 answer's JSON of an `invalid_poses: report` request (on the batcher's thread): the
    lifted poses' replies, null and errors for the others (counted as rejected input, once per
    reason, as a refused request is); ModelOutputError when the model failed on any pose."""
    assert lifted.replies is not None  # the job asks for them
    head = {"model_id": info.model_id, "joints": list(info.joint_names)}
    result = outcome(count, readable, lifted.prepared)
    metrics.reject("http", result.errors)
    return report_json(head, lifted.replies.check(), result)


def _body(info: ModelInfo, lifted: Lifted) -> bytes:
    """The 200 answer's JSON (on the batcher's thread); InvalidKeypoints naming every pose that
    breaks a rule, ModelOutputError when the model failed on any pose."""
    lifted.prepared.check()
    assert lifted.replies is not None  # the job asks for them
    head = {"model_id": info.model_id, "joints": list(info.joint_names)}
    return replies_json(head, lifted.replies.check())


def add_middleware(
    app: FastAPI,
    metrics: Metrics,
    *,
    max_body_bytes: int,
    max_in_flight: int,
    api_keys: ApiKeys | None,
    allowed_hosts: list[str] | None,
    large: LargeBodies | None = None,
) -> None:
    """The middleware around every route, outermost first: the Host allow-list (None: any), reply
    headers, /lift metrics, API keys, the body limit (while the body is read), the in-flight bound
    (once the body arrived; a large body that `large` has no room for is refused before it is read)."""
    # Each add wraps the ones before: the last added runs first.
    app.add_middleware(LoadShedMiddleware, max_in_flight=max_in_flight, large=large)  # counted by the metrics
    app.add_middleware(BodyLimitMiddleware, max_bytes=max_body_bytes, metrics=metrics)
    if api_keys is not None:
        app.add_middleware(ApiKeyMiddleware, keys=api_keys)
    app.add_middleware(LiftMetricsMiddleware, metrics=metrics)
    app.add_middleware(SecurityHeadersMiddleware)
    if allowed_hosts is not None:  # Starlette's check (IPv6 literals and ports parsed), no redirects
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts, www_redirect=False)


def create_app(
    engine: LiftBatcher | Catalog,
    metrics: Metrics,
    limits: Limits,
    *,
    max_body_bytes: int,
    ui: bool,
    max_in_flight: int,
    api_keys: ApiKeys | None = None,
    temporal: TemporalModels | None = None,
    allowed_hosts: list[str] | None = None,
) -> FastAPI:
    """The FastAPI app; it shares `engine` (one model's batcher, or a Catalog of several: a
    request's `model` picks one) with the gRPC server, and so the onnxruntime sessions. `ui`: also
    serve the web page at GET / (service/page.py). Beyond `max_in_flight` POST /lift
    requests in progress, the next is answered 503 at once. `api_keys`: POST /lift and /v1/* need
    one of them (None: open). `allowed_hosts`: the Host names answered (None: any)."""
    models = Catalog.of(engine, temporal is not None)
    large = LargeBodies(waiting=2)  # POST /lift bodies over OFF_LOOP_BYTES: one at a time
    app = FastAPI(
        title="RepNet pose lifting",
        version=VERSION,  # the package's
        description="Lifts 2D human keypoints to a 3D pose and a weak-perspective camera "
        "(RepNet, Wandt & Rosenhahn, CVPR 2019).\n\n" + FRAME_DOC,
        # Starlette would answer /lift/ with a redirect to an absolute URL built from the request's
        # Host header (an open redirect behind a proxy that passes Host on): /lift/ is a 404.
        redirect_slashes=False,
        docs_url=None,  # add_docs: Swagger UI from this package, not a CDN
        redoc_url=None,
    )
    add_middleware(
        app,
        metrics,
        max_body_bytes=max_body_bytes,
        max_in_flight=max_in_flight,
        api_keys=api_keys,
        allowed_hosts=allowed_hosts,
        large=large,
    )
    add_error_handlers(app, metrics)

    async def lift(request: LiftRequest, http: Request) -> Response:
        """Lift one pose or a batch: each reply has the 3D pose, camera and reprojection."""
        count = len(request.poses)
        started = getattr(http.state, STARTED_KEY, None)  # since the body arrived
        engine = models.pick(request.model, temporal=request.temporal != "off")
        source = peer_of(http)  # the batch queue is shared fairly between connections

        def read(i: int) -> PoseInput:
            return to_pose_input(request.poses[i], request, i)

        if request.temporal != "off":
            body = await lift_temporal(request, engine, temporal, limits, metrics, started, read, source)
            return Response(body, media_type="application/json")
        if request.invalid_poses == REPORT:
            with metrics.parsing("http", started):
                readable = await offload(count, read_poses, request, limits, read)
            report = Job(
                finish=partial(_report_body, engine.lifter.info, metrics, count, readable),
                poses=readable.poses,
                threshold=request.confidence_threshold,
                track_ids=[request.poses[i].track_id for i in readable.positions],
            )
            answer = await engine.run_async(report, "http", source=source)
            return Response(answer, media_type="application/json")
        with metrics.parsing("http", started):
            poses = await offload(count, _read, request, limits)
        job = Job(
            finish=partial(_body, engine.lifter.info),
            poses=poses,
            threshold=request.confidence_threshold,
            track_ids=[p.track_id for p in request.poses],
        )
        return Response(await engine.run_async(job, "http", source=source), media_type="application/json")

    # A large body is decoded and validated on a worker thread, and its request handled, one at a
    # time per worker; two more wait, and beyond a large request gets 503 (server.http.body)
    app.router.add_api_route(
        "/lift",
        lift,
        methods=["POST"],
        response_model=LiftResponse,
        responses=ERRORS,
        summary="Lift 2D poses to 3D",
        route_class_override=off_loop_route(LiftRequest, large),
    )

    @app.get("/healthz", summary="The process is up")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get(
        "/readyz",
        summary="The model is loaded and the server accepts work",
        responses={503: {"model": ErrorResponse}},
    )
    async def readyz() -> Response:
        if not models.ready:
            return JSONResponse({"detail": "shutting down"}, status_code=503)
        return JSONResponse({"status": "ready", "model_id": models.default})

    # HEAD: 200 without a body (uvicorn writes none for HEAD)
    app.add_api_route("/healthz", healthz, methods=["HEAD"], include_in_schema=False)
    app.add_api_route("/readyz", readyz, methods=["HEAD"], include_in_schema=False)

    add_model_routes(app, models, limits, max_body_bytes, temporal, {422: ERRORS[422]})

    @app.get("/metrics", summary="Prometheus metrics", response_class=Response)
    async def prometheus() -> Response:
        return Response(generate_latest(metrics.scraped()), media_type=CONTENT_TYPE_LATEST)

    add_docs(app)
    if ui:
        add_page(app)
    return app
