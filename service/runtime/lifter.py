"""Lifter: owns the onnxruntime session; model-joint ndarrays in, Prediction out."""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import onnxruntime as ort

from repnet.core import geometry
from repnet.core.errors import InvalidKeypoints, ModelLoadError, Violation
from repnet.core.geometry import BoolArray, FloatArray
from repnet.core.inputs import MODEL_ID, MODEL_ID_RULE
from repnet.runtime.session import HasSessionOptions, open_session

log = logging.getLogger(__name__)

INPUTS = ("keypoints_2d", "visibility")
OUTPUTS = ("pose_3d", "camera")
# Optional output (N,) float32 in [0, 1]: a pose score (a density, or a critic) calibrated as a
# percentile among real validation poses; its calibration is the JSON metadata entry
# PLAUSIBILITY_CALIBRATION. Other outputs (a training critic's raw "critic") are not read.
PLAUSIBILITY = "plausibility"
PLAUSIBILITY_CALIBRATION = "plausibility_calibration"
# What a row the model failed on holds, so that the reply of the rest of its run can be derived
# (never sent: the reply marks the row failed).
STAND_IN_CAMERA = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=np.float32)
# The start-up check's bounds for a person: the 3D pose spans this much (mm) along its longest
# axis, and its reprojection misses the input by at most this fraction of the input's spread.
PERSON_EXTENT_MM = (300.0, 5000.0)
MAX_REPROJECTION_SPREAD = 0.25


def model_id_of(metadata: dict[str, str], path: Path) -> str:
    """A model file's id: its metadata model_id, else its file name's stem; ModelLoadError naming the
    file when that id breaks MODEL_ID_RULE."""
    given = metadata.get("model_id")
    model_id = given or path.stem
    if MODEL_ID.fullmatch(model_id) is None:
        where = "its metadata model_id" if given else "its file name (it has no metadata model_id)"
        raise ModelLoadError(f"{path}: the model id {model_id!r} from {where} is not {MODEL_ID_RULE}")
    return model_id


def non_finite_rows(*arrays: np.ndarray) -> BoolArray:
    """(N,) True for each pose with a NaN or infinity in any of the (N, ...) arrays."""
    n = arrays[0].shape[0]
    with np.errstate(over="ignore", invalid="ignore"):  # a NaN or infinity makes its sum one
        if all(math.isfinite(a.sum()) for a in arrays):  # the usual case: one reduction each (an
            return np.zeros(n, bool)  # overflow only takes the long way)
    finite = np.ones(n, bool)
    for a in arrays:
        finite &= np.isfinite(a.reshape(n, math.prod(a.shape[1:]))).all(axis=1)  # N may be 0
    return ~finite


# An absolute path of the machine that built the model (POSIX, two or more parts), e.g. in the
# metadata's train_command: /root/.cache/repnet/runs/s5_r2_limbs/last.pt.
_BUILD_PATH = re.compile(r"(?<![\w.~:/-])/(?:[^\s/;,:'\"=]+/)+[^\s/;,:'\"=]*")


def without_build_paths(text: str) -> str:
    """`text` with each absolute path cut to what says something off the build machine: from its
    last `runs` folder on (runs/s5_r2_limbs/last.pt), else its last part (last.pt)."""

    def cut(match: re.Match[str]) -> str:
        parts = [p for p in match.group(0).split("/") if p]
        if "runs" in parts:
            return "/".join(parts[len(parts) - 1 - parts[::-1].index("runs") :])
        return parts[-1] if parts else match.group(0)

    return _BUILD_PATH.sub(cut, text)


# How a model was trained, in its metadata `training_method` (training.export and repnet adapt write
# it); for the models exported before that entry, by model_id.
TRAINING_METHOD = "training_method"
KNOWN_METHODS = {
    "repnet-h36m-v7": "Supervised on synthetic projections of Human3.6M 3D poses (training subjects S1, "
    "S5-S8; random cameras, with ground-truth and Stacked-Hourglass 2D): every stage's adversarial phase "
    "is empty. The paper's weakly supervised losses (reprojection, camera, WGAN-GP critic with its KCS "
    "path) are used by `repnet adapt`, on a user's own 2D.",
}


def training_method_of(metadata: dict[str, str]) -> str:
    """How a model was trained, from its metadata ("" when it does not say)."""
    return metadata.get(TRAINING_METHOD) or KNOWN_METHODS.get(metadata.get("model_id", ""), "")


