"""The reply: its fields (core.fields) computed from a Prediction and its input, as JSON rows and proto."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from repnet.core import geometry
from repnet.core.errors import ModelOutputError
from repnet.core.fields import NAMES
from repnet.core.geometry import BoolArray, FloatArray
from repnet.core.inputs import ModelInput
from repnet.core.lookalike import format_warnings
from repnet.runtime.lifter import Prediction, non_finite_rows


@dataclass(frozen=True)
class Replies:
    """The replies of N poses: per field of FIELDS an (N, *shape) array (warnings: N lists of
    strings; plausibility: None for a model without it), and the poses that failed."""

    columns: dict[str, Any]
    # (N,) the model's output, or the geometry derived from it, is not finite: no reply, a server
    # fault (ModelOutputError) for these poses alone.
    failed: BoolArray

    def __post_init__(self) -> None:
        if tuple(self.columns) != NAMES:
            raise ValueError(f"expected the reply fields {list(NAMES)}, got {list(self.columns)}")

    def __len__(self) -> int:
        return len(self.failed)

    def slice(self, start: int, stop: int) -> Replies:
        """The replies of poses start..stop-1 (views of the arrays)."""
        columns = {k: None if v is None else v[start:stop] for k, v in self.columns.items()}
        return Replies(columns, self.failed[start:stop])

    @classmethod
    def join(cls, parts: Sequence[Replies]) -> Replies:
        """The replies of consecutive poses as one."""
        if len(parts) == 1:
            return parts[0]
        columns: dict[str, Any] = {}
        for name, first in parts[0].columns.items():
            if first is None:
                columns[name] = None
            elif isinstance(first, np.ndarray):
                columns[name] = np.concatenate([p.columns[name] for p in parts])
            else:
                columns[name] = [item for p in parts for item in p.columns[name]]
        return cls(columns, np.concatenate([p.failed for p in parts]))

    def check(self) -> Replies:
        """These replies when no pose failed; else ModelOutputError naming the poses that did."""
        if self.failed.any():
            raise ModelOutputError(np.flatnonzero(self.failed).tolist())
        return self

    def _lists(self, flat: bool) -> dict[str, list[Any]]:
        """Every field as one Python list item per pose: a few ndarray.tolist calls for all poses
        instead of several per pose (tolist on float32 gives the same floats as converting to float64
        first). `flat`: each pose's matrices as one flat list, as proto carries them."""
        n = len(self)
        lists: dict[str, list[Any]] = {}
        for name, value in self.columns.items():
            if value is None:
                lists[name] = [None] * n  # null in JSON, unset in proto
            elif isinstance(value, np.ndarray):
                lists[name] = (value.reshape(n, -1) if flat and value.ndim > 2 else value).tolist()
            else:
                lists[name] = list(value)
        return lists

    def to_json(self) -> list[dict[str, Any]]:
        """One JSON-ready dict per pose (HTTP, the CLI)."""
        lists = self._lists(flat=False)
        return [{name: values[i] for name, values in lists.items()} for i in range(len(self))]

    def proto_fields(self) -> list[dict[str, Any]]:
        """Per pose, the fields of its proto PoseResult as keyword arguments (None: unset). gRPC
        builds each reply once, in the message that carries it: LiftResponse(poses=...),
        LiftFrameResult(pose=...), instead of a PoseResult copied into it."""
        lists = self._lists(flat=True)
        return [{k: v[i] for k, v in lists.items()} for i in range(len(self))]


@dataclass(frozen=True)
class TemporalRows:
    """What a temporal model answered for some poses of a request (repnet.runtime.plans)."""

    rows: npt.NDArray[np.int64]  # (n,) the poses, rows of the request's inputs
    pose_camera: FloatArray  # (n, J, 3) their pose in the camera's orientation (no ray turn), mm
    failed: BoolArray  # (n,) the model's answer is not finite

    @classmethod
    def none(cls) -> TemporalRows:
        """No temporal answer."""
        return cls(np.zeros(0, np.int64), np.zeros((0, 17, 3), np.float32), np.zeros(0, bool))


def build_replies(
    inputs: ModelInput,
    prediction: Prediction,
    temporal: TemporalRows | None = None,
    track_ids: list[str | None] | None = None,
    rotation: FloatArray | None = None,
) -> Replies:
    """Every reply field of the poses `inputs` from their `prediction`: the camera geometry
    (computed here only), the input's joint flags and the warnings. A pose whose geometry is not
    finite (a finite but absurd model output) fails like one the model failed on.

    temporal -- the temporal answers of tracked poses: their pose_3d_camera, with pose_3d that pose
    turned back by the camera rotation (so K, pose_3d and the reprojection stay one answer);
    track_ids -- each pose's track (None: untracked)."""
    camera, pose_3d = prediction.camera, prediction.pose_3d
    points, visible = inputs.keypoints_2d, inputs.visible
    temporal = TemporalRows.none() if temporal is None else temporal
    failed = prediction.failed.copy()
    with np.errstate(over="ignore", invalid="ignore"):  # what is not finite fails its pose below
        rotation = geometry.camera_rotation(camera) if rotation is None else rotation  # (N, 3, 3)
        if len(temporal.rows):  # pose_camera = pose_3d R^T, so pose_3d = pose_camera R
            pose_3d = pose_3d.copy()
            pose_3d[temporal.rows] = temporal.pose_camera @ rotation[temporal.rows]
            failed[temporal.rows] |= temporal.failed
        stats = geometry.visible_stats(points, visible)  # the input's mean and spread, read twice
        reprojection = geometry.reproject(camera, pose_3d, points, visible, stats)  # (N, J, 2) px
        error = geometry.reprojection_error(reprojection, points, visible)  # (N,) px
        pose_3d_camera = geometry.rotate_to_camera(pose_3d, camera_orientation(inputs, rotation))
    columns = {
        "pose_3d": pose_3d,
        "pose_3d_camera": pose_3d_camera,
        "camera": camera,
        "scale": geometry.camera_scale(camera),
        "rotation": rotation,
        "reprojection": reprojection,
        "reprojection_error_px": error,
        "visible": visible,
        "imputed": inputs.imputed,
        "derived": inputs.derived,
        "plausibility": prediction.plausibility,
        "warnings": _warnings(inputs, error, prediction.plausibility, stats[1]),
        "temporal": _marked(len(inputs), temporal.rows),
        "track_id": [None] * len(inputs) if track_ids is None else list(track_ids),
        **root_columns(inputs, pose_3d_camera),
    }
    return Replies(columns, failed | non_finite_rows(rotation, reprojection, error))


