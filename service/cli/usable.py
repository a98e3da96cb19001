"""`repnet lift`'s poses that the service takes: the core's input rules run before lifting, so a file
with some unusable poses (a COCO annotation file's people of `num_keypoints: 0`, a detection with
too few joints) still lifts; the others are skipped and reported by the file's own identifiers, or,
with --strict, refuse the file as the service would."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from repnet.client.result import LiftClientError
from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.inputs import Limits, PoseInput
from repnet.core.keypoints import check_threshold, prepare_poses
from repnet.io.poses import Poses

SHOWN = 5  # skipped poses named on stderr; the output lists them all


def pose_inputs(
    points: np.ndarray,
    conf: np.ndarray | None,
    fmt: str,
    rows: Sequence[int],
    intrinsics: Any = None,
    person_height_m: float | None = None,
) -> list[PoseInput]:
    """Poses `rows` of (N, J, 2) points (NaN where missing) as the service receives them."""
    return [
        PoseInput(
            points[i],
            ~np.isnan(points[i]).any(axis=1),
            None if conf is None else conf[i],
            fmt,
            intrinsics,
            person_height_m=person_height_m,
        )
        for i in rows
    ]


@dataclass(frozen=True)
class Skipped:
    """A pose of the file that breaks an input rule."""

    index: int  # in the file's poses
    where: str  # the file's identifiers: frame, person, and the file's own label if it has one
    violations: tuple[Violation, ...]  # named within the pose: keypoints[4]

    def to_json(self, poses: Poses) -> dict[str, Any]:
        """The entry of the output's `skipped`."""
        entry: dict[str, Any] = {
            "frame": int(poses.frame[self.index]),
            "person": int(poses.person[self.index]),
        }
        if poses.label is not None:
            entry["source"] = poses.label[self.index]
        entry["errors"] = [{"field": v.field, "reason": v.reason, "code": v.code} for v in self.violations]
        return entry


def where(poses: Poses, i: int) -> str:
    """Pose i as the file knows it: `frame 3, person 1 (image_id 397133, id 1768)`."""
    label = "" if poses.label is None else f" ({poses.label[i]})"
    return f"frame {int(poses.frame[i])}, person {int(poses.person[i])}{label}"


def unusable(poses: Poses, fmt: str, threshold: float | None, limits: Limits) -> list[Skipped]:
    """The poses the service would refuse, by the rules of each pose (the request's own rules,
    its threshold and size, are the lift's to report)."""
    try:
        check_threshold(threshold, limits)
    except InvalidKeypoints:
        return []
    rows = range(len(poses.points))
    prepared = prepare_poses(pose_inputs(poses.points, poses.confidence, fmt, rows), limits, threshold)
    return [Skipped(i, where(poses, i), found) for i, found in enumerate(prepared.violations) if found]


def keep(poses: Poses, skipped: Sequence[Skipped]) -> Poses:
    """The poses without the skipped ones."""
    kept = np.setdiff1d(np.arange(len(poses.points)), [s.index for s in skipped])
    return replace(
        poses,
        points=poses.points[kept],
        confidence=None if poses.confidence is None else poses.confidence[kept],
        frame=poses.frame[kept],
        person=poses.person[kept],
        track_id=None if poses.track_id is None else tuple(poses.track_id[i] for i in kept),
        label=None if poses.label is None else tuple(poses.label[i] for i in kept),
    )


def describe(skipped: Sequence[Skipped], total: int) -> list[str]:
    """Lines for stderr: how many were skipped, and the first SHOWN of them with their reasons."""
    lines = [
        f"skipped {len(skipped)} of {total} poses that break the input rules (--strict refuses the file):"
    ]
    for s in skipped[:SHOWN]:
        first = s.violations[0]
        more = f" (and {len(s.violations) - 1} more)" if len(s.violations) > 1 else ""
        lines.append(f"  {s.where}: {first.message}{more}")
    if len(skipped) > SHOWN:
        lines.append(f"  ... and {len(skipped) - SHOWN} more (all in the output's `skipped`)")
    return lines


def refusal(skipped: Sequence[Skipped], total: int) -> LiftClientError:
    """--strict: the file refused, its unusable poses named as describe names them."""
    found = describe(skipped, total)[1:]
    return LiftClientError(
        f"{len(skipped)} of {total} poses break the input rules (without --strict they are skipped):\n"
        + "\n".join(found),
        "rejected",
    )


def usable_poses(
    poses: Poses, fmt: str, threshold: float | None, limits: Limits, strict: bool, tell: Any
) -> tuple[Poses, list[Skipped]]:
    """The poses to lift and the ones skipped (told on stderr); with `strict`, the file refused
    (LiftClientError) when any breaks a rule; when none is left, a LiftClientError saying why."""
    skipped = unusable(poses, fmt, threshold, limits)
    if not skipped:
        return poses, []
    total = len(poses.points)
    if strict:
        raise refusal(skipped, total)
    if len(skipped) == total:
        found = describe(skipped, total)[1:]
        raise LiftClientError(f"none of the {total} poses can be lifted:\n" + "\n".join(found), "rejected")
    for line in describe(skipped, total):
        tell(line)
    return keep(poses, skipped), skipped
