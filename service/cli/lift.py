"""What `repnet lift` does between reading the poses and writing them out: the temporal mode and the
frame rate, the tracks, the lift (through the service or in this process), the output rows."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from repnet.cli.usable import usable_poses
from repnet.client.body import Batch, Intrinsics, Tracking
from repnet.client.chunks import Progress
from repnet.client.http import LiftClient
from repnet.client.result import LiftClientError, LiftResult
from repnet.core.contract import DEFAULT_FPS, MODES
from repnet.core.formats import FORMATS, MODEL_PARENTS
from repnet.core.inputs import Limits
from repnet.io.output import Lifted
from repnet.io.poses import Poses

Say = Callable[[str], None]


def say(message: str) -> None:
    """A note on stderr."""
    print(f"repnet: {message}", file=sys.stderr)


class LiftBackend(Protocol):
    """Where the poses are lifted: the service (RemoteBackend) or this process (LocalBackend)."""

    def temporal_modes(self) -> tuple[str, ...]:
        """The temporal modes it has a model for."""
        ...

    def lift_batch(self, batch: Batch, progress: Progress | None = None) -> list[LiftResult]:
        """The results of the batch's poses, in order."""
        ...

    def limits(self) -> Limits:
        """The input rules' limits of the poses it lifts."""
        ...


class RemoteBackend:
    """The service at `url`, through LiftClient (requests of `batch` poses; temporal ones as long
    as the service takes), with `api_key`, the CA file of an https:// service and the `model` each
    request names (None: the service's default)."""

    def __init__(
        self,
        url: str,
        timeout: float,
        batch: int,
        api_key: str | None = None,
        ca_file: Path | None = None,
        model: str | None = None,
    ) -> None:
        self.client = LiftClient(
            url, timeout=timeout, batch_size=batch, api_key=api_key, ca_file=ca_file, model=model
        )

    def temporal_modes(self) -> tuple[str, ...]:
        """The modes of the service's temporal models (GET /v1/model)."""
        return tuple(str(entry.get("mode")) for entry in self.client.model().get("temporal") or ())

    def limits(self) -> Limits:
        """The service's limits (GET /v1/model)."""
        found = self.client.model()["limits"]
        return Limits(
            max_request_poses=int(found["max_request_poses"]),
            min_visible_joints=int(found["min_visible_joints"]),
            confidence_threshold=float(found["confidence_threshold"]),
            max_coordinate=float(found["max_coordinate_px"]),
        )

    def lift_batch(self, batch: Batch, progress: Progress | None = None) -> list[LiftResult]:
        """LiftClient.lift_batch of the batch."""
        t = batch.tracking
        return self.client.lift_batch(
            batch.points,
            format=batch.format,
            confidence=batch.conf,
            confidence_threshold=batch.threshold,
            intrinsics=batch.intrinsics,
            temporal=t.temporal,
            fps=t.fps,
            track_ids=t.track_ids,
            frames=t.frames,
            progress=progress,
            person_height_m=batch.person_height_m,
        )

    def close(self) -> None:
        """Close the client's connections."""
        self.client.close()


def local_backend(model: Path | None, batch: int) -> LiftBackend:
    """A LocalBackend (imported here: it loads onnxruntime and the service's core)."""
    from repnet.cli.local import LocalBackend

    return LocalBackend(model, batch)


@dataclass(frozen=True)
class Choice:
    """How a file's poses are lifted."""

    temporal: str  # off, causal, offline
    fps: float | None  # the tracks' frame rate (None when off and the file gives none)
    stills: str | None = None  # why the frames were taken for unrelated still images; None: they were not


def stills_reason(numbered_by: str | None, frames: Sequence[int]) -> str | None:
    """Why frames numbered so are unrelated still images rather than a clip, or None for a clip: ids
    with no number, or numbers of which fewer than half follow the previous one by 1 (COCO image ids
    397133, 37777, 252219; a clip's frames step by 1 but where nobody was found). The page's
    stillsReason (static/lift.js) is this rule."""
    distinct = sorted(set(frames))
    if numbered_by is None or len(distinct) < 2:
        return None
    if numbered_by == "image names":
        return "image ids not numbered"
    steps = np.diff(distinct)
    return None if 2 * int((steps == 1).sum()) >= len(steps) else f"{numbered_by} not consecutive"


