"""Python HTTP clients of the lifting service (sync and async, httpx) and their result types."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from repnet.client.body import (
    Batch,
    build_request,
    http_error,
    parse_each,
    parse_response,
)
from repnet.client.chunks import Part, Progress, assemble, lift_parts
from repnet.client.connection import DEFAULT_BATCH, DEFAULT_URL, HttpBase, connection_options, json_body
from repnet.client.result import (
    ArrayLike,
    BoolArray,
    FloatArray,
    LiftClientError,
    LiftResult,
    as_poses,
)
from repnet.core.formats import DEFAULT_FORMAT

__all__ = [
    "ArrayLike",
    "AsyncLiftClient",
    "BoolArray",
    "FloatArray",
    "LiftClient",
    "LiftClientError",
    "LiftResult",
    "as_poses",
    "build_request",
    "http_error",
    "parse_response",
]


class LiftClient(HttpBase):
    """Synchronous HTTP client: `LiftClient(url).lift(keypoints, format="coco17")`.

    503 answers (queue full, model not ready) and refused connections are retried `retries` times
    with exponential backoff; every other failure raises LiftClientError at once. `api_key`: sent as
    a bearer token (a server with REPNET_API_KEYS_FILE); `ca_file`: the CA of an https:// server;
    `model`: the model_id every request names (GET /v1/models; None: the service's default).
    """

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        timeout: float = 10.0,
        retries: int = 3,
        backoff: float = 0.1,
        batch_size: int = DEFAULT_BATCH,
        transport: httpx.BaseTransport | None = None,
        api_key: str | None = None,
        ca_file: str | Path | None = None,
        model: str | None = None,
    ) -> None:
        super().__init__(url, timeout, retries, backoff, batch_size, model)
        options = connection_options(api_key, ca_file)
        self._http = httpx.Client(base_url=url, timeout=timeout, transport=transport, **options)

    def __enter__(self) -> LiftClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the HTTP connections."""
        self._http.close()

    def _send(self, method: str, path: str, body: dict[str, Any] | None = None) -> httpx.Response:
        attempt = 0
        while True:
            outcome = self._next(self._try(method, path, body), method, path, attempt)
            if isinstance(outcome, httpx.Response):
                return outcome
            time.sleep(outcome)
            attempt += 1

    def _try(self, method: str, path: str, body: dict[str, Any] | None) -> httpx.Response | httpx.HTTPError:
        try:
            return self._http.request(method, path, **json_body(body))
        except httpx.HTTPError as err:
            return err

    def lift(
        self,
        keypoints: ArrayLike,
        *,
        format: str = DEFAULT_FORMAT,
        confidence: ArrayLike | None = None,
        confidence_threshold: float | None = None,
        intrinsics: Sequence[float] | None = None,
        person_height_m: float | None = None,
    ) -> LiftResult:
        """Lift one (J, 2) pose; NaN marks a missing joint, `confidence` is (J,) in [0, 1];
        `intrinsics` (fx, fy, cx, cy) px, if known, turn pose_3d_camera along the ray to the person
        and give root_camera_m, its depth from `person_height_m` (skeleton height, m) if given."""
        conf = None if confidence is None else np.asarray(confidence)[None]
        return self.lift_batch(
            np.asarray(keypoints)[None],
            format=format,
            confidence=conf,
            confidence_threshold=confidence_threshold,
            intrinsics=intrinsics,
            person_height_m=person_height_m,
        )[0]

    def lift_batch(
        self,
        keypoints: ArrayLike,
        *,
        format: str = DEFAULT_FORMAT,
        confidence: ArrayLike | None = None,
        confidence_threshold: float | None = None,
        intrinsics: Sequence[float] | None = None,
        temporal: str = "off",
        fps: float | None = None,
        track_ids: Sequence[str | None] | None = None,
        frames: ArrayLike | None = None,
        progress: Progress | None = None,
        person_height_m: float | None = None,
    ) -> list[LiftResult]:
        """Lift (N, J, 2) poses in requests of at most `batch_size`; results in input order.

        temporal -- "off" (each pose alone), "causal" or "offline": each tracked pose is lifted from
        its track's frames (up to it, or around it) at `fps`; track_ids (N,) gives each pose's track
        (None: lifted alone) and frames (N,) their frame numbers. A clip of more poses than the
        service's max_temporal_poses (GET /v1/model) is sent as overlapping requests, each with the
        frames its windows read, answered as one request would be (repnet.client.chunks).
        progress(n) -- told after each request how many poses it answered.
        """
        batch = self._batch(
            keypoints,
            format,
            confidence,
            confidence_threshold,
            intrinsics,
            temporal,
            fps,
            track_ids,
            frames,
            person_height_m,
        )
        return [r for r in self._lift(batch, progress) if isinstance(r, LiftResult)]  # or raised

    def lift_each(
        self, keypoints: ArrayLike, *, progress: Progress | None = None, **options: Any
    ) -> list[LiftResult | LiftClientError]:
        """lift_batch (the same options) with `invalid_poses: report`: a pose that breaks an input
        rule is not lifted and its item is a LiftClientError (status 422, `details` naming its
        fields), while the others are lifted; a refusal of a whole request still raises."""
        return self._lift(self._batch(keypoints, **options, invalid_poses="report"), progress)

    def _lift(self, batch: Batch, progress: Progress | None) -> list[LiftResult | LiftClientError]:
        temporal = batch.tracking.temporal
        parts = self._parts(batch, None if temporal == "off" else self.model())
        report = batch.invalid_poses == "report"

        def lift(part: Part) -> list[LiftResult | LiftClientError]:
            response = self._send("POST", "/lift", self._body(batch, part))
            return parse_each(response, part) if report else list(parse_response(response, part))

        return lift_parts(len(batch.points), parts, lift, progress)

    def model(self) -> dict[str, Any]:
        """GET /v1/model (of the client's model): joints, formats, limits and the model's metadata."""
        response = self._send("GET", self._model_path())
        if response.status_code != 200:
            raise http_error(response)
        result: dict[str, Any] = response.json()
        return result

    def ready(self) -> bool:
        """True when /readyz answers 200; never retries, never raises."""
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.HTTPError:
            return False


class AsyncLiftClient(HttpBase):
    """The asyncio twin of LiftClient: `await client.lift(...)`; batches run concurrently."""

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        timeout: float = 10.0,
        retries: int = 3,
        backoff: float = 0.1,
        batch_size: int = DEFAULT_BATCH,
        max_concurrency: int = 8,
        transport: httpx.AsyncBaseTransport | None = None,
        api_key: str | None = None,
        ca_file: str | Path | None = None,
        model: str | None = None,
    ) -> None:
        super().__init__(url, timeout, retries, backoff, batch_size, model)
        self.max_concurrency = max_concurrency
        options = connection_options(api_key, ca_file)
        self._http = httpx.AsyncClient(base_url=url, timeout=timeout, transport=transport, **options)

    async def __aenter__(self) -> AsyncLiftClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Close the HTTP connections."""
        await self._http.aclose()

    async def _send(self, method: str, path: str, body: dict[str, Any] | None = None) -> httpx.Response:
        attempt = 0
        while True:
            outcome = self._next(await self._try(method, path, body), method, path, attempt)
            if isinstance(outcome, httpx.Response):
                return outcome
            await asyncio.sleep(outcome)
            attempt += 1

    async def _try(
        self, method: str, path: str, body: dict[str, Any] | None
    ) -> httpx.Response | httpx.HTTPError:
        try:
            return await self._http.request(method, path, **json_body(body))
        except httpx.HTTPError as err:
            return err

    async def lift(
        self,
        keypoints: ArrayLike,
        *,
        format: str = DEFAULT_FORMAT,
        confidence: ArrayLike | None = None,
        confidence_threshold: float | None = None,
        intrinsics: Sequence[float] | None = None,
        person_height_m: float | None = None,
    ) -> LiftResult:
        """Lift one (J, 2) pose; see LiftClient.lift."""
        conf = None if confidence is None else np.asarray(confidence)[None]
        results = await self.lift_batch(
            np.asarray(keypoints)[None],
            format=format,
            confidence=conf,
            confidence_threshold=confidence_threshold,
            intrinsics=intrinsics,
            person_height_m=person_height_m,
        )
        return results[0]

    async def lift_batch(
        self,
        keypoints: ArrayLike,
        *,
        format: str = DEFAULT_FORMAT,
        confidence: ArrayLike | None = None,
        confidence_threshold: float | None = None,
        intrinsics: Sequence[float] | None = None,
        temporal: str = "off",
        fps: float | None = None,
        track_ids: Sequence[str | None] | None = None,
        frames: ArrayLike | None = None,
        progress: Progress | None = None,
        person_height_m: float | None = None,
    ) -> list[LiftResult]:
        """Lift (N, J, 2) poses in requests of at most `batch_size`, `max_concurrency` at a time;
        temporal clips as LiftClient.lift_batch sends them."""
        batch = self._batch(
            keypoints,
            format,
            confidence,
            confidence_threshold,
            intrinsics,
            temporal,
            fps,
            track_ids,
            frames,
            person_height_m,
        )
        return [r for r in await self._lift(batch, progress) if isinstance(r, LiftResult)]  # or raised

    async def lift_each(
        self, keypoints: ArrayLike, *, progress: Progress | None = None, **options: Any
    ) -> list[LiftResult | LiftClientError]:
        """LiftClient.lift_each: lift_batch with `invalid_poses: report`."""
        return await self._lift(self._batch(keypoints, **options, invalid_poses="report"), progress)

    async def _lift(self, batch: Batch, progress: Progress | None) -> list[LiftResult | LiftClientError]:
        temporal = batch.tracking.temporal
        parts = self._parts(batch, None if temporal == "off" else await self.model())
        slots = asyncio.Semaphore(self.max_concurrency)
        report = batch.invalid_poses == "report"

        async def post(part: Part) -> list[LiftResult | LiftClientError]:
            async with slots:
                response = await self._send("POST", "/lift", self._body(batch, part))
            results: list[LiftResult | LiftClientError] = (
                parse_each(response, part) if report else list(parse_response(response, part))
            )
            if progress is not None:
                progress(int(part.keep.sum()))
            return results

        answers = await asyncio.gather(*(post(p) for p in parts))
        return assemble(len(batch.points), parts, answers)

    async def model(self) -> dict[str, Any]:
        """GET /v1/model (of the client's model): joints, formats, limits, temporal models, metadata."""
        response = await self._send("GET", self._model_path())
        if response.status_code != 200:
            raise http_error(response)
        result: dict[str, Any] = response.json()
        return result
