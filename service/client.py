"""Python HTTP clients of the lifting service (sync and async, httpx) and their result types."""

from __future__ import annotations

import asyncio
import ssl
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]
ArrayLike = npt.ArrayLike

DEFAULT_URL = "http://localhost:8000"
DEFAULT_BATCH = 256  # poses per request; the server's default limit is 1024


class LiftClientError(Exception):
    """The service refused a request or could not be reached.

    `status`: the HTTP status (int) or gRPC status name (str); None when no answer came.
    `details`: the server's per-field items (field, reason, code, ...) for rejected input.
    """

    def __init__(self, message: str, status: int | str | None = None, details: Sequence[dict[str, Any]] = ()):
        super().__init__(message if status is None else f"{status}: {message}")
        self.message = message
        self.status = status
        self.details = tuple(details)


# The per-pose shapes of the float matrices of a reply (-1: one row per model joint); the reply's
# fields are declared in service/replies.py, and tests/service/test_replies.py checks these against it.
_SHAPES = {"pose_3d": (-1, 3), "pose_3d_camera": (-1, 3), "camera": (2, 3), "rotation": (3, 3),
           "reprojection": (-1, 2)}  # fmt: skip


@dataclass(frozen=True)
class LiftResult:
    """One lifted pose; joint arrays follow `joints` (the model's 17 joints)."""

    pose_3d: FloatArray  # (17, 3) mm, pelvis at origin, template frame
    pose_3d_camera: FloatArray  # (17, 3) mm, rotated into the camera's orientation
    camera: FloatArray  # (2, 3) weak-perspective K
    scale: float
    rotation: FloatArray  # (3, 3)
    reprojection: FloatArray  # (17, 2) px in the input image
    reprojection_error_px: float
    visible: BoolArray  # (17,) the model saw the joint
    imputed: BoolArray  # (17,) no visible source: the model filled it in
    derived: BoolArray  # (17,) midpoint of two detector joints
    joints: tuple[str, ...]
    model_id: str
    plausibility: float | None = None  # in [0, 1]; None when the model has no plausibility output
    warnings: tuple[str, ...] = ()  # why the answer may be wrong, e.g. the format looks mistaken
    temporal: bool = False  # a temporal model answered (a tracked pose)
    track_id: str | None = None  # the pose's track; None for an untracked pose

    @classmethod
    def pose_fields(cls) -> tuple[str, ...]:
        """The names of the reply's fields a LiftResult carries, in reply order (not joints, model_id)."""
        return tuple(f.name for f in fields(cls) if f.name not in ("joints", "model_id"))

    @classmethod
    def from_fields(cls, get: Callable[[str], Any], joints: Sequence[str], model_id: str) -> LiftResult:
        """Build from one pose of an answer: `get(name)` gives a field as JSON lists (HTTP) or a
        flat repeated field (gRPC)."""
        arrays: dict[str, Any] = {k: np.asarray(get(k), np.float32).reshape(s) for k, s in _SHAPES.items()}
        flags: dict[str, Any] = {k: np.asarray(get(k), bool) for k in ("visible", "imputed", "derived")}
        try:
            plausibility = get("plausibility")
        except KeyError:  # a server from before the field: the same as a model without the output
            plausibility = None
        warnings, temporal, track_id = (_optional(get, name) for name in ("warnings", "temporal", "track_id"))
        return cls(**arrays, **flags, scale=float(get("scale")), joints=tuple(joints), model_id=model_id,
                   reprojection_error_px=float(get("reprojection_error_px")),
                   plausibility=None if plausibility is None else float(plausibility),
                   warnings=tuple(str(w) for w in warnings or ()), temporal=bool(temporal),
                   track_id=str(track_id) if track_id else None)  # fmt: skip


def _optional(get: Callable[[str], Any], name: str) -> Any:
    """A field a server from before it does not send (KeyError): None."""
    try:
        return get(name)
    except KeyError:
        return None