def choose(
    poses: Poses, asked: str | None, fps: float | None, modes: Callable[[], Sequence[str]], tell: Say
) -> Choice:
    """The temporal mode: `asked` (--temporal), else offline for a sequence (poses of more than one
    frame) and off for one frame or for unrelated still images (stills_reason, told, unless a frame
    rate or tracks make them a clip); a default the lifter has no model for falls back to causal,
    then off (told). The frame rate: `fps` (--fps), else the file's, else DEFAULT_FPS (told)."""
    rate = fps if fps is not None else poses.fps
    clip = asked in MODES or rate is not None or poses.track_id is not None
    stills = None if clip else stills_reason(poses.numbered_by, poses.frame.tolist())
    if stills is not None:
        count = poses.frame_count
        tell(f"{count} still images ({stills}): lifted one by one; --fps N to treat them as a video")
        return Choice("off", None, stills)
    mode = asked or ("offline" if poses.frame_count > 1 else "off")
    if asked is None and mode != "off" and mode not in (found := modes()):
        fallback = "causal" if "causal" in found else "off"
        tell(f"no {mode} temporal model here: lifting the sequence with temporal {fallback}")
        mode = fallback
    if rate is None and mode != "off":
        rate = DEFAULT_FPS
        by = poses.numbered_by  # why the frames were taken for a video, where they may not have been
        video = "" if by is None else f"{poses.frame_count} frames ({by} in sequence): "
        tell(f"{video}assuming {DEFAULT_FPS:g} fps (the input gives no frame rate; set it with --fps)")
    return Choice(mode, rate)


def tracks_of(poses: Poses, choice: Choice) -> tuple[str | None, ...] | None:
    """Each pose's track: the file's, else, for a sequence or a temporal lift, the tracker's
    (repnet.client.tracker); None for one frame or still images lifted alone."""
    if poses.track_id is not None:
        return poses.track_id
    if choice.temporal == "off" and (poses.frame_count < 2 or choice.stills is not None):
        return None
    from repnet.client.tracker import assign_tracks

    numbers = assign_tracks(poses.frame, poses.points, choice.fps or DEFAULT_FPS)
    return tuple(str(n) for n in numbers.tolist())


def batch_of(
    poses: Poses,
    fmt: str,
    threshold: float | None,
    intrinsics: Intrinsics | None,
    choice: Choice,
    tracks: tuple[str | None, ...] | None,
    person_height_m: float | None = None,
) -> Batch:
    """What is sent: the poses with their tracks and frame numbers."""
    frames = None if tracks is None else poses.frame.astype(np.int64)
    tracking = Tracking.of(len(poses.points), choice.temporal, choice.fps, tracks, frames)
    return Batch(poses.points, poses.confidence, fmt, threshold, intrinsics, tracking, person_height_m)


def result_json(result: LiftResult, points: np.ndarray, conf: np.ndarray | None) -> dict[str, Any]:
    """One pose of the output file: its input and every field of the service's reply. A missing
    joint is null in both `keypoints` and `confidence`: NaN, and any non-finite coordinate, which the
    service reads as missing where its confidence is 0 (and refuses elsewhere)."""
    missing = ~np.isfinite(points).all(axis=1)  # (J,)
    keypoints = [None if gone else p.tolist() for p, gone in zip(points, missing, strict=True)]
    confidence = (
        None if conf is None else [None if gone else float(c) for c, gone in zip(conf, missing, strict=True)]
    )
    fields = {name: _json_value(getattr(result, name)) for name in LiftResult.pose_fields()}
    return {"input": {"keypoints": keypoints, "confidence": confidence}, **fields}


def _json_value(value: Any) -> Any:
    """A LiftResult field as JSON: arrays as nested lists, tuples as lists."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    return list(value) if isinstance(value, tuple) else value


def output_rows(results: Sequence[LiftResult], poses: Poses) -> list[dict[str, Any]]:
    """The output file's poses: frame, person (index in its frame), input and reply fields."""
    conf = poses.confidence
    return [
        {
            "frame": int(poses.frame[i]),
            "person": int(poses.person[i]),
            **result_json(r, poses.points[i], None if conf is None else conf[i]),
        }
        for i, r in enumerate(results)
    ]


