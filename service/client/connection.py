"""What both HTTP clients share: the connection's options (API key, CA file), the retries of a refused or
failed request and the answer's parsing."""

from __future__ import annotations

import json
import ssl
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx

from repnet.client.body import (
    Batch,
    Tracking,
    as_intrinsics,
    temporal_parts,
)
from repnet.client.chunks import Part, batches
from repnet.client.result import (
    ArrayLike,
    LiftClientError,
    LiftInputError,
    as_poses,
)
from repnet.core.formats import DEFAULT_FORMAT

DEFAULT_URL = "http://localhost:8000"


DEFAULT_BATCH = 256  # poses per request; the server's default limit is 1024


def json_body(body: dict[str, Any] | None) -> dict[str, Any]:
    """httpx's request arguments for a JSON body: written by json.dumps, whose Infinity and NaN the
    service reads and judges (a field-level error naming the joint), where httpx's json= raises."""
    if body is None:
        return {}
    return {"content": json.dumps(body).encode(), "headers": {"content-type": "application/json"}}


def connection_options(api_key: str | None, ca_file: str | Path | None) -> dict[str, Any]:
    """httpx client arguments: the API key as `Authorization: Bearer KEY` on every request, and the
    CA certificates (PEM) that an https:// server's certificate must chain to (None: the system's)."""
    options: dict[str, Any] = {}
    if api_key is not None:
        options["headers"] = {"authorization": f"Bearer {api_key}"}
    if ca_file is not None:
        options["verify"] = ssl.create_default_context(cafile=str(ca_file))
    return options


class HttpBase:
    """Settings and request building shared by the sync and async clients."""

    def __init__(
        self, url: str, timeout: float, retries: int, backoff: float, batch_size: int, model: str | None
    ) -> None:
        self.url, self.timeout, self.retries, self.backoff = url, timeout, retries, backoff
        self.batch_size = batch_size
        self.model_id = model  # the model every request names (None: the service's default)

    def _body(self, batch: Batch, part: Part) -> dict[str, Any]:
        """The POST /lift body of the poses of `part`, naming the client's model."""
        body = batch.body(part)
        return body if self.model_id is None else {**body, "model": self.model_id}

    def _model_path(self) -> str:
        """GET /v1/model of the client's model."""
        return "/v1/model" if self.model_id is None else f"/v1/model?model={quote(self.model_id)}"

    def _batch(
        self,
        keypoints: ArrayLike,
        format: str = DEFAULT_FORMAT,
        confidence: ArrayLike | None = None,
        confidence_threshold: float | None = None,
        intrinsics: Sequence[float] | None = None,
        temporal: str = "off",
        fps: float | None = None,
        track_ids: Sequence[str | None] | None = None,
        frames: ArrayLike | None = None,
        person_height_m: float | None = None,
        invalid_poses: str = "refuse",
    ) -> Batch:
        points, conf = as_poses(keypoints, confidence)
        try:
            tracking = Tracking.of(len(points), temporal, fps, track_ids, frames)
            return Batch(
                points,
                conf,
                format,
                confidence_threshold,
                as_intrinsics(intrinsics),
                tracking,
                person_height_m,
                invalid_poses,
            )
        except (ValueError, TypeError) as err:  # raised before any request: as the service would
            raise LiftInputError("arguments", str(err)) from err

    def _parts(self, batch: Batch, model: dict[str, Any] | None) -> list[Part]:
        """Requests of batch_size poses, or of a temporal clip within the service's limits (`model`:
        GET /v1/model)."""
        if model is None or not len(batch.points):
            return batches(len(batch.points), self.batch_size)
        return temporal_parts(batch.points, batch.conf, batch.tracking, model)

    def _delay(self, response: httpx.Response | None, attempt: int) -> float | None:
        """Seconds before the next try (Retry-After, else exponential), None to give up."""
        if attempt >= self.retries:
            return None
        header = response.headers.get("retry-after", "") if response is not None else ""
        return min(float(header), 30.0) if header.replace(".", "", 1).isdigit() else self.backoff * 2**attempt

    def _next(
        self, outcome: httpx.Response | httpx.HTTPError, method: str, path: str, attempt: int
    ) -> httpx.Response | float:
        """The retry policy of both clients, after try `attempt` of `method path`: the response to give
        back, or the seconds to wait before the next try. 503 answers (queue full, model not ready) and
        refused connections are retried; any other failure raises LiftClientError."""
        if isinstance(outcome, httpx.Response):
            if outcome.status_code != 503 or (delay := self._delay(outcome, attempt)) is None:
                return outcome
            return delay
        if not isinstance(outcome, httpx.ConnectError):
            raise LiftClientError(f"{method} {path} failed: {outcome!r}") from outcome
        if (delay := self._delay(None, attempt)) is None:
            raise LiftClientError(f"cannot reach {self.url}: {outcome}") from outcome
        return delay