def _marked(n: int, rows: np.ndarray) -> BoolArray:
    """(n,) True at `rows`."""
    found = np.zeros(n, bool)
    found[rows] = True
    return found


# A pose whose plausibility is below IMPLAUSIBLE_BELOW gets a warning. It is about the 1st percentile
# of the bundled model's answers to Human3.6M validation poses with ground-truth 2D (0.009 on 4,000
# of them; `python -m bench.plausibility_rank`, docs/RESULTS.md): 1.3 % of the answers to that
# rightly read 2D are warned, 5.7 % with 20 px of noise, 31 % with 40 px, 2.9 % of SH detections'.
IMPLAUSIBLE_BELOW = 0.01


def _warnings(
    inputs: ModelInput, error: FloatArray, plausibility: FloatArray | None, spread: np.ndarray
) -> list[list[str]]:
    """Per pose, why its answer may be wrong: joints read as missing at (0, 0), a format mix-up, else
    an implausible 3D pose (a mix-up's answer mostly is: its warning names the likelier cause).
    `spread`: each input's visible spread (px)."""
    out = format_warnings(inputs, error, plausibility, spread)
    if plausibility is not None:
        for i in np.flatnonzero(plausibility < IMPLAUSIBLE_BELOW).tolist():  # NaN: False
            if out[i]:
                continue
            out[i].append(
                f"plausibility: the 3D pose looks implausible (plausibility {float(plausibility[i]):.3g} < "
                f"{IMPLAUSIBLE_BELOW:g}, below 99 % of the answers to real people's 2D): check the "
                "format and the keypoints"
            )
    for i in np.flatnonzero(inputs.zeroed).tolist():
        count = int(inputs.zeroed[i])
        out[i].insert(
            0,
            f"keypoints: {count} joint{'s' if count > 1 else ''} at exactly (0, 0) without "
            "confidence counted as missing (detectors write 0, 0 for a joint they did not find); "
            "send null for a missing joint, or a confidence per joint",
        )
    return out


def camera_orientation(inputs: ModelInput, rotation: FloatArray) -> FloatArray:
    """(N, 3, 3) each pose's orientation in the camera frame: the camera rotation R, turned along the
    ray from the camera to the person where the pose's intrinsics are given (geometry.ray_rotation)."""
    given = np.flatnonzero(~np.isnan(inputs.intrinsics[:, 0]))
    if not len(given):
        return rotation
    k = inputs.intrinsics[given]
    ray = geometry.ray_rotation(inputs.keypoints_2d[given], inputs.visible[given], k[:, :2], k[:, 2:])
    turned: FloatArray = rotation.copy()
    turned[given] = ray @ rotation[given]
    return turned


def root_columns(inputs: ModelInput, pose_3d_camera: FloatArray) -> dict[str, list[Any]]:
    """root_camera_m and root_height_source of each pose: None without intrinsics (or where the root
    cannot be placed in front of the camera). The answer is scaled to the person's given skeleton
    height, else kept at its own (the template's) size, then placed by geometry.root_translation."""
    n = len(inputs)
    roots: list[Any] = [None] * n
    sources: list[Any] = [None] * n
    given = np.flatnonzero(~np.isnan(inputs.intrinsics[:, 0]))
    if not len(given):
        return {"root_camera_m": roots, "root_height_source": sources}
    pose = pose_3d_camera[given].astype(np.float64)  # (n, J, 3) mm
    height_mm = 1000.0 * inputs.person_height_m[given].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        size = np.where(np.isnan(height_mm), 1.0, height_mm / geometry.skeleton_height(pose))
        points, visible, camera = inputs.keypoints_2d[given], inputs.visible[given], inputs.intrinsics[given]
        root = geometry.root_translation(points, visible, size[:, None, None] * pose, camera)
    placed = np.isfinite(root).all(axis=1) & (root[:, 2] > 0)
    for k, i in enumerate(given.tolist()):
        if placed[k]:
            roots[i] = (root[k] / 1000.0).tolist()
            sources[i] = "template" if np.isnan(height_mm[k]) else "given"
    return {"root_camera_m": roots, "root_height_source": sources}
