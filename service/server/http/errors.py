"""The HTTP API's one error path: core errors, pydantic's and FastAPI's 400 as JSON error bodies."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException

from repnet.core.errors import (
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
from repnet.server.http.middleware import OUTCOME_KEY, STARTED_KEY
from repnet.server.http.schemas import DETECTOR_OUTPUT, UNKNOWN_FIELD
from repnet.server.metrics import INVALID, Metrics, outcome_of

log = logging.getLogger(__name__)


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
        codes = {"json_invalid": "malformed_json", DETECTOR_OUTPUT: DETECTOR_OUTPUT}
        code = codes.get(str(error.get("type")), "malformed")
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


def undecodable_reason(cause: BaseException | None) -> str:
    """Why json.loads failed on a body, from the exception FastAPI's 400 was raised from."""
    if isinstance(cause, UnicodeDecodeError):
        return "the body cannot be decoded as JSON: it is not valid UTF-8"
    if isinstance(cause, RecursionError):
        return "the body cannot be decoded as JSON: it is nested too deeply"
    if isinstance(cause, ValueError) and "digits" in str(cause):  # int('1' * 5000): CVE-2020-10735
        return (
            f"the body cannot be decoded as JSON: a number has more than {sys.get_int_max_str_digits()} "
            "digits; send coordinates as ordinary numbers"
        )
    return "the body cannot be decoded as JSON"


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
        violation = Violation("body", undecodable_reason(err.__cause__), "malformed_json")
        setattr(request.state, OUTCOME_KEY, INVALID)
        metrics.reject("http", [violation])
        return JSONResponse(error_body([violation]), status_code=400)
