"""The input's shapes: a detector pose as a transport received it (PoseInput), the limits it is held to, the
model's input the rules make of it (ModelInput, Prepared), and the example person every model is checked
on."""

from __future__ import annotations

import re
from dataclasses import dataclass, fields

import numpy as np
import numpy.typing as npt

from repnet.core.errors import InvalidKeypoints, Violation
from repnet.core.formats import (
    DEFAULT_FORMAT,
)
from repnet.core.geometry import BoolArray, FloatArray

# Below this spread (px) the visible joints count as one point: the input cannot be normalised.
# A model id (a model file's metadata model_id, else its file name's stem): what a request's `model`
# names and what logs, metrics and /v1/models show, so letters, digits, `.`, `_` and `-` only.
MODEL_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
MODEL_ID_RULE = "1-64 letters, digits, '.', '_' or '-', starting with a letter or digit"
MIN_SPREAD_PX = 1e-3


Points = npt.NDArray[np.floating]


# A person standing, h36m17 px: the OpenAPI example, the page's first example and the start-up check.
EXAMPLE_KEYPOINTS: list[list[float]] = [
    [512.0, 515.0],
    [483.5, 516.3],
    [471.0, 624.2],
    [481.3, 730.0],
    [541.3, 513.7],
    [550.6, 628.1],
    [561.9, 735.4],
    [514.8, 455.4],
    [516.4, 390.7],
    [511.1, 363.4],
    [516.6, 334.0],
    [550.1, 402.1],
    [570.4, 466.5],
    [573.0, 525.4],
    [482.4, 405.9],
    [458.7, 469.6],
    [454.4, 527.5],
]


@dataclass(frozen=True)
class Limits:
    """The documented input limits. These defaults are the service's (Settings takes its defaults
    from here; the server's limits_of builds one from Settings); `repnet lift --local` and `repnet
    adapt` use them as they are."""

    max_request_poses: int = 1024
    min_visible_joints: int = 6
    confidence_threshold: float = 0.2  # default when a request does not set its own
    max_coordinate: float = 1e6  # px
    max_temporal_poses: int = 6000  # most poses of a request with temporal causal or offline


@dataclass(frozen=True)
class PoseInput:
    """One detector pose as a transport received it."""

    # (K, 2) px in the wire's precision (JSON float64, proto float32); rows of absent joints are ignored
    points: Points
    present: BoolArray  # (K,) False where the request marks the joint missing (JSON null)
    confidence: Points | None = None  # (K,) in [0, 1], or None
    format: str = DEFAULT_FORMAT
    # (fx, fy, cx, cy) px of the pinhole camera that saw the pose, if the client knows it.
    intrinsics: tuple[float, float, float, float] | None = None
    # The pose's own confidence threshold, checked by check_threshold (a stream frame has one);
    # None: the request's, else the server default.
    confidence_threshold: float | None = None
    # The person's skeleton height in metres (geometry.skeleton_height), if known: sets the depth of
    # root_camera_m; None: the answer's own size (the model's template) is used.
    person_height_m: float | None = None


@dataclass(frozen=True)
class ModelInput:
    """N poses in the model's joints, ready for Lifter.lift, with what the reply needs of their input."""

    keypoints_2d: FloatArray  # (N, 17, 2) px; 0 where not visible
    visible: BoolArray  # (N, 17)
    derived: BoolArray  # (N, 17) the joint is the midpoint of two detector joints
    imputed: BoolArray  # (N, 17) no visible source: the model fills the joint in
    format_index: npt.NDArray[np.int8]  # (N,) the pose's format, an index into formats.FORMAT_NAMES
    nose_height: npt.NDArray[np.float32]  # (N,) formats.nose_height of its 17 input joints, or NaN
    intrinsics: FloatArray  # (N, 4) fx, fy, cx, cy px of the pose's camera; NaN where not given
    zeroed: npt.NDArray[np.int16]  # (N,) joints at exactly (0, 0) without confidence, read as missing
    person_height_m: FloatArray  # (N,) the person's skeleton height in m; NaN where not given

    def __len__(self) -> int:
        return int(self.keypoints_2d.shape[0])

    def slice(self, start: int, stop: int) -> ModelInput:
        """Poses start..stop-1 (views)."""
        return ModelInput(*(getattr(self, name)[start:stop] for name in _INPUT_FIELDS))


_INPUT_FIELDS = tuple(f.name for f in fields(ModelInput))


@dataclass(frozen=True)
class Prepared:
    """A request's poses after the input rules: the valid ones as one ModelInput, in request order,
    and per pose what is wrong with it (fields named within the pose, e.g. keypoints[4])."""

    inputs: ModelInput  # the valid poses
    violations: tuple[tuple[Violation, ...], ...]  # per pose of the request; () for a valid one

    def check(self) -> ModelInput:
        """The model input when every pose is valid; else InvalidKeypoints listing every violation
        of every pose, named within the request: poses[2].keypoints[4]."""
        named = [v.within(f"poses[{i}]") for i, found in enumerate(self.violations) for v in found]
        if named:
            raise InvalidKeypoints(named)
        return self.inputs