def as_poses(
    keypoints: ArrayLike, confidence: ArrayLike | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, J, 2) float points (NaN = missing joint) and (N, J) confidence or None."""
    points = np.asarray(keypoints, dtype=np.float64)
    if points.ndim != 3 or points.shape[-1] != 2:
        raise ValueError(f"expected keypoints of shape (N, J, 2), got {points.shape}")
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    if conf is not None and conf.shape != points.shape[:2]:
        raise ValueError(f"expected confidence of shape {points.shape[:2]}, got {conf.shape}")
    return points, conf


def build_request(points: np.ndarray, conf: np.ndarray | None, format: str,
                  confidence_threshold: float | None = None,
                  intrinsics: Sequence[float] | None = None) -> dict[str, Any]:  # fmt: skip
    """The POST /lift body for (N, J, 2) points; a joint with a NaN coordinate becomes null.
    intrinsics: (fx, fy, cx, cy) px of the camera, for every pose of the body."""
    poses = []
    for i, pose in enumerate(points):
        item: dict[str, Any] = {"keypoints": [None if np.isnan(p).any() else p.tolist() for p in pose]}
        if conf is not None:
            item["confidence"] = conf[i].tolist()
        poses.append(item)
    body: dict[str, Any] = {"format": format, "poses": poses}
    if confidence_threshold is not None:
        body["confidence_threshold"] = confidence_threshold
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        body["intrinsics"] = {"focal_px": [fx, fy], "principal_point_px": [cx, cy]}
    return body


def http_error(response: httpx.Response) -> LiftClientError:
    """The server's error answer as a LiftClientError with its message and field details."""
    try:
        detail = response.json().get("detail", response.text)
    except ValueError:
        detail = response.text or response.reason_phrase
    if isinstance(detail, list):
        items = [d for d in detail if isinstance(d, dict)]
        message = "; ".join(str(d.get("message") or d.get("reason") or d) for d in items) or str(detail)
        return LiftClientError(message, response.status_code, items)
    return LiftClientError(str(detail), response.status_code)


def parse_response(response: httpx.Response) -> list[LiftResult]:
    """The results of a POST /lift answer, or LiftClientError with the server's message."""
    if response.status_code != 200:
        raise http_error(response)
    body = response.json()
    return [LiftResult.from_fields(p.__getitem__, body["joints"], body["model_id"]) for p in body["poses"]]


def connection_options(api_key: str | None, ca_file: str | Path | None) -> dict[str, Any]:
    """httpx client arguments: the API key as `Authorization: Bearer KEY` on every request, and the
    CA certificates (PEM) that an https:// server's certificate must chain to (None: the system's)."""
    options: dict[str, Any] = {}
    if api_key is not None:
        options["headers"] = {"authorization": f"Bearer {api_key}"}
    if ca_file is not None:
        options["verify"] = ssl.create_default_context(cafile=str(ca_file))
    return options


class _HttpBase:
    """Settings and request building shared by the sync and async clients."""

    def __init__(self, url: str, timeout: float, retries: int, backoff: float, batch_size: int) -> None:
        self.url, self.timeout, self.retries, self.backoff = url, timeout, retries, backoff
        self.batch_size = batch_size

    def _bodies(self, keypoints: ArrayLike, format: str, confidence: ArrayLike | None,
                confidence_threshold: float | None,
                intrinsics: Sequence[float] | None) -> list[dict[str, Any]]:  # fmt: skip
        points, conf = as_poses(keypoints, confidence)
        parts = [slice(a, a + self.batch_size) for a in range(0, len(points), self.batch_size)]
        return [build_request(points[p], None if conf is None else conf[p], format, confidence_threshold,
                              intrinsics)
                for p in parts]  # fmt: skip

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