@dataclass(frozen=True)
class ModelInfo:
    """What the ONNX metadata says about the model."""

    model_id: str
    skeleton: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    metadata: dict[str, str]  # every custom metadata entry, verbatim

    @property
    def public_metadata(self) -> dict[str, str]:
        """Every metadata entry as GET /v1/model shows it: build paths cut (without_build_paths)."""
        return {key: without_build_paths(value) for key, value in self.metadata.items()}

    @property
    def evaluation(self) -> dict[str, Any]:
        """The evaluation figures embedded at export (empty for an untrained model), build paths cut."""
        try:
            value = json.loads(without_build_paths(self.metadata.get("evaluation", "{}") or "{}"))
        except json.JSONDecodeError:
            return {}
        return value if isinstance(value, dict) else {}

    @property
    def training_method(self) -> str:
        """How the model was trained, in a sentence or two ("" when its metadata does not say)."""
        return training_method_of({**self.metadata, "model_id": self.model_id})

    @property
    def plausibility_calibration(self) -> dict[str, Any] | None:
        """How the model calibrated its plausibility output (metadata JSON), None if it says nothing."""
        try:
            value = json.loads(self.metadata.get(PLAUSIBILITY_CALIBRATION, "null") or "null")
        except json.JSONDecodeError:
            return None
        return value if isinstance(value, dict) else None


@dataclass(frozen=True)
class Prediction:
    """The model's outputs for N poses, and which of them the model failed on."""

    pose_3d: FloatArray  # (N, J, 3) mm, pelvis at origin, template frame
    camera: FloatArray  # (N, 2, 3) weak-perspective K
    # (N,) the model's output was not finite: pose_3d, camera and plausibility hold stand-ins there.
    failed: BoolArray
    plausibility: FloatArray | None = None  # (N,) in [0, 1]; None when the model has no such output

    def __len__(self) -> int:
        return int(self.pose_3d.shape[0])

    def slice(self, start: int, stop: int) -> Prediction:
        """Poses start..stop-1 of this prediction (views, no copy)."""
        plausibility = None if self.plausibility is None else self.plausibility[start:stop]
        return Prediction(
            self.pose_3d[start:stop], self.camera[start:stop], self.failed[start:stop], plausibility
        )

    @classmethod
    def join(cls, parts: Sequence[Prediction]) -> Prediction:
        """The Predictions of consecutive pose ranges as one, in order."""
        if len(parts) == 1:
            return parts[0]
        joined = {f.name: [getattr(p, f.name) for p in parts] for f in fields(cls)}
        columns: dict[str, Any] = {k: None if v[0] is None else np.concatenate(v) for k, v in joined.items()}
        return cls(**columns)  # None: an optional output the model does not have


def _read_info(session: ort.InferenceSession, path: Path) -> ModelInfo:
    meta = dict(session.get_modelmeta().custom_metadata_map)
    try:
        joint_names = tuple(str(n) for n in json.loads(meta["joint_names"]))
        parents = tuple(int(p) for p in json.loads(meta.get("parents", "[]")))
    except (KeyError, ValueError, TypeError) as err:
        raise ModelLoadError(f"{path}: metadata 'joint_names' must be a JSON list of names ({err})") from err
    return ModelInfo(
        model_id=model_id_of(meta, path),
        skeleton=meta.get("skeleton", ""),
        joint_names=joint_names,
        parents=parents,
        metadata=meta,
    )


def _check_names(session: ort.InferenceSession, path: Path) -> None:
    """Checked before the metadata, so that a model of another kind is named as such."""
    inputs = [i.name for i in session.get_inputs()]
    outputs = [o.name for o in session.get_outputs()]
    if set(inputs) != set(INPUTS) or not set(OUTPUTS) <= set(outputs):
        raise ModelLoadError(
            f"{path}: expected inputs {list(INPUTS)} and outputs {list(OUTPUTS)}, "
            f"got inputs {inputs} and outputs {outputs}"
        )


def _check_contract(session: ort.InferenceSession, info: ModelInfo, path: Path) -> None:
    inputs = {i.name: i.shape for i in session.get_inputs()}
    outputs = {o.name: o.shape for o in session.get_outputs()}
    joints = len(info.joint_names)
    if inputs["keypoints_2d"][1:] != [joints, 2] or outputs["pose_3d"][1:] != [joints, 3]:
        raise ModelLoadError(
            f"{path}: expected keypoints_2d (N, {joints}, 2) and pose_3d (N, {joints}, 3) for the "
            f"{joints} joints in its metadata, got {inputs['keypoints_2d']} and {outputs['pose_3d']}"
        )
    if PLAUSIBILITY in outputs and len(outputs[PLAUSIBILITY]) != 1:
        raise ModelLoadError(
            f"{path}: expected output {PLAUSIBILITY} of shape (N,), got {outputs[PLAUSIBILITY]}"
        )


class ModelInputLike(Protocol):
    """What Lifter.run reads of a keypoints.ModelInput (keypoints imports nothing of the lifter)."""

    @property
    def keypoints_2d(self) -> np.ndarray:
        """(N, J, 2) px."""

    @property
    def visible(self) -> np.ndarray:
        """(N, J) bool."""


