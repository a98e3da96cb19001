"""What the clients give back: LiftResult (one lifted pose), LiftClientError, and the shapes both
transports' answers are read into."""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from repnet.core.fields import FLAGS, MATRICES

FloatArray = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]
ArrayLike = npt.ArrayLike


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

    def renumbered(self, positions: Sequence[int]) -> LiftClientError:
        """The same error about a request that held the poses at `positions` of the caller's: its
        pose indices (poses[i] in the message and fields, `pose` of the details) made the caller's."""
        details = []
        for item in self.details:
            field, pose = item.get("field"), item.get("pose")
            renamed = {"field": renumber_poses(field, positions)} if isinstance(field, str) else {}
            moved = {"pose": positions[pose]} if isinstance(pose, int) and 0 <= pose < len(positions) else {}
            details.append({**item, **renamed, **moved})
        return LiftClientError(renumber_poses(self.message, positions), self.status, details)


def renumber_poses(message: str, positions: Sequence[int]) -> str:
    """Rename poses[i] to poses[positions[i]] in a message about one request of a larger batch."""

    def rename(match: re.Match[str]) -> str:
        i = int(match.group(1))
        return f"poses[{positions[i]}]" if i < len(positions) else match.group(0)

    return re.sub(r"poses\[(\d+)\]", rename, message)


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
    root_camera_m: FloatArray | None = None  # (3,) m, the root in the camera frame; None without intrinsics
    root_height_source: str | None = None  # "given" or "template": whose size set the root's depth

    @classmethod
    def pose_fields(cls) -> tuple[str, ...]:
        """The names of the reply's fields a LiftResult carries, in reply order (not joints, model_id)."""
        return tuple(f.name for f in fields(cls) if f.name not in ("joints", "model_id"))

    @classmethod
    def from_fields(cls, get: Callable[[str], Any], joints: Sequence[str], model_id: str) -> LiftResult:
        """Build from one pose of an answer: `get(name)` gives a field as JSON lists (HTTP) or a
        flat repeated field (gRPC)."""
        arrays: dict[str, Any] = {k: np.asarray(get(k), np.float32).reshape(s) for k, s in MATRICES.items()}
        flags: dict[str, Any] = {k: np.asarray(get(k), bool) for k in FLAGS}
        try:
            plausibility = get("plausibility")
        except KeyError:  # a server from before the field: the same as a model without the output
            plausibility = None
        warnings, temporal, track_id = (_optional(get, name) for name in ("warnings", "temporal", "track_id"))
        root, source = _optional(get, "root_camera_m"), _optional(get, "root_height_source")
        return cls(
            **arrays,
            **flags,
            scale=float(get("scale")),
            joints=tuple(joints),
            model_id=model_id,
            reprojection_error_px=float(get("reprojection_error_px")),
            plausibility=None if plausibility is None else float(plausibility),
            warnings=tuple(str(w) for w in warnings or ()),
            temporal=bool(temporal),
            track_id=str(track_id) if track_id else None,
            root_camera_m=np.asarray(root, np.float32).reshape(3) if root else None,
            root_height_source=str(source) if source else None,
        )


def _optional(get: Callable[[str], Any], name: str) -> Any:
    """A field a server from before it does not send (KeyError): None."""
    try:
        return get(name)
    except KeyError:
        return None


class LiftInputError(LiftClientError, ValueError):
    """Arguments a client cannot send (the shape of the keypoints, the tracks): raised before any
    request, with the status 422 the service would answer. A ValueError too, as before."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(reason, 422, [{"field": field, "reason": reason, "code": "client_argument"}])


def as_poses(
    keypoints: ArrayLike, confidence: ArrayLike | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, J, 2) float points (NaN = missing joint) and (N, J) confidence or None. (N, J, 3) rows
    [x, y, confidence], as detectors write them, give the confidence (as over HTTP)."""
    try:
        points = np.asarray(keypoints, dtype=np.float64)
        conf = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise LiftInputError("keypoints", f"expected numbers: {str(err)[:100]}") from err
    if points.ndim == 3 and points.shape[-1] == 3:
        if conf is not None:
            raise LiftInputError(
                "confidence",
                "give the confidence either as the third value of each joint or as `confidence`, not both",
            )
        points, conf = points[..., :2], points[..., 2]
    if points.ndim != 3 or points.shape[-1] != 2:
        hint = " (MediaPipe [x, y, z, visibility]: multiply x, y by the image size, pass [x, y, visibility])"
        raise LiftInputError(
            "keypoints",
            "expected keypoints of shape (N, J, 2) or (N, J, 3) [x, y, "
            f"confidence], got {points.shape}{hint if points.shape[-1:] == (4,) else ''}",
        )
    if conf is not None and conf.shape != points.shape[:2]:
        reason = f"expected confidence of shape {points.shape[:2]}, got {conf.shape}"
        raise LiftInputError("confidence", reason)
    return points, conf