def output_document(
    results: Sequence[LiftResult], poses: Poses, fmt: str, choice: Choice, skipped: list[dict[str, Any]]
) -> dict[str, Any]:
    """The output file: the model, how the poses were lifted, the joints, the poses, those skipped."""
    return {
        "model_id": results[0].model_id,
        "format": fmt,
        "temporal": choice.temporal,
        "fps": choice.fps,
        "stills": choice.stills,
        "input_joints": list(FORMATS[fmt].joint_names),
        "joints": list(results[0].joints),
        "parents": list(MODEL_PARENTS),
        "poses": output_rows(results, poses),
        "skipped": skipped,
    }


def warn_about(results: Sequence[LiftResult], poses: Poses) -> None:
    """Say on stderr how many poses got a warning, with the first of each kind and where it was."""
    kinds: dict[str, list[int]] = {}
    for i, result in enumerate(results):
        for warning in result.warnings:
            kinds.setdefault(warning.split(" (")[0], []).append(i)
    for kind, where in kinds.items():
        first = where[0]
        message = next(w for w in results[first].warnings if w.startswith(kind))
        say(
            f"warning: {len(where)} of {len(results)} poses: {message} (first: poses[{first}], "
            f"frame {poses.frame[first]}, person {poses.person[first]})"
        )


def lift_poses(
    args: Any, poses: Poses, fmt: str, temporal: str | None, progress_bar: Callable[[int, str], Any]
) -> tuple[Lifted, Choice]:
    """Lift `poses` as `repnet lift` and `repnet video` do, with their shared flags (`args`, see
    repnet.cli.options): through the service at args.url or in this process (args.local), the
    unusable poses skipped (told) or refused (args.strict), in the temporal mode `temporal` (None:
    choose's default), the poses' progress on a `progress_bar(total, unit)`. The output document
    with its results, and the choice of mode and frame rate."""
    remote = (
        None
        if args.local
        else RemoteBackend(args.url, args.timeout, args.batch_size, args.api_key, args.ca_file, args.model)
    )
    original = poses
    try:
        model = None if args.model is None else Path(args.model)  # --local: an ONNX file
        lifter = local_backend(model, args.batch_size) if remote is None else remote
        threshold = args.confidence_threshold
        poses, skipped = usable_poses(poses, fmt, threshold, lifter.limits(), args.strict, say)
        choice = choose(poses, temporal, args.fps, lifter.temporal_modes, say)
        ids = tracks_of(poses, choice)
        batch = batch_of(poses, fmt, threshold, args.intrinsics, choice, ids, args.person_height)
        bar = progress_bar(len(poses.points), "pose")
        try:
            results = lifter.lift_batch(batch, None if bar is None else bar.update)
        finally:
            if bar is not None:
                bar.close()
    finally:
        if remote is not None:
            remote.close()
    out = output_document(results, poses, fmt, choice, [s.to_json(original) for s in skipped])
    warn_about(results, poses)
    return Lifted(out, results, poses), choice


def tell_written(files: Sequence[Path], lifted: Lifted, choice: Choice) -> None:
    """Say on stderr what was lifted and where it was written."""
    n, frames = len(lifted.results), lifted.poses.frame_count
    doc = lifted.document
    tracks = "" if choice.temporal == "off" else f", temporal {choice.temporal} at {choice.fps:g} fps"
    counted = f"{n} pose{'s' * (n != 1)} of {frames} frame{'s' * (frames != 1)}"
    say(
        f"lifted {counted} ({doc['format']}, model {doc['model_id']}{tracks}) -> {', '.join(map(str, files))}"
    )


__all__ = [
    "Choice",
    "LiftClientError",
    "RemoteBackend",
    "batch_of",
    "choose",
    "lift_poses",
    "output_document",
    "output_rows",
    "stills_reason",
    "tell_written",
    "tracks_of",
]
