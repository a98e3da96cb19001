"""The HTTP clients' POST /lift bodies: the poses with their tracks, how a batch or a temporal clip is
cut into requests (repnet.client.chunks), and the answers read back."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np

from repnet.client.chunks import Part, split_clip
from repnet.client.result import ArrayLike, LiftClientError, LiftResult
from repnet.core.contract import ENVELOPE_BYTES, TEMPORAL_MODES, Contract

Intrinsics = tuple[float, float, float, float]


@dataclass(frozen=True)
class Tracking:
    """How the poses of a batch are lifted: `temporal` off (each alone), causal or offline (each
    tracked pose from its track's frames), with the tracks' frame rate, and per pose its track
    (None: untracked) and frame number."""

    temporal: str = "off"
    fps: float | None = None
    track_ids: tuple[str | None, ...] | None = None  # (N,)
    frames: np.ndarray | None = None  # (N,) int >= 0

    @classmethod
    def of(
        cls,
        count: int,
        temporal: str,
        fps: float | None,
        track_ids: Sequence[str | None] | None,
        frames: ArrayLike | None,
    ) -> Tracking:
        """The tracking of `count` poses, checked: ValueError on a misuse the service could not judge."""
        if temporal not in TEMPORAL_MODES:
            raise ValueError(f"temporal must be one of {', '.join(TEMPORAL_MODES)}, got {temporal!r}")
        ids = None if track_ids is None else tuple(None if t is None else str(t) for t in track_ids)
        numbers = None if frames is None else np.asarray(frames)
        if ids is not None and len(ids) != count:
            raise ValueError(f"expected {count} track_ids, one per pose, got {len(ids)}")
        if numbers is not None and (numbers.shape != (count,) or (count and numbers.dtype.kind not in "iu")):
            raise ValueError(
                f"expected frames of shape ({count},) of integers, got {numbers.dtype} {numbers.shape}"
            )
        if temporal != "off" and (fps is None or ids is None or numbers is None):
            raise ValueError(f"temporal {temporal} needs fps, track_ids and frames")
        return cls(temporal, None if fps is None else float(fps), ids, numbers)

    def extra(self) -> dict[str, Any]:
        """The body's own fields for these poses."""
        body: dict[str, Any] = {} if self.temporal == "off" else {"temporal": self.temporal}
        if self.fps is not None:
            body["fps"] = self.fps
        return body

    def of_pose(self, i: int) -> dict[str, Any]:
        """Pose i's track fields."""
        item: dict[str, Any] = {}
        if self.track_ids is not None and self.track_ids[i] is not None:
            item["track_id"] = self.track_ids[i]
        if self.frames is not None:
            item["frame"] = int(self.frames[i])
        return item


def pose_item(points: np.ndarray, conf: np.ndarray | None) -> dict[str, Any]:
    """One (J, 2) pose of a body; a joint with a NaN coordinate becomes null."""
    item: dict[str, Any] = {"keypoints": [None if np.isnan(p).any() else p.tolist() for p in points]}
    if conf is not None:
        item["confidence"] = conf.tolist()
    return item


def build_request(
    points: np.ndarray,
    conf: np.ndarray | None,
    format: str,
    confidence_threshold: float | None = None,
    intrinsics: Sequence[float] | None = None,
    tracking: Tracking | None = None,
    send: np.ndarray | None = None,
    person_height_m: float | None = None,
) -> dict[str, Any]:
    """The POST /lift body for (N, J, 2) points (those at `send` of them, when given).
    intrinsics: (fx, fy, cx, cy) px of the camera, for every pose of the body; person_height_m: the
    person's skeleton height in metres, for every pose."""
    rows = np.arange(len(points)) if send is None else send
    poses = []
    for i in rows.tolist():
        item = pose_item(points[i], None if conf is None else conf[i])
        poses.append(item if tracking is None else {**item, **tracking.of_pose(i)})
    body: dict[str, Any] = {"format": format, "poses": poses}
    if confidence_threshold is not None:
        body["confidence_threshold"] = confidence_threshold
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        body["intrinsics"] = {"focal_px": [fx, fy], "principal_point_px": [cx, cy]}
    if person_height_m is not None:
        body["person_height_m"] = float(person_height_m)
    return body if tracking is None else {**body, **tracking.extra()}


@dataclass(frozen=True)
class Batch:
    """The poses of one lift_batch call and what is sent with them (HTTP, or --local)."""

    points: np.ndarray  # (N, J, 2) px, NaN for a missing joint
    conf: np.ndarray | None  # (N, J)
    format: str
    threshold: float | None
    intrinsics: Intrinsics | None  # (fx, fy, cx, cy) px
    tracking: Tracking
    person_height_m: float | None = None  # the person's skeleton height, m
    invalid_poses: str = "refuse"  # "report": lift_each's requests

    def body(self, part: Part) -> dict[str, Any]:
        """The POST /lift body of the poses of `part`."""
        body = build_request(
            self.points,
            self.conf,
            self.format,
            self.threshold,
            self.intrinsics,
            self.tracking,
            part.send,
            self.person_height_m,
        )
        return body if self.invalid_poses == "refuse" else {**body, "invalid_poses": self.invalid_poses}


def as_intrinsics(values: Sequence[float] | None) -> Intrinsics | None:
    """(fx, fy, cx, cy) as floats; ValueError unless four."""
    if values is None:
        return None
    fx, fy, cx, cy = (float(v) for v in values)
    return (fx, fy, cx, cy)


def contract_of(model: dict[str, Any], mode: str) -> Contract:
    """The contract of the service's `mode` temporal model, from GET /v1/model; LiftClientError
    (422, as the service would answer) when it has none."""
    for entry in model.get("temporal") or ():
        if entry.get("mode") == mode:
            return Contract(mode, float(entry["grid_fps"]), int(entry["window"]), float(entry["max_fps"]))
    reason = f"this service has no {mode} temporal model (GET /v1/model lists none); send temporal off"
    raise LiftClientError(reason, 422, [{"field": "temporal", "reason": reason, "code": "no_temporal_model"}])


def temporal_parts(
    points: np.ndarray, conf: np.ndarray | None, tracking: Tracking, model: dict[str, Any]
) -> list[Part]:
    """The requests of a temporal batch within the service's limits (GET /v1/model `model`):
    max_temporal_poses poses and max_body_bytes bytes each, a cut track sent with the context its
    model reads (repnet.client.chunks); LiftClientError when that cannot be."""
    contract = contract_of(model, tracking.temporal)
    limits = model["limits"]
    widest = max(
        len(json.dumps({**pose_item(p, None if conf is None else conf[i]), **tracking.of_pose(i)}))
        for i, p in enumerate(points)
    )
    by_bytes = (int(limits["max_body_bytes"]) - ENVELOPE_BYTES) // (widest + 2)
    most = min(int(limits.get("max_temporal_poses") or 0), by_bytes)
    track_ids = tracking.track_ids or (None,) * len(points)
    frames = tracking.frames if tracking.frames is not None else np.zeros(len(points), np.int64)
    try:
        return split_clip(track_ids, frames, contract.reach(float(tracking.fps or 0.0)), most)
    except ValueError as err:
        raise LiftClientError(f"{err} (max_body_bytes {limits['max_body_bytes']})", 413) from err


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


def parse_response(response: httpx.Response, part: Part | None = None) -> list[LiftResult]:
    """The results of a POST /lift answer, or LiftClientError with the server's message (its pose
    indices those of the caller's batch when the request held the poses of `part`)."""
    results = parse_each(response, part)
    if errors := [r for r in results if isinstance(r, LiftClientError)]:  # not asked for: refuse
        raise errors[0]
    return [r for r in results if isinstance(r, LiftResult)]


def parse_each(response: httpx.Response, part: Part | None = None) -> list[LiftResult | LiftClientError]:
    """parse_response's, where a pose not lifted (`invalid_poses: report`) is its own
    LiftClientError (status 422) with its errors, renumbered as parse_response renumbers."""
    if response.status_code != 200:
        error = http_error(response)
        raise error if part is None else error.renumbered(part.send.tolist())
    body = response.json()
    by_pose: dict[int, list[dict[str, Any]]] = {}
    for item in body.get("errors") or ():
        by_pose.setdefault(int(item.get("pose") or 0), []).append(item)
    results: list[LiftResult | LiftClientError] = []
    for i, pose in enumerate(body["poses"]):
        if pose is not None:
            results.append(LiftResult.from_fields(pose.__getitem__, body["joints"], body["model_id"]))
            continue
        items = by_pose.get(i, [])
        error = LiftClientError("; ".join(str(d.get("message")) for d in items) or "not lifted", 422, items)
        results.append(error if part is None else error.renumbered(part.send.tolist()))
    return results