class LiftClient(_HttpBase):
    """Synchronous HTTP client: `LiftClient(url).lift(keypoints, format="coco17")`.

    503 answers (queue full, model not ready) and refused connections are retried `retries` times
    with exponential backoff; every other failure raises LiftClientError at once. `api_key`: sent as
    a bearer token (a server with REPNET_API_KEYS_FILE); `ca_file`: the CA of an https:// server.
    """

    def __init__(self, url: str = DEFAULT_URL, *, timeout: float = 10.0, retries: int = 3,
                 backoff: float = 0.1, batch_size: int = DEFAULT_BATCH,
                 transport: httpx.BaseTransport | None = None, api_key: str | None = None,
                 ca_file: str | Path | None = None) -> None:  # fmt: skip
        super().__init__(url, timeout, retries, backoff, batch_size)
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
            return self._http.request(method, path, json=body)
        except httpx.HTTPError as err:
            return err

    def lift(self, keypoints: ArrayLike, *, format: str = "h36m17", confidence: ArrayLike | None = None,
             confidence_threshold: float | None = None,
             intrinsics: Sequence[float] | None = None) -> LiftResult:  # fmt: skip
        """Lift one (J, 2) pose; NaN marks a missing joint, `confidence` is (J,) in [0, 1];
        `intrinsics` (fx, fy, cx, cy) px, if known, turn pose_3d_camera along the ray to the person."""
        conf = None if confidence is None else np.asarray(confidence)[None]
        return self.lift_batch(np.asarray(keypoints)[None], format=format, confidence=conf,
                               confidence_threshold=confidence_threshold,
                               intrinsics=intrinsics)[0]  # fmt: skip

    def lift_batch(self, keypoints: ArrayLike, *, format: str = "h36m17", confidence: ArrayLike | None = None,
                   confidence_threshold: float | None = None,
                   intrinsics: Sequence[float] | None = None) -> list[LiftResult]:  # fmt: skip
        """Lift (N, J, 2) poses in requests of at most `batch_size`; results in input order."""
        bodies = self._bodies(keypoints, format, confidence, confidence_threshold, intrinsics)
        return [r for body in bodies for r in parse_response(self._send("POST", "/lift", body))]

    def model(self) -> dict[str, Any]:
        """GET /v1/model: joints, formats, limits and the model's metadata."""
        response = self._send("GET", "/v1/model")
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


class AsyncLiftClient(_HttpBase):
    """The asyncio twin of LiftClient: `await client.lift(...)`; batches run concurrently."""

    def __init__(self, url: str = DEFAULT_URL, *, timeout: float = 10.0, retries: int = 3,
                 backoff: float = 0.1, batch_size: int = DEFAULT_BATCH, max_concurrency: int = 8,
                 transport: httpx.AsyncBaseTransport | None = None, api_key: str | None = None,
                 ca_file: str | Path | None = None) -> None:  # fmt: skip
        super().__init__(url, timeout, retries, backoff, batch_size)
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
            return await self._http.request(method, path, json=body)
        except httpx.HTTPError as err:
            return err

    async def lift(self, keypoints: ArrayLike, *, format: str = "h36m17", confidence: ArrayLike | None = None,
                   confidence_threshold: float | None = None,
                   intrinsics: Sequence[float] | None = None) -> LiftResult:  # fmt: skip
        """Lift one (J, 2) pose; see LiftClient.lift."""
        conf = None if confidence is None else np.asarray(confidence)[None]
        results = await self.lift_batch(np.asarray(keypoints)[None], format=format, confidence=conf,
                                        confidence_threshold=confidence_threshold,
                                        intrinsics=intrinsics)  # fmt: skip
        return results[0]

    async def lift_batch(self, keypoints: ArrayLike, *, format: str = "h36m17",
                         confidence: ArrayLike | None = None,
                         confidence_threshold: float | None = None,
                         intrinsics: Sequence[float] | None = None) -> list[LiftResult]:  # fmt: skip
        """Lift (N, J, 2) poses in requests of at most `batch_size`, `max_concurrency` at a time."""
        bodies = self._bodies(keypoints, format, confidence, confidence_threshold, intrinsics)
        slots = asyncio.Semaphore(self.max_concurrency)

        async def post(body: dict[str, Any]) -> httpx.Response:
            async with slots:
                return await self._send("POST", "/lift", body)

        responses = await asyncio.gather(*(post(b) for b in bodies))
        return [r for response in responses for r in parse_response(response)]