class Lifter:
    """Runs the RepNet ONNX model; safe to call from many threads at once."""

    def __init__(self, session: ort.InferenceSession, path: Path) -> None:
        self.session = session
        self.path = path
        _check_names(session, path)
        self.info = _read_info(session, path)
        _check_contract(session, self.info, path)
        self.has_plausibility = PLAUSIBILITY in {o.name for o in session.get_outputs()}
        self._outputs = [*OUTPUTS, PLAUSIBILITY] if self.has_plausibility else list(OUTPUTS)

    @classmethod
    def load(cls, path: Path, settings: HasSessionOptions | None = None) -> Lifter:
        """Open the model at `path` with the session options of `settings` (threads and spinning;
        default SessionOptions()); raise ModelLoadError saying what is wrong with the model."""
        lifter = cls(open_session(path, settings), path)
        log.info("loaded model %s (%s) from %s", lifter.info.model_id, lifter.info.skeleton, path)
        return lifter

    def check_outputs(self, keypoints_2d: np.ndarray, visibility: np.ndarray) -> None:
        """Lift known (N, J, 2) poses of people; ModelLoadError if the outputs are not finite or not
        a person that explains its input. A model with broken weights loads without complaint."""
        where = f"{self.path}: the model fails its check on {len(keypoints_2d)} known poses"
        try:
            prediction = self.lift(keypoints_2d, visibility)
        except Exception as err:  # onnxruntime's own untyped errors: a graph that loads but cannot run
            message = " ".join(str(err).split())  # one line
            raise ModelLoadError(f"{where}: the run failed: {message}") from None
        reprojection = geometry.reproject(prediction.camera, prediction.pose_3d, keypoints_2d, visibility)
        error = geometry.reprojection_error(reprojection, keypoints_2d, visibility)  # (N,) px
        if (failed := prediction.failed | ~np.isfinite(error)).any():
            raise ModelLoadError(f"{where}: non-finite output for poses {np.flatnonzero(failed).tolist()}")
        extent = np.ptp(prediction.pose_3d, axis=1).max(axis=1)  # (N,) mm
        low, high = PERSON_EXTENT_MM
        if not ((extent >= low) & (extent <= high)).all():
            found = ", ".join(f"{e:.0f}" for e in extent)
            raise ModelLoadError(f"{where}: pose_3d spans {found} mm, a person spans {low:.0f} to {high:.0f}")
        spread = geometry.visible_spread(keypoints_2d, visibility)  # (N,) px
        if not (error <= MAX_REPROJECTION_SPREAD * spread).all():
            found = ", ".join(f"{e:.1f}" for e in error)
            raise ModelLoadError(
                f"{where}: reprojection errors {found} px, more than {MAX_REPROJECTION_SPREAD:g} of "
                f"the inputs' spread ({', '.join(f'{s:.0f}' for s in spread)} px)"
            )

    @property
    def num_joints(self) -> int:
        """J, the number of model joints."""
        return len(self.info.joint_names)

    def run(self, parts: Sequence[ModelInputLike]) -> Prediction:
        """Lift the poses of several requests' inputs (each with keypoints_2d and visible) in one run."""
        keypoints = np.concatenate([p.keypoints_2d for p in parts])  # (N, J, 2)
        return self.lift(keypoints, np.concatenate([p.visible for p in parts]))

    def lift(self, keypoints_2d: np.ndarray, visibility: np.ndarray) -> Prediction:
        """Lift (N, J, 2) pixel keypoints with (N, J) visibility (bool or 0/1) to a Prediction.

        Coordinates of joints that are not visible are ignored, whatever they hold.
        """
        j = self.num_joints
        if keypoints_2d.ndim != 3 or keypoints_2d.shape[1:] != (j, 2) or keypoints_2d.shape[0] == 0:
            raise InvalidKeypoints(
                [Violation("keypoints_2d", f"expected shape (N, {j}, 2), got {keypoints_2d.shape}", "shape")]
            )
        if visibility.shape != keypoints_2d.shape[:2]:
            raise InvalidKeypoints(
                [
                    Violation(
                        "visibility",
                        f"expected shape {keypoints_2d.shape[:2]}, got {visibility.shape}",
                        "shape",
                    )
                ]
            )
        visible = visibility.astype(bool)
        points = np.where(visible[..., None], keypoints_2d, 0.0).astype(np.float32, copy=False)  # (N, J, 2)
        if not np.isfinite(points).all():
            raise InvalidKeypoints(
                [Violation("keypoints_2d", "visible coordinates must be finite", "non_finite")]
            )
        pose_3d, camera, *plausibility = self.session.run(
            self._outputs, {"keypoints_2d": points, "visibility": visible.astype(np.float32)}
        )
        failed = non_finite_rows(pose_3d, camera, *plausibility)  # (N,)
        if failed.any():
            # Stand-ins for the failed rows (the camera geometry cannot take NaN: an SVD of NaN does
            # not converge), so that the other poses of the run are still answered.
            pose_3d = np.where(failed[:, None, None], 0.0, pose_3d).astype(np.float32)
            camera = np.where(failed[:, None, None], STAND_IN_CAMERA, camera).astype(np.float32)
            plausibility = [np.where(failed, 0.0, p).astype(np.float32) for p in plausibility]
        return Prediction(pose_3d, camera, failed, plausibility[0] if plausibility else None)
